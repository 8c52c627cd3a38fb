"""The data recorder of the simulated NV200, sans-I/O (facts from the vendor's ``nv200``
library, ``DataRecorder``, and piezosystem jena's NV200 command list).

Two channels (0, 1) record in parallel, each from the source ``recsrc,<ch>,<src>``: 0 piezo
position (µm with a sensor; the piezo voltage without one), 1 setpoint (in open loop the
voltage commanded), 2 piezo voltage [V] (the scanner's amplifier stage output, read with the
sensor's capture; without a sensor the voltage commanded),
3 position error, 4 its absolute value, 6/7 piezo currents (0 here). The base rate is
20 kHz (50 µs); ``recstr`` keeps every n-th sample; ``reclen`` points per channel (at most
6144; 0 = the whole buffer). ``recast`` says what starts it once ``recrun,1`` armed it: 0 at
once, 1 the next ``set`` command, 2 the waveform generator's start (``grun,1``, also without
``recrun,1``). ``recrun`` reads 1 while armed or recording. ``recoutf,<ch>`` answers every
point recorded so far, ``recout,<ch>,<i>,<n>`` n of them from index i.

Timing: started at t0 (the command's time; with ``recast,2`` the generator's start tick, so
point 0 is taken in the tick that outputs waveform sample 0), point k is taken at
t0 + k·recstr·50 µs: a voltage or setpoint is the value in force then, a position the
scanner's position sensor at that instant (the response to the samples before it).
"""
from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

BUFFER_SIZE = 6144
BASE_SAMPLE_S = 50e-6


class NV200Recorder:
    """``NV200Recorder(sensor, position_um)``: ``sensor(t0_s, period_s, n)`` is a capture of
    the sink's position sensor or None; ``position_um(volts)`` the unit's linear position of
    an output voltage (used without a sensor capture)."""

    def __init__(self, sensor: Callable[[float, float, int], Any], position_um: Callable[[float], float],
                 has_sensor: bool) -> None:
        self.sensor = sensor
        self.position_um = position_um
        self.has_sensor = has_sensor
        self.recsrc = {0: 0, 1: 1}
        self.state = "idle"              # idle, armed, recording, done
        self.t0_s = 0.0
        self.n = 0
        self.stride = 1
        self.capture: Any = None
        self._held = {"volts": 0.0, "set": 0.0}
        self._volts = np.zeros(0)
        self._setp = np.zeros(0)
        self._filled = 0

    @property
    def running(self) -> bool:
        return self.state in ("armed", "recording")

    def output_changed(self, t_s: float, volts: float, setpoint: float) -> None:
        self._fill(t_s, strict=True)
        self._held = {"volts": volts, "set": setpoint}

    def outputs_changed(self, t_s: np.ndarray, volts: np.ndarray, setpoints: np.ndarray) -> None:
        """:meth:`output_changed` for a block of changes (``t_s`` non-decreasing) at once:
        the same points filled with the same values, without a call per change."""
        t = np.asarray(t_s, dtype=np.float64)
        if not len(t):
            return
        if self.state == "recording" and self._filled < self.n:
            # change i holds from point first[i] on (points due strictly before it keep the old)
            first = np.ceil((t - self.t0_s) / (self.stride * BASE_SAMPLE_S) - 1e-9)
            upto = int(min(first[-1], self.n))
            if upto > self._filled:
                k = np.arange(self._filled, upto)
                i = np.searchsorted(first, k, side="right") - 1
                for dst, new, old in ((self._volts, volts, self._held["volts"]), (self._setp, setpoints, self._held["set"])):
                    dst[self._filled:upto] = np.where(i >= 0, np.asarray(new, dtype=np.float64)[np.maximum(i, 0)], old)
                self._filled = upto
        self._held = {"volts": float(volts[-1]), "set": float(setpoints[-1])}

    def sync(self, now_s: float) -> None:
        self._fill(now_s, strict=False)
        if self.state == "recording" and self.count() >= self.n:
            self.state = "done"

    def _fill(self, t_s: float, strict: bool) -> None:
        if self.state != "recording" or self._filled >= self.n:
            return
        x = (t_s - self.t0_s) / (self.stride * BASE_SAMPLE_S)
        last = math.ceil(x - 1e-9) - 1 if strict else math.floor(x + 1e-9)
        upto = min(last + 1, self.n)
        if upto > self._filled:
            self._volts[self._filled:upto] = self._held["volts"]
            self._setp[self._filled:upto] = self._held["set"]
            self._filled = upto

    def arm(self) -> None:
        self.state = "armed"

    def stop(self) -> None:
        if self.capture is not None:
            self.capture.cancel()
        self.state = "done" if self.state == "recording" else "idle"

    def start(self, now_s: float, stride: int, reclen: int) -> None:
        """Start recording at ``now_s`` (point 0 taken then)."""
        self.sync(now_s)
        if self.capture is not None:
            self.capture.cancel()
        self.t0_s = float(now_s)
        self.stride, self.n = int(stride), int(reclen) or BUFFER_SIZE
        self._volts, self._setp, self._filled = np.zeros(self.n), np.zeros(self.n), 0
        wants_position = any(s in (0, 2, 3, 4) for s in self.recsrc.values())   # 2: the amplifier stage
        self.capture = (self.sensor(self.t0_s, self.stride * BASE_SAMPLE_S, self.n)
                        if wants_position and self.has_sensor else None)
        self.state = "recording"

    def count(self) -> int:
        n = self._filled
        if self.capture is not None:
            n = min(n, self.capture.count)
        return n

    def values(self, ch: int) -> np.ndarray:
        """Every point of channel ``ch`` recorded so far, in the source's unit."""
        n = self.count()
        src = self.recsrc[ch]
        volts, setp = self._volts[:n], self._setp[:n]
        if src == 2:                     # the piezo voltage: the amplifier stage's output
            return self.capture.v_V[:n, 0].copy() if self.capture is not None else volts.copy()
        if src == 1:
            return setp.copy()
        if src in (6, 7):
            return np.zeros(n)
        if not self.has_sensor:          # without a sensor "position" is the piezo voltage
            pos, ref = volts, setp
        else:
            model = np.array([self.position_um(v) for v in volts])
            pos = self.capture.y_nm[:n, 0] / 1000.0 if self.capture is not None else model
            ref = np.array([self.position_um(v) for v in setp])
        if src == 0:
            return np.asarray(pos, dtype=float).copy()
        err = ref - pos
        return np.abs(err) if src == 4 else err
