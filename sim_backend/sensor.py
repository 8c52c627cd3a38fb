"""The simulated scanner's position sensor and the recordings amplifiers take from it.

Per axis (``SensorConfig``): the true tip position p[n] of the axis (end of simulation
sample n) through a first-order low-pass lp[n] = a·lp[n-1] + (1 - a)·p[n],
a = exp(-2π·bandwidth_Hz·dt_s), a delay of d = round(delay_s / dt_s) samples, Gaussian
noise w[n] (RMS ``noise_nm``) and a quantiser of step q = ``resolution_nm``:
s[n] = q·round((lp[n - d] + w[n]) / q). The noise comes from its own generator seeded from
the scanner's seed, so turning the sensor on changes no other output of the scanner.

A :class:`SensorCapture` asks for readings at times t0_s + k·period_s (an amplifier's data
recorder armed at a wave start): the scanner fills it as simulated time passes them, each
with the reading of the last simulation sample ending at or before that time (the recorder
samples and holds), and beside it the piezo voltage of that sample (``v_V``: the amplifier
stage's output, after its bandwidth and slew, before the hysteresis — what a device's
piezo-voltage monitor records). The sensor runs only while a capture waits; when the first capture
arrives it starts settled at the present position (filter state = position, delay line
filled with it), as a sensor that has been on all along with the scanner at rest.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.signal import lfilter

from .config import SensorConfig

#: a time within this fraction of a sample of a sample's end is that sample's end: the
#: rounding of times a device computes as t0 + k·period (the captures' times here, the
#: scanner's whole samples in :func:`afmctl.sim_backend.scanner.whole_samples`)
SAMPLE_TOL = 1e-6


class SensorCapture:
    """Readings [x, y, z] nm wanted at ``t_s[k] = t0_s + k·period_s`` (k < n), filled by
    the scanner: ``y_nm`` (n, 3) (NaN until filled), the piezo voltages ``v_V`` (n, 3) [V]
    at the same instants, ``count`` filled so far, ``done``."""

    def __init__(self, t0_s: float, period_s: float, n: int) -> None:
        if not (math.isfinite(t0_s) and math.isfinite(period_s) and period_s > 0 and n >= 0):
            raise ValueError(f"capture: t0_s={t0_s!r}, period_s={period_s!r} > 0, n={n!r} >= 0 expected")
        self.t0_s = float(t0_s)
        self.period_s = float(period_s)
        self.t_s = self.t0_s + self.period_s * np.arange(int(n))
        self.y_nm = np.full((int(n), 3), np.nan)
        self.v_V = np.full((int(n), 3), np.nan)
        self.count = 0
        self.cancelled = False

    @property
    def done(self) -> bool:
        return self.count >= len(self.t_s) or self.cancelled

    def cancel(self) -> None:
        """Stop filling (a recorder re-armed or stopped); what was filled stays."""
        self.cancelled = True

    def hold(self, until_s: float, reading: np.ndarray, dt_s: float, volts: np.ndarray | None = None) -> None:
        """Readings due at or before ``until_s`` [s] (already past when asked) get ``reading``
        (and the piezo voltages ``volts`` [V])."""
        k1 = int(np.searchsorted(self.t_s, until_s + SAMPLE_TOL * dt_s, side="right"))
        if k1 > self.count and not self.cancelled:
            self.y_nm[self.count:k1] = reading
            if volts is not None:
                self.v_V[self.count:k1] = volts
            self.count = k1

    def fill(self, t_start_s: float, dt_s: float, readings: np.ndarray, before: np.ndarray,
             volts: np.ndarray | None = None, volts_before: np.ndarray | None = None) -> None:
        """Take the readings of a simulated block: ``readings[i]`` at the end of sample i,
        i.e. at ``t_start_s + (i + 1)·dt_s``; ``before`` is the reading held at ``t_start_s``;
        ``volts`` / ``volts_before`` the piezo voltages [V] likewise."""
        n = len(readings)
        if n == 0 or self.cancelled:
            return
        t_end = t_start_s + n * dt_s
        k0 = self.count
        k1 = int(np.searchsorted(self.t_s, t_end + SAMPLE_TOL * dt_s, side="right"))
        if k1 <= k0:
            return
        idx = np.floor((self.t_s[k0:k1] - t_start_s) / dt_s + SAMPLE_TOL).astype(np.int64) - 1
        rows = np.where(idx[:, None] >= 0, readings[np.clip(idx, 0, n - 1)], before[None, :])
        self.y_nm[k0:k1] = rows
        if volts is not None and volts_before is not None:
            self.v_V[k0:k1] = np.where(idx[:, None] >= 0, volts[np.clip(idx, 0, n - 1)], volts_before[None, :])
        self.count = k1


class PositionSensor:
    """The three axis sensors (streaming: :meth:`reset`, :meth:`block`)."""

    def __init__(self, configs: Sequence[SensorConfig], seed: int) -> None:
        self.configs = list(configs)
        self.seed = int(seed)
        self.noise_nm = np.array([c.noise_nm for c in self.configs])
        self.res_nm = np.array([c.resolution_nm for c in self.configs])
        self.reset(np.zeros(3))

    def reset(self, position_nm: np.ndarray) -> None:
        """Settled at ``position_nm`` [x, y, z]; the noise generator re-seeded."""
        p = np.asarray(position_nm, dtype=np.float64).reshape(3)
        self.rng = np.random.default_rng([self.seed, 0x5E_45_0B])
        self._lp = p.copy()
        self._delay: list[np.ndarray] = [np.full(0, p[i]) for i in range(3)]
        self._dt: float | None = None
        self.last_nm = self._quantise(p[None, :])[0]

    def _quantise(self, v: np.ndarray) -> np.ndarray:
        out = v.copy()
        for i in range(3):
            if self.res_nm[i] > 0:
                out[:, i] = np.round(v[:, i] / self.res_nm[i]) * self.res_nm[i]
        return out

    def _delay_samples(self, i: int, dt_s: float) -> int:
        return int(round(self.configs[i].delay_s / dt_s))

    def block(self, position_nm: np.ndarray, dt_s: float) -> np.ndarray:
        """Readings (N, 3) [nm] for true positions ``position_nm`` (N, 3) at the ends of N
        samples of ``dt_s`` seconds, continuing the sensor's state."""
        p = np.asarray(position_nm, dtype=np.float64)
        n = p.shape[0]
        if n == 0:
            return np.empty((0, 3))
        out = np.empty((n, 3))
        for i, cfg in enumerate(self.configs):
            a = math.exp(-2 * math.pi * cfg.bandwidth_Hz * dt_s) if cfg.bandwidth_Hz else 0.0
            prev = self._lp[i]
            lp, _ = lfilter([1.0 - a], [1.0, -a], p[:, i], zi=[a * self._lp[i]])
            self._lp[i] = lp[-1]
            d = self._delay_samples(i, dt_s)
            hist = self._delay[i]
            if len(hist) != d:      # a new sample period: the line is refilled with its oldest value
                fill = hist[0] if len(hist) else prev
                hist = np.full(d, fill)
            line = np.concatenate([hist, lp])
            out[:, i] = line[:n]
            self._delay[i] = line[len(line) - d:] if d else line[:0]
        out += self.rng.standard_normal((n, 3)) * self.noise_nm
        out = self._quantise(out)
        self.last_nm = out[-1].copy()
        return out
