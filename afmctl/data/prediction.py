"""Run a model file forward on measured voltages and score it against measured displacement
(``afmctl model predict`` / ``model validate``; ``identify`` reports its fit the same way).

Units: t [s], u [V], y [nm]. A model's ``delay_s`` is honoured (``y(t) = M[u](t − delay_s)``).
Errors are reported as RMS and max, with and without the mean offset (a held-out run of a
real scanner sits on a different absolute sensor offset), in nm and in % of the measured span.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .datafiles import uniform_period
from .identdata import delayed, turning_points

log = logging.getLogger(__name__)


def predict_nm(model, t_s: np.ndarray, u_V: np.ndarray, where: str,
               warm: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """The model's displacement [nm] for the voltages ``u_V`` at times ``t_s``, starting from
    the model file's initial state, or after running it through ``warm = (t_s, u_V)`` first
    (a warm start: the recording that preceded this one)."""
    if warm is not None:
        t_all, u_all = np.concatenate([warm[0], t_s]), np.concatenate([warm[1], u_V])
        if np.any(np.diff(t_all) <= 0):  # a separate recording: put it right before this one
            gap = float(np.median(np.diff(t_s))) if t_s.size > 1 else 1.0
            t_all = np.concatenate([warm[0] - warm[0][-1] + t_s[0] - gap, t_s])
        return predict_nm(model, t_all, u_all, where)[warm[0].size:]
    dt = uniform_period(t_s, where) if getattr(model, "time_dependent", False) else (
        float(np.median(np.diff(t_s))) if t_s.size > 1 else None)
    shift_s = 0.0 if getattr(model, "has_own_delay", False) else float(getattr(model, "delay_s", 0.0))
    u_in = delayed(t_s, u_V, shift_s)
    return np.asarray(model.forward(dt).block(np.ascontiguousarray(u_in, dtype=np.float64)))


@dataclass
class ErrorStats:
    """Prediction error over one stretch of a record [nm]."""

    label: str
    t0_s: float
    t1_s: float
    rms_nm: float
    max_nm: float
    rms_demeaned_nm: float
    max_demeaned_nm: float
    mean_nm: float
    span_nm: float

    def row(self) -> str:
        pct = 100.0 / self.span_nm if self.span_nm > 0 else float("nan")
        return (f"{self.label:>8} {self.t0_s:8.3f} {self.t1_s:8.3f} {self.rms_nm:9.4g} {self.max_nm:9.4g} "
                f"{self.rms_demeaned_nm:9.4g} {self.max_demeaned_nm:9.4g} {self.mean_nm:9.4g} "
                f"{self.rms_demeaned_nm * pct:7.3f} {self.max_demeaned_nm * pct:7.3f}")


HEADER = (f"{'segment':>8} {'t0 [s]':>8} {'t1 [s]':>8} {'rms':>9} {'max':>9} {'rms-mean':>9} {'max-mean':>9} "
          f"{'mean':>9} {'rms %':>7} {'max %':>7}")


def error_stats(label: str, t_s: np.ndarray, y_nm: np.ndarray, y_pred_nm: np.ndarray, span_nm: float) -> ErrorStats:
    """RMS/max of ``y_pred − y`` with and without its mean over these samples."""
    e = y_pred_nm - y_nm
    m = float(np.mean(e))
    return ErrorStats(label, float(t_s[0]), float(t_s[-1]), float(np.sqrt(np.mean(e * e))),
                      float(np.max(np.abs(e))), float(np.sqrt(np.mean((e - m) ** 2))),
                      float(np.max(np.abs(e - m))), m, span_nm)


def segment_bounds(u_V: np.ndarray, max_segments: int = 20) -> list[tuple[int, int]]:
    """Split a record at the input's lower turning points (one segment per input cycle);
    one segment when the input has fewer than two cycles or more than ``max_segments``."""
    tp = turning_points(u_V)
    mid = float(np.median(u_V))
    cuts = sorted({0, u_V.size, *(int(k) for k in tp if k > 0 and u_V[k] < mid)})
    pieces = [(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b - a > 1]
    if len(pieces) < 2 or len(pieces) > max_segments:
        return [(0, u_V.size)]
    return pieces


def score(t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, y_pred_nm: np.ndarray,
          start: int = 0, measured: np.ndarray | None = None) -> list[ErrorStats]:
    """Whole-record stats (samples from ``start``), then one line per input cycle; only the
    samples ``measured`` (a boolean per sample; None: all) count."""
    keep = np.ones(t_s.size, dtype=bool) if measured is None else measured
    span = float(np.ptp(y_nm[start:][keep[start:]]))

    def stats(label: str, a: int, b: int) -> ErrorStats | None:
        k = keep[a:b]
        return error_stats(label, t_s[a:b][k], y_nm[a:b][k], y_pred_nm[a:b][k], span) if k.any() else None

    out = [stats("all", start, t_s.size)]
    bounds = segment_bounds(u_V[start:])
    if len(bounds) > 1:
        out += [stats(f"cycle {i}", a + start, b + start) for i, (a, b) in enumerate(bounds, start=1)]
    return [s for s in out if s is not None]


def plot_validation(path: str, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, y_pred_nm: np.ndarray,
                    start: int, title: str) -> None:
    """Measured vs predicted over time and against u, and the error with its mean removed."""
    from ..figures import pyplot, save_figure
    plt = pyplot()

    sl = slice(start, None)
    e = y_pred_nm[sl] - y_nm[sl]
    fig, ax = plt.subplots(1, 3, figsize=(14, 4))
    ax[0].plot(t_s[sl], y_nm[sl] / 1e3, lw=0.8, label="measured")
    ax[0].plot(t_s[sl], y_pred_nm[sl] / 1e3, lw=0.8, ls="--", label="model")
    ax[0].set(xlabel="t [s]", ylabel="y [µm]", title=title)
    ax[0].legend()
    ax[1].plot(u_V[sl], y_nm[sl] / 1e3, lw=0.6, label="measured")
    ax[1].plot(u_V[sl], y_pred_nm[sl] / 1e3, lw=0.6, ls="--", label="model")
    ax[1].set(xlabel="u [V]", ylabel="y [µm]")
    ax[2].plot(t_s[sl], e, lw=0.5, label="model − measured")
    ax[2].plot(t_s[sl], e - np.mean(e), lw=0.5, label="mean removed")
    rms = float(np.sqrt(np.mean((e - np.mean(e)) ** 2)))
    ax[2].set(xlabel="t [s]", ylabel="error [nm]", title=f"RMS {rms:.4g} nm (mean removed)")
    ax[2].legend()
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
