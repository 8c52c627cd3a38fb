"""What the wave-table drivers (GCS, NV200) share: the status they report, and the checks
of a whole wave table before any of it is sent: every sample finite and inside
the limits, every step (from the present output to sample 0, between samples and — when it
plays more than once — from the last sample back to the first) within ``max_step_V``."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .base import VoltageLimits
from .errors import LimitError


@dataclass(frozen=True)
class WaveStatus:
    """What the controller's wave generators do: ``running`` per axis, and the last start's
    ``rate_Hz`` [points/s], ``divider`` (servo cycles per point), ``cycles`` and ``points``
    per axis."""

    running: dict[str, bool]
    rate_Hz: float
    divider: int
    cycles: int
    points: dict[str, int]


def check_table(axis: str, table_V: Sequence[float] | np.ndarray, limits: VoltageLimits, *, max_step_V: float | None,
                start_V: float | None = None, wraps: bool = False) -> np.ndarray:
    """The table as a float array [V], or :class:`LimitError` naming the first bad sample
    (0-based index) and what it breaks."""
    v = np.asarray(table_V, dtype=float)
    if v.ndim != 1 or len(v) == 0:
        raise LimitError(f"wave table of axis {axis}: need a non-empty list of voltages")
    bad = np.flatnonzero(~np.isfinite(v) | (v < limits.min_V) | (v > limits.max_V))
    if len(bad):
        k = int(bad[0])
        raise LimitError(f"wave table of axis {axis}: sample {k} = {v[k]:g} V is outside the limits "
                         f"[{limits.min_V:g}, {limits.max_V:g}] V; nothing was sent")
    if max_step_V is None:
        return v
    if start_V is not None and abs(v[0] - start_V) > max_step_V:
        raise LimitError(f"wave table of axis {axis}: sample 0 = {v[0]:g} V is {abs(v[0] - start_V):g} V from "
                         f"the present output {start_V:g} V, over max_step_V={max_step_V:g} V; nothing was sent")
    steps = np.abs(np.diff(v))
    over = np.flatnonzero(steps > max_step_V)
    if len(over):
        k = int(over[0]) + 1
        raise LimitError(f"wave table of axis {axis}: sample {k} = {v[k]:g} V steps {steps[k - 1]:g} V from "
                         f"sample {k - 1}, over max_step_V={max_step_V:g} V; nothing was sent")
    if wraps and abs(v[0] - v[-1]) > max_step_V:
        raise LimitError(f"wave table of axis {axis}: the wrap from sample {len(v) - 1} = {v[-1]:g} V to sample 0 "
                         f"= {v[0]:g} V is over max_step_V={max_step_V:g} V; nothing was sent")
    return v
