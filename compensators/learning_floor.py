"""What stopped learning: the floor the remaining error stands on (sans-I/O).

When the guards of :mod:`afmctl.compensators.learning` stop (no better table, the error
rising), the reason names the floor, the first that holds of:

* ``range`` — the table needs voltages beyond the range: samples of the judged lines sit on
  a limit;
* ``slew`` — it needs a faster change than the amplifier's slew limit: steps of the judged
  lines at the limit;
* ``noise`` — the remaining error is mostly the sensor's noise (its RMS over the judged
  lines within :data:`NOISE_RMS_FACTOR` × the noise's σ);
* ``line rate`` — most of the remaining error lies above the learned band, where no play
  measured the scanner's response: the line's harmonics there are beyond what the line
  rate lets the scanner follow (or the plays excite);
* else ``learning`` — none of these: the law's own limit (the measured response
  scatters; a longer or slower learning may get further).
Units: V, nm, Hz.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: the error is the noise's when its RMS is within this factor of the noise's σ
NOISE_RMS_FACTOR = 1.5
#: a judged sample this close to a limit [share of the range] is on it
EDGE_SHARE = 1e-6


@dataclass(frozen=True)
class Floor:
    """``kind`` (range / slew / noise / line rate / learning) and a ``phrase`` saying why."""

    kind: str
    phrase: str


def name_floor(table_V: np.ndarray, error_nm: np.ndarray, judged: np.ndarray, noise_nm: float, line_nm: float,
               u_min_V: float, u_max_V: float, max_step_V: float, high_share: float, cutoff_Hz: float) -> Floor:
    """The floor (module docstring) of the best table ``table_V`` [V] whose error
    ``error_nm`` [nm] is judged where ``judged``; ``high_share``: the share of the
    remaining error's energy above the learned band, whose top is ``cutoff_Hz``."""
    u = np.asarray(table_V, dtype=float)
    sel = np.asarray(judged, dtype=bool)
    edge = EDGE_SHARE * (u_max_V - u_min_V) if np.isfinite(u_max_V - u_min_V) else 0.0
    on_limit = int(np.count_nonzero(sel & ((u <= u_min_V + edge) | (u >= u_max_V - edge))))
    if on_limit:
        return Floor("range", f"the range: {on_limit} samples of the judged lines need voltages beyond "
                              f"{u_min_V:g} .. {u_max_V:g} V")
    if np.isfinite(max_step_V) and max_step_V > 0:
        steps = np.abs(np.diff(u, prepend=u[0]))
        at = int(np.count_nonzero(sel & (steps >= 0.999 * max_step_V)))
        if at:
            return Floor("slew", f"the slew limit: {at} steps of the judged lines are at it")
    e = np.asarray(error_nm, dtype=float)[sel]
    rms = float(np.sqrt(np.mean(e * e))) if e.size else 0.0
    if noise_nm > 0 and rms <= NOISE_RMS_FACTOR * noise_nm:
        return Floor("noise", f"the sensor's noise: the error's RMS {rms:.3g} nm is the noise's "
                              f"(σ {noise_nm:.3g} nm, {100 * noise_nm / line_nm:.2g} % of the line)")
    if high_share > 0.5:
        return Floor("line rate", f"what the line rate permits: {100 * high_share:.0f} % of the remaining error "
                                  f"lies above {cutoff_Hz:.4g} Hz, where no play measured the scanner's response")
    return Floor("learning", f"the learning's own: RMS {rms:.3g} nm over the judged lines, above the noise "
                             f"(σ {noise_nm:.3g} nm) and inside the measured band (up to {cutoff_Hz:.4g} Hz)")
