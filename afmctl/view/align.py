"""Tracking error of the live tip: put the simulator's tip and the controller's targets on
one clock.

The controller stamps setpoints with its own time since start (``t_s`` of the setpoint
records), the simulator stamps the tip with the plant's time; both processes start at
different moments. :class:`ClockOffset` estimates, per sender, ``arrival time − sender
time`` as the minimum over the last seconds (the message that arrived fastest bounds the
offset best), so ``sender time + offset`` is that sender's time on this machine's
monotonic clock.
:class:`TargetHistory` keeps the last few seconds of targets at full rate and interpolates
the target at the tip's (aligned) time: ``error_nm = tip_nm − target_nm``. What remains is
the real lag of the chain (serial link, amplifier, scanner dynamics) plus at most the
delivery jitter of the fastest messages (a few ms).
"""
from __future__ import annotations

from collections import deque

import numpy as np


class ClockOffset:
    """Minimum of ``arrival_s − sender_t_s`` [s] over the last ``window_s`` seconds of
    arrivals; ``None`` until the first sample.

    A windowed (not an all-time) minimum, because a sender's clock need not run at the
    wall clock's rate: a controller that misses deadlines under load stamps its samples
    with their *scheduled* time, which falls behind. The window is long against the
    delivery jitter (a few ms) and short against that slip."""

    def __init__(self, window_s: float = 2.0) -> None:
        self.window_s = window_s
        # a sliding-window minimum: offsets increase from front to back, the front is the min
        self._mins: deque[tuple[float, float]] = deque()

    @property
    def offset_s(self) -> float | None:
        return self._mins[0][1] if self._mins else None

    def update(self, arrival_s: float, sender_t_s: float) -> None:
        d = arrival_s - sender_t_s
        while self._mins and self._mins[-1][1] >= d:
            self._mins.pop()
        self._mins.append((arrival_s, d))
        while self._mins[0][0] < arrival_s - self.window_s:
            self._mins.popleft()


class TargetHistory:
    """The last ``keep_s`` seconds of targets [nm] at full rate, by controller time [s]."""

    def __init__(self, keep_s: float = 5.0) -> None:
        self.keep_s = keep_s
        self._t: deque[np.ndarray] = deque()
        self._xyz: deque[np.ndarray] = deque()

    def add(self, t_s: np.ndarray, target_nm: np.ndarray) -> None:
        if len(t_s) == 0:
            return
        if self._t and t_s[0] < self._t[-1][-1]:      # controller restarted: forget the old run
            self._t.clear()
            self._xyz.clear()
        self._t.append(np.asarray(t_s, float).copy())
        self._xyz.append(np.asarray(target_nm, float).reshape(-1, 3).copy())
        while len(self._t) > 1 and self._t[-1][-1] - self._t[1][0] > self.keep_s:
            self._t.popleft()
            self._xyz.popleft()

    @property
    def span_s(self) -> tuple[float, float] | None:
        """(oldest, newest) controller time held [s], or None when empty."""
        return (float(self._t[0][0]), float(self._t[-1][-1])) if self._t else None

    def at(self, t_s: np.ndarray) -> np.ndarray:
        """Targets [nm] (N, 3) linearly interpolated at controller times ``t_s`` [s]; NaN
        outside the held span."""
        t_s = np.asarray(t_s, float)
        out = np.full((len(t_s), 3), np.nan)
        if not self._t:
            return out
        t = np.concatenate(self._t)
        xyz = np.concatenate(self._xyz)
        inside = (t_s >= t[0]) & (t_s <= t[-1])
        for a in range(3):
            out[inside, a] = np.interp(t_s[inside], t, xyz[:, a])
        return out
