"""Excitation voltages to play while recording the displacement, for identification
(``afmctl excite`` writes them to a CSV)."""
from __future__ import annotations

import numpy as np

from ..data.excitation import ExcitationSpec, excitation


def excite(kind: str, u_min_V: float, u_max_V: float, rate_Hz: float, *, slew_V_per_s: float | None = None,
           sweep_V_per_s: float | None = None, dwell_s: float = 2.0, gap_s: float = 1.0,
           amplitude_frac: float = 0.02, f_min_Hz: float = 5.0, f_max_Hz: float | None = None,
           periods: int = 8, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``(t_s, u_V)``: the excitation of ``kind`` — ``static`` (major loop and first-order
    reversal curves), ``creep`` (a staircase with ``dwell_s`` holds), ``dynamics`` (a
    small-signal multisine, ±``amplitude_frac`` of the range, ``f_min_Hz``…``f_max_Hz``,
    ``periods`` periods) or ``all`` (the three, ``gap_s`` apart) — sampled at ``rate_Hz``,
    starting at ``u_min_V``; no sample changes faster than half of ``slew_V_per_s``. See
    :mod:`afmctl.data.excitation` for the references."""
    spec = ExcitationSpec(u_min_V=u_min_V, u_max_V=u_max_V, rate_Hz=rate_Hz, sweep_V_per_s=sweep_V_per_s,
                          slew_V_per_s=slew_V_per_s, dwell_s=dwell_s, gap_s=gap_s, amplitude_frac=amplitude_frac,
                          f_min_Hz=f_min_Hz, f_max_Hz=f_max_Hz, periods=periods, seed=seed)
    u = excitation(kind, spec)
    return np.arange(u.size) / spec.rate_Hz, u
