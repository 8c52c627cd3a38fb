"""Timing histograms of the control loop: lateness and work per tick [s].

Every tick of a run lands in a fixed histogram (no allocation on the loop thread):
0.5 µs bins below 2 ms, then 100 µs bins up to 102 ms; later values land in the last bin
(the maximum is kept separately by :class:`afmctl.control.controller.Controller`). :func:`percentiles`
reads quantiles back at bin centres.
"""
from __future__ import annotations

import numpy as np

#: fine bins: width [s] and count (0 .. 2 ms)
FINE_S, N_FINE = 0.5e-6, 4000
#: coarse bins: width [s] and count (2 ms .. 102 ms)
COARSE_S, N_COARSE = 100e-6, 1000
N_BINS = N_FINE + N_COARSE
FINE_END_S = FINE_S * N_FINE
#: 1 / FINE_S: a duration [s] times this is its fine bin index
FINE_BINS_PER_S = 1.0 / FINE_S
EDGES_S = np.concatenate([np.arange(N_FINE) * FINE_S, FINE_END_S + np.arange(N_COARSE) * COARSE_S])
WIDTHS_S = np.concatenate([np.full(N_FINE, FINE_S), np.full(N_COARSE, COARSE_S)])


def new_histogram() -> np.ndarray:
    """An empty lateness/work histogram (int64 counts, :data:`N_BINS` bins)."""
    return np.zeros(N_BINS, dtype=np.int64)


def bin_of(v_s: float) -> int:
    """Histogram bin of a duration ``v_s`` ≥ 0 [s]."""
    if v_s < FINE_END_S:
        return int(v_s * 2e6)
    b = N_FINE + int((v_s - FINE_END_S) * 1e4)
    return b if b < N_BINS else N_BINS - 1


def add(hist: np.ndarray, v_s: float) -> None:
    """Count one duration ``v_s`` ≥ 0 [s] (the fine-bin fast path first)."""
    b = int(v_s * FINE_BINS_PER_S)
    hist[b if b < N_FINE else bin_of(v_s)] += 1


def percentiles(hist: np.ndarray, qs: tuple[float, ...]) -> tuple[float, ...]:
    """Quantiles [s] of a lateness/work histogram (bin centres); 0 for an empty one."""
    cum = np.cumsum(hist)
    total = int(cum[-1])
    if total == 0:
        return tuple(0.0 for _ in qs)
    out = []
    for q in qs:
        b = min(int(np.searchsorted(cum, q * total)), N_BINS - 1)
        out.append(float(EDGES_S[b] + 0.5 * WIDTHS_S[b]))
    return tuple(out)
