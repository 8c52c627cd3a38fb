"""Graceful degradation of the dynamics inverse at the amplifier's limits.

The exact inverse of a scanner's dynamics can ask for more voltage or slew than the
amplifier has (the sharp turnarounds of a raster at a high line rate). Instead of
sending that, :func:`invert_within_limits` lowers the band limit of the regularised
inverse (:mod:`afmctl.compensators.dynamics_inverse`) step by step — which rounds the
turnarounds symmetrically, outside the central part of the lines — until the voltages
of the whole chain (dynamics inverse, then the static hysteresis/creep inverse) fit the
range and the slew limit. If even the lowest band limit does not fit, the voltages are
clipped and rate-limited, and the counts are reported: nothing beyond the limits is
ever returned.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .base import StreamingOperator

log = logging.getLogger(__name__)

#: each attempt divides the band limit by this
STEP = 1.25


@dataclass(frozen=True)
class LimitedInverse:
    """Result of :func:`invert_within_limits`: voltages [V] and what was done to fit them."""

    u_V: np.ndarray
    bandwidth_Hz: float
    model_bandwidth_Hz: float
    needed_slew_V_per_s: float
    clipped: int
    slew_limited: int

    def report(self) -> str:
        """One line for the user."""
        if math.isfinite(self.bandwidth_Hz):
            txt = f"dynamics inverse band limit {self.bandwidth_Hz:.4g} Hz"
            if self.bandwidth_Hz < self.model_bandwidth_Hz:
                txt += f" (lowered from {self.model_bandwidth_Hz:.4g} Hz to stay within the limits)"
        else:   # a chain without dynamics: the static inverse alone
            txt = "static inverse"
        txt += f", fastest change {self.needed_slew_V_per_s:.4g} V/s"
        if self.clipped or self.slew_limited:
            txt += (f"; NOT reachable: {self.clipped} samples clipped to the range, "
                    f"{self.slew_limited} samples slew-limited")
        return txt


def _max_slew(u: np.ndarray, dt_s: float) -> float:
    return float(np.max(np.abs(np.diff(u)))) / dt_s if u.size > 1 else 0.0


def rate_limit(u: np.ndarray, lo: float, hi: float, max_step: float,
               u_start_V: float | None = None) -> tuple[np.ndarray, int, int]:
    """Clip to [lo, hi], then limit each sample's change to ``max_step`` [V] (causal);
    returns (voltages, samples clipped, samples rate-limited). ``u_start_V``: the voltage
    the amplifier holds before the first sample (None: the first sample is reachable), so
    a trajectory that does not start where the scanner rests ramps there at the slew
    limit. A limited step is made 1e-9 shorter than ``max_step`` so that rounding never
    lets it exceed the limit."""
    c = np.clip(u, lo, hi)
    clipped = int(np.count_nonzero(c != u))
    out = c.copy()
    limited = 0
    step = max_step * (1 - 1e-9)
    prev = out[0] if (u_start_V is None or out.size == 0) else min(max(float(u_start_V), lo), hi)
    for k in range(out.size):
        d = out[k] - prev
        if abs(d) > max_step:
            out[k] = prev + math.copysign(step, d)
            limited += 1
        prev = out[k]
    return out, clipped, limited


def invert_within_limits(dynamics, target_nm: np.ndarray, dt_s: float,
                         static_inverse: Callable[[], StreamingOperator], u_min_V: float, u_max_V: float,
                         slew_V_per_s: float | None = None, min_bandwidth_Hz: float | None = None,
                         u_start_V: float | None = None) -> LimitedInverse:
    """Voltages [V] for ``target_nm`` through ``dynamics`` (a
    :class:`~afmctl.compensators.dynamics.LinearDynamicsModel`, offline stable inverse)
    and a fresh static inverse from ``static_inverse()`` (nm → V), within
    [u_min_V, u_max_V] and ``slew_V_per_s``. The band limit goes down from the model's by
    :data:`STEP` per attempt to ``min_bandwidth_Hz`` (default a fifth of the slowest pole).
    ``u_start_V``: the voltage held before the first sample (see :func:`rate_limit`); the
    ramp from it is not counted when the band limit is chosen."""
    model_bw = dynamics.inverse_bandwidth_Hz(dt_s)
    p = dynamics.poles()
    floor = min_bandwidth_Hz or (0.2 * float(np.min(np.abs(p))) / (2 * math.pi) if p.size else model_bw / 10)
    base = static_inverse().block(target_nm)  # what the static chain alone needs
    base_out = bool(np.any((base < u_min_V) | (base > u_max_V)))
    max_step = (slew_V_per_s or math.inf) * dt_s
    bw = model_bw
    while True:
        y_d = dynamics.model_copy(update={"bandwidth_Hz": bw}).inverse_offline(target_nm, dt_s)
        u = static_inverse().block(y_d)
        slew = _max_slew(u, dt_s)
        in_range = base_out or not np.any((u < u_min_V) | (u > u_max_V))
        if (slew <= max_step / dt_s and in_range) or bw / STEP < floor:
            break
        bw /= STEP
    u_out, clipped, limited = rate_limit(u, u_min_V, u_max_V, max_step, u_start_V)
    res = LimitedInverse(u_out, bw, model_bw, slew, clipped, limited)
    log.info("%s", res.report())
    return res
