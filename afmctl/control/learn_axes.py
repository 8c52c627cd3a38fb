"""Per learned axis of ``afmctl learn --config``: its error per play, its best table column,
and whether it still learns.

The axes are learned column by column (one :class:`~afmctl.compensators.learning.Learner`
each), so each is judged on its own figure — its largest error [nm] over the judged part
of the raster (:func:`afmctl.data.axis_errors.axis_errors`) — not on the worst axis's %
of its own reference. Judged on the worst axis, a raster's slow axis (its % refers to its
short step per line) decided the stop and the kept table for both: on the simulated
E-727 without a model, learning stopped after three plays and kept the unlearned table
while the fast axis had gone from 834 to 87 nm. An axis whose error no longer improves,
reaches the noise floor or whose learner's guard stops it keeps its best column from then
on (:meth:`AxisBook.finish`); learning ends when every axis has finished, and the learned
table is made of each axis's best column (:meth:`AxisBook.best_table`). Units: nm, V.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..data.axis_errors import AxisError, ErrorReport
from .wave_plan import WaveTable

#: relative improvement below which two plays in a row mean an axis's error is at its floor
STALL_IMPROVEMENT = 0.03


@dataclass
class AxisProgress:
    """One learned axis: ``figures_nm``, its judged max error [nm] per play;
    ``best`` (the judged error) of play ``best_iteration`` whose column is
    ``best_column_V`` [V]; ``done``: why it no longer learns ('' while it learns);
    ``diverged``: its learner's guard stopped it."""

    axis: str
    figures_nm: list[float] = field(default_factory=list)
    best: AxisError | None = None
    best_iteration: int = -1
    best_column_V: np.ndarray | None = None
    done: str = ""
    diverged: bool = False

    def stalled(self) -> bool:
        """The last two plays each improved the error by less than :data:`STALL_IMPROVEMENT`."""
        m = self.figures_nm[-3:]
        return len(m) == 3 and all(m[i + 1] > (1.0 - STALL_IMPROVEMENT) * m[i] for i in (0, 1))


class AxisBook:
    """The :class:`AxisProgress` of each learned axis (module docstring)."""

    def __init__(self, axes: list[str]) -> None:
        self.axes = {a: AxisProgress(a) for a in axes}

    def record(self, k: int, table: WaveTable, judged: ErrorReport) -> None:
        """Play ``k`` of ``table`` was judged ``judged``: each axis's figure, and the best of
        each axis that still learns (a finished one plays its best column again)."""
        for a, p in self.axes.items():
            err = judged.axis(a)
            fig = err.max_nm if math.isfinite(err.max_nm) else math.inf
            p.figures_nm.append(fig)
            if not p.done and (p.best is None or fig < p.best.max_nm):
                p.best, p.best_iteration = err, k
                p.best_column_V = table.u_V[:, "xyz".index(a)].copy()

    def learning(self) -> list[str]:
        """The axes that still learn."""
        return [a for a, p in self.axes.items() if not p.done]

    def finish(self, axis: str, why: str, diverged: bool = False) -> None:
        """``axis`` keeps its best column from now on, because ``why``."""
        p = self.axes[axis]
        p.done, p.diverged = why, diverged

    def all_done(self) -> bool:
        return not self.learning()

    def any_diverged(self) -> bool:
        return any(p.diverged for p in self.axes.values())

    def best_column(self, axis: str) -> np.ndarray:
        col = self.axes[axis].best_column_V
        assert col is not None   # record() ran before any axis can finish
        return col

    def best_table(self, table: WaveTable) -> WaveTable:
        """``table`` with each learned axis's column replaced by its best one."""
        u = table.u_V.copy()
        for a, p in self.axes.items():
            if p.best_column_V is not None:
                u[:, "xyz".index(a)] = p.best_column_V
        return WaveTable(table.target_nm, table.corrected_nm, table.drift_nm, u, table.T_C, table.pad,
                         list(table.report))

    def best_text(self) -> str:
        """Per axis the play its best column comes from and that play's figures."""
        return "; ".join(f"{p.best.text()} (iteration {p.best_iteration})" for p in self.axes.values()
                         if p.best is not None)

    def done_text(self, axes: list[str] | None = None) -> str:
        """Why each finished axis (or each of ``axes``) keeps its best column."""
        names = axes if axes is not None else [a for a, p in self.axes.items() if p.done]
        return "; ".join(f"{a} keeps iteration {self.axes[a].best_iteration}: {self.axes[a].done}" for a in names)
