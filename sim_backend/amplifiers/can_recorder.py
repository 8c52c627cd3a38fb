"""The data recorder of the simulated CAN amplifier (frames REC_CTRL, REC_READ, REC_STATUS,
REC_DATA of ``drivers/afm_amplifier.dbc``), sans-I/O.

Armed (REC_CTRL arm: axes, signals, points, divider), it starts with the stream's clock: at
the tick of the first sample played after arming (for a fresh stream its sample 0 at t0).
Point k is taken at t0 + k·divider/rate: the output voltage in force then (stream sample
k·divider) and the scanner's position sensor at that instant (the response to the samples
before it; without a sensor in the sink there is no position and it is sent as 0) and, with
SIGNALS bit 2, the piezo voltage then (the monitor of the output stage: the scanner's
amplifier stage output, after its bandwidth and slew; without a sink the voltage in force).
It holds
``CAPACITY`` points per signal; REC_READ asks for a range of them back. An arm for more
points (up to :data:`MAX_POINTS`, what REC_CTRL's POINTS carries) records into a ring: the
last ``CAPACITY`` points are kept, and a point must be read back (while the recorder records)
before ``CAPACITY`` more are taken (:meth:`TickRecorder.held`).
"""
from __future__ import annotations

import enum
import math
from collections.abc import Callable
from typing import Any

import numpy as np

CAPACITY = 8192
#: the most points one arm takes (REC_CTRL POINTS, 16 bits): beyond CAPACITY, a ring
MAX_POINTS = 0xFFFF


class RecState(enum.IntEnum):
    IDLE = 0
    ARMED = 1
    RECORDING = 2
    DONE = 3
    FAULT = 4


class TickRecorder:
    """``TickRecorder(sensor)``: ``sensor(t0_s, period_s, n)`` is a capture of the sink's
    position sensor or None."""

    def __init__(self, sensor: Callable[[float, float, int], Any]) -> None:
        self.sensor = sensor
        self.state = RecState.IDLE
        self.axes_mask, self.signals, self.points, self.divider = 0, 0, 0, 1
        self.t0_s, self.period_s = 0.0, 0.0
        self.capture: Any = None
        self._held = np.zeros(3)
        self._volts = np.zeros((0, 3))
        self._filled = 0

    def arm(self, axes_mask: int, signals: int, points: int, divider: int) -> int:
        """Returns 0, or the DETAIL of ERROR 6: 1 points, 2 divider, 3 axes/signals."""
        if not 1 <= points <= MAX_POINTS:
            return 1
        if divider < 1:
            return 2
        if not axes_mask or not signals:
            return 3
        if self.capture is not None:
            self.capture.cancel()
        self.axes_mask, self.signals, self.points, self.divider = axes_mask, signals, points, divider
        self.state, self._filled, self.capture = RecState.ARMED, 0, None
        return 0

    def stop(self) -> None:
        if self.capture is not None:
            self.capture.cancel()
        self.state = RecState.DONE if self.state is RecState.RECORDING else RecState.IDLE

    def played(self, values: tuple[float, float, float], t_s: float, rate_Hz: float) -> None:
        """A stream sample played at its tick ``t_s``; an armed recorder starts with it."""
        if self.state is RecState.ARMED:
            self.t0_s, self.period_s = t_s, self.divider / rate_Hz
            self._volts, self._filled = np.zeros((self.points, 3)), 0
            self.capture = self.sensor(t_s, self.period_s, self.points) if self.signals & 5 else None
            self.state = RecState.RECORDING
        self._fill(t_s, strict=True)
        self._held = np.asarray(values, dtype=np.float64)

    def sync(self, now_s: float) -> None:
        """Points due by ``now_s`` take the output in force; the state says when all are in."""
        self._fill(now_s, strict=False)
        if self.state is RecState.RECORDING and self.count() >= self.points:
            self.state = RecState.DONE

    def _fill(self, t_s: float, strict: bool) -> None:
        if self.state is not RecState.RECORDING or self._filled >= self.points:
            return
        x = (t_s - self.t0_s) / self.period_s
        last = math.ceil(x - 1e-9) - 1 if strict else math.floor(x + 1e-9)
        upto = min(last + 1, self.points)
        if upto > self._filled:
            self._volts[self._filled:upto] = self._held
            self._filled = upto

    def count(self) -> int:
        if self.state in (RecState.IDLE, RecState.ARMED):
            return 0
        n = self._filled
        if self.capture is not None:
            n = min(n, self.capture.count)
        return n

    def held(self, first: int, count: int) -> int:
        """0 when points ``first`` .. ``first + count - 1`` can be sent back, else the DETAIL
        of ERROR 6: 4 not recorded yet, 5 overwritten (more than CAPACITY points ago)."""
        if self.state is RecState.IDLE or first + count > self.count():
            return 4
        if first < self.count() - CAPACITY:
            return 5
        return 0

    def point(self, k: int, axis: int) -> tuple[float, float, float]:
        """(position [nm], voltage [V], piezo voltage [V]) of point ``k`` on axis index
        ``axis``; a signal not recorded reads 0."""
        y = float(self.capture.y_nm[k, axis]) if self.capture is not None and self.signals & 1 else 0.0
        u = float(self._volts[k, axis]) if self.signals & 2 else 0.0
        v = 0.0
        if self.signals & 4:
            v = float(self.capture.v_V[k, axis]) if self.capture is not None else float(self._volts[k, axis])
        return (y if math.isfinite(y) else 0.0), u, (v if math.isfinite(v) else 0.0)
