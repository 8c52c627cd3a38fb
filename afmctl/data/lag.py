"""The lag of a motion behind its target, per axis: the delay that best aligns the measured
(or replayed) position with the target over the judged part of the record.

For an axis whose target moves over the judged part (the central part of a raster's lines,
:func:`afmctl.data.axis_errors.judged_part`, else the whole record), the lag τ [samples]
minimises the squared difference between the position p[k] and the target delayed by τ,
r(k − τ) (the target linearly interpolated between samples): first over whole samples
within ±``max_lag`` (a cross-correlation by least squares), then to a fraction of a sample
around the best one. τ > 0: the motion trails the target (a delay), τ < 0: it leads.

Beside it, what is left after the lag: max |e| and RMS [nm] of p[k] − r(k − τ) over the
same samples — the part of the tracking error a delay does not explain. An axis whose
target holds over the judged part, or a raster's slow axis (it steps between the lines),
has no lag (``why`` says so). Units: samples, s, nm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .axis_errors import AXES, MIN_SPAN_NM, judged_part

#: longest lag looked for [s] (and at most a quarter of a raster's line)
MAX_LAG_S = 0.1


@dataclass(frozen=True)
class AxisLag:
    """One axis's lag ``samples`` (None: not measurable, ``why``) at the period ``dt_s`` [s],
    and the error left after it: ``rest_max_nm``, ``rest_rms_nm``."""

    axis: str
    samples: float | None
    dt_s: float
    rest_max_nm: float | None = None
    rest_rms_nm: float | None = None
    why: str | None = None

    @property
    def ms(self) -> float | None:
        return None if self.samples is None else self.samples * self.dt_s * 1e3

    def text(self) -> str:
        """``x 0.52 ms (1.04 samples), after it max 3.1 nm / RMS 1.2 nm``."""
        if self.samples is None:
            return f"{self.axis} — ({self.why})"
        return (f"{self.axis} {self.ms:.3g} ms ({self.samples:.3g} samples), after it max "
                f"{self.rest_max_nm:.3g} nm / RMS {self.rest_rms_nm:.3g} nm")

    def as_dict(self) -> dict:
        return {"axis": self.axis, "lag_samples": self.samples, "lag_ms": self.ms, "dt_s": self.dt_s,
                "rest_max_nm": self.rest_max_nm, "rest_rms_nm": self.rest_rms_nm, "why": self.why}


def _shifted(r: np.ndarray, tau: float, idx: np.ndarray) -> np.ndarray:
    """r(k − τ) at the samples ``idx``, linearly interpolated (held at the ends)."""
    return np.interp(idx - tau, np.arange(len(r), dtype=float), r)


def axis_lag(target: np.ndarray, position: np.ndarray, mask: np.ndarray, max_lag: int) -> float:
    """The lag [samples] of ``position`` behind ``target`` (one axis, (N,) nm) over the
    samples of ``mask`` (module docstring); sub-sample."""
    from scipy.optimize import minimize_scalar
    r = np.asarray(target, dtype=float)
    p = np.asarray(position, dtype=float)
    idx = np.flatnonzero(mask)
    n = len(r)
    best, best_sse = 0, np.inf
    for lag in range(-max_lag, max_lag + 1):
        src = idx - lag
        ok = (src >= 0) & (src < n)
        if np.count_nonzero(ok) < max(2, idx.size // 2):
            continue
        d = p[idx[ok]] - r[src[ok]]
        sse = float(np.mean(d * d))
        if sse < best_sse:
            best, best_sse = lag, sse
    fine = minimize_scalar(lambda tau: float(np.mean((p[idx] - _shifted(r, tau, idx)) ** 2)),
                           bounds=(best - 1.0, best + 1.0), method="bounded", options={"xatol": 1e-3})
    return float(fine.x) if fine.fun <= best_sse else float(best)


def measure_lags(target_nm: np.ndarray, position_nm: np.ndarray, dt_s: float, axes: str = AXES,
                 max_lag_s: float = MAX_LAG_S) -> list[AxisLag]:
    """Per axis of ``axes``, the lag of ``position_nm`` behind ``target_nm`` (both (N, 3) [nm],
    columns x, y, z, one row per period ``dt_s`` [s]) over the judged part of the record."""
    tgt = np.asarray(target_nm, dtype=float)
    pos = np.asarray(position_nm, dtype=float)
    mask, _part, raster = judged_part(tgt, axes)
    max_lag = max(1, int(round(max_lag_s / dt_s)))
    if raster is not None:
        max_lag = max(1, min(max_lag, int(np.median([ln.n for ln in raster[1]])) // 4))
    out = []
    for a in axes:
        k = AXES.index(a)
        if not np.any(mask) or np.ptp(tgt[mask, k]) < MIN_SPAN_NM:
            out.append(AxisLag(a, None, dt_s, why="its target holds over the judged part"))
            continue
        if raster is not None and a != raster[0]:
            out.append(AxisLag(a, None, dt_s, why="a raster's slow axis: its target holds along the lines"))
            continue
        tau = axis_lag(tgt[:, k], pos[:, k], mask, max_lag)
        idx = np.flatnonzero(mask)
        rest = pos[idx, k] - _shifted(tgt[:, k], tau, idx)
        out.append(AxisLag(a, tau, dt_s, float(np.max(np.abs(rest))), float(np.sqrt(np.mean(rest * rest)))))
    return out
