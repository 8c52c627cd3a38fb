"""What a record's input covers, and so what it can identify (#36: a choice that holds on
the next recording).

* **Minor loops**: reversals of the input inside its range (not within 10 % of either end).
  Full-range cycles alone identify only the Preisach plane's row and column sums (its
  major-loop branches); its inside comes from the fit's prior (PI-like) or its smoothing.
* **Holds after a step**: creep shows only while the input rests. Without any hold of at
  least :data:`MIN_HOLD_S` (ten times the shortest lag a creep stage has), a creep stage
  fitted to the record explains the hysteresis model's misfit, not creep (on full-range
  sines, ``preisach+creep`` predicted minor loops 1.8–2.7× worse than ``preisach``);
  holds of :data:`GOOD_HOLD_S` and more show the slower lags too.
* **Several rates**: the spread of the input's half-periods (rate dependence, dynamics).
* **Large fast parts** (:func:`~afmctl.compensators.dynamics_identify.fast_parts` over more
  than :data:`~afmctl.compensators.dynamics_identify.LARGE_FRACTION` of the span): what tells
  an amplifier lag before the hysteresis from one after it, and drives the amplifier into its
  slew limit.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import _coverage_kernels as K

#: a record needs a hold of at least this long [s] after a step for a creep stage to be tried
MIN_HOLD_S = 0.1
#: holds of this long [s] identify the slower lags too (what ``afmctl excite --kind creep`` records)
GOOD_HOLD_S = 1.0
#: at least this many reversals inside the range make minor loops
MIN_INTERIOR_REVERSALS = 3


def _reversals(u_V: np.ndarray, tol: float, use_numba: bool = True) -> np.ndarray:
    """Indices of the input's turning points, ignoring wiggles smaller than ``tol`` [V]
    (:func:`._coverage_kernels.reversals_py`; ``use_numba=False`` runs that reference)."""
    u = np.ascontiguousarray(u_V, dtype=float)
    out = np.empty(u.size, dtype=np.int64)
    kernel = K.reversals_nb if use_numba else K.reversals_py
    return out[:kernel(u, float(tol), out)].copy()


def turning_points(u_V: np.ndarray, tol_fraction: float = 0.01) -> np.ndarray:
    """Indices of the input's reversal points (moves under ``tol_fraction`` of the span ignored)."""
    return _reversals(u_V, tol_fraction * float(np.ptp(u_V)))


def interior_reversals(u_V: np.ndarray) -> int:
    """How many of the input's reversals lie inside its range (more than 10 % of the span from
    either end): the minor loops."""
    u = np.asarray(u_V, dtype=float)
    return _interior(u, turning_points(u))


def _interior(u: np.ndarray, tp: np.ndarray) -> int:
    """How many of the turning points ``tp`` of ``u`` lie more than 10 % of the span inside."""
    span = float(np.ptp(u))
    lo, hi = float(np.min(u)), float(np.max(u))
    at = u[tp]
    return int(np.count_nonzero((at > lo + 0.1 * span) & (at < hi - 0.1 * span)))


def longest_hold_s(t_s: np.ndarray, u_V: np.ndarray, tol: float, use_numba: bool = True) -> float:
    """Longest time [s] the input stays within ``tol`` [V] after it first moved
    (:func:`._coverage_kernels.longest_hold_py`; ``use_numba=False`` runs that reference)."""
    u = np.ascontiguousarray(u_V, dtype=float)
    moved = np.flatnonzero(np.abs(u - u[0]) > tol)
    if moved.size == 0:
        return 0.0
    kernel = K.longest_hold_nb if use_numba else K.longest_hold_py
    return float(kernel(np.ascontiguousarray(t_s, dtype=float), u, float(tol), int(moved[0])))


def large_fast_part(t_s: np.ndarray, u_V: np.ndarray) -> bool:
    """Whether the record has a fast part whose input spans more than a fifth of the record's
    span (non-uniform samples: taken as yes, not judged here)."""
    from .dynamics_identify import LARGE_FRACTION, fast_parts, is_uniform

    if not is_uniform(t_s):
        return True
    span = float(np.ptp(u_V))
    return any(float(np.ptp(u_V[a:b])) > LARGE_FRACTION * span for a, b in fast_parts(u_V, t_s))


@dataclass(frozen=True)
class Coverage:
    """What the input ``u`` [V] of a record (times ``t`` [s]) covers (module docstring)."""

    interior_reversals: int
    longest_hold_s: float
    several_rates: bool
    large_fast: bool

    @classmethod
    def of(cls, t_s: np.ndarray, u_V: np.ndarray) -> "Coverage":
        t, u = np.asarray(t_s, dtype=float), np.asarray(u_V, dtype=float)
        tp = turning_points(u)
        half = np.diff(t[tp]) if tp.size > 2 else np.array([])
        several = bool(half.size >= 2 and float(np.max(half)) >= 3.0 * float(np.min(half)))
        return cls(_interior(u, tp), longest_hold_s(t, u, 0.005 * float(np.ptp(u))), several,
                   several and large_fast_part(t, u))

    @property
    def minor_loops(self) -> bool:
        return self.interior_reversals >= MIN_INTERIOR_REVERSALS

    @property
    def holds(self) -> bool:
        """A hold long enough to try a creep stage at all."""
        return self.longest_hold_s >= MIN_HOLD_S

    @property
    def long_holds(self) -> bool:
        return self.longest_hold_s >= GOOD_HOLD_S
