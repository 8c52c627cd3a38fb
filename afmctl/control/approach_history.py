"""What the approach before a compensated table adds to its play, taken out (``output =
"wave"``, a model with a creep stage).

A table :func:`~afmctl.control.wave_plan.plan_table` computes is the model's inverse of the
target from the creep stage's rest: its lags at their initial state (the scanner rested at
0 V), the first row held for the preview's padding. On the device the output first rests
where it is, ramps to the first row at ``safety.ramp_V_per_s`` and holds it for
``amplifier.settle_s`` (:mod:`afmctl.control.wave_run`, phase ``approach``): the creep of
that ramp has run a settle hold longer than the inverse assumed when the table starts, and
the table lands off by it (the README tour's model, a fresh simulated E-727: 23.2 nm max /
16.8 nm RMS of the 2 µm line, an offset; the model's term over the table 63 → 20 nm).
Right after ``afmctl calibrate`` on the same device the calibration's creep adds its own
(:func:`~afmctl.control.learn_history.calibration_history`; 42.9 nm in the first run).

:func:`approach_term_nm` is the history term (:mod:`afmctl.compensators.learning_history`)
of that approach against the inverse's rest; :func:`with_approach_taken_out` takes it out of
every column whose model has a creep stage, through the model's static part, as
:mod:`afmctl.control.learned_after` does for a learned table (whose learning already played
each table after the same approach). It assumes the axis rested at its present output
before the run (or since the calibration ended). Units: V, nm, s.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from afmctl.compensators.dynamics_limits import rate_limit
from afmctl.compensators.learning_history import VoltageHistory, creep_stages, history_term_nm

from .learn_history import calibration_history, resume_calibration
from .learned_after import NEGLIGIBLE_NM, take_out
from .wave_plan import WaveTable


#: passes of :func:`approach_corrected`: the corrected table's first row is where the
#: approach ramps to, so its term depends on the correction (a creep fraction of it,
#: ~4 %: the error left shrinks that much per pass)
PASSES = 3


def approach_term_nm(model: Any, dt_s: float, u_V: np.ndarray, start_V: float, rate_V_per_s: float,
                     settle_s: float, prior: dict[str, Any] | None = None,
                     to_V: float | None = None) -> tuple[np.ndarray, float | None]:
    """The history term [nm] per row of a play of column ``u_V`` [V] after the approach —
    rest at ``start_V`` (or, with ``prior``, what a calibration left: its ``history``
    entry), a ramp to ``to_V`` (default: the first row) at ``rate_V_per_s`` [V/s], a hold
    of ``settle_s`` [s] — against the rest the inverse assumed (the creep stage's lags at
    their initial state); and the seconds since the calibration ended (None: ``prior`` not
    taken)."""
    u = np.asarray(u_V, dtype=np.float64)
    before = _before_approach(model, dt_s, u, start_V, prior)
    if before is None:
        return np.zeros(u.size), None
    return _approach_term(before, u, float(u[0]) if to_V is None else float(to_V), rate_V_per_s, settle_s), before[2]


def approach_corrected(model: Any, dt_s: float, u_V: np.ndarray, start_V: float, rate_V_per_s: float,
                       settle_s: float, prior: dict[str, Any] | None = None
                       ) -> tuple[np.ndarray, np.ndarray, float | None]:
    """Column ``u_V`` [V] with the term of the approach to its own first row taken out
    (:func:`approach_term_nm`, :data:`PASSES` passes), the term [nm] and the seconds since
    the calibration ended (None: not taken)."""
    u = np.asarray(u_V, dtype=np.float64)
    before = _before_approach(model, dt_s, u, start_V, prior)
    if before is None:
        return u, np.zeros(u.size), None
    out = u
    for _ in range(PASSES):
        term = _approach_term(before, u, float(out[0]), rate_V_per_s, settle_s)
        out = take_out(u, term, model, dt_s)
    return out, term, before[2]


def _before_approach(model: Any, dt_s: float, u: np.ndarray, start_V: float, prior: dict[str, Any] | None
                     ) -> tuple[VoltageHistory, VoltageHistory, float | None] | None:
    """The axis before the approach — settled at ``start_V``, or continued from what a
    calibration left (``prior``) —, the rest the table's inverse assumed, and the seconds
    since the calibration ended (None: not taken); None for a creep stage without lag
    states."""
    h = VoltageHistory(model, dt_s, float(start_V), settle_s=dt_s, peak_V=float(np.max(u)))
    if not h.creep_state():
        return None
    rest = h.copy()
    rest.resume(creep_stages(model)[1].forward(dt_s).z.tolist(), h.last_V)    # type: ignore[index]
    h.settle()
    return h, rest, resume_calibration(h, prior) if prior else None


def _approach_term(before: tuple[VoltageHistory, VoltageHistory, float | None], u: np.ndarray, to_V: float,
                   rate_V_per_s: float, settle_s: float) -> np.ndarray:
    """The term [nm] of a play of ``u`` after a ramp from ``before`` to ``to_V`` [V] and a hold."""
    h = before[0].copy()
    h.ramp(to_V, rate_V_per_s)
    h.hold(settle_s)
    return history_term_nm(h, before[1], u)


def with_approach_taken_out(table: WaveTable, config: Any, models: list[Any], start_V: list[float],
                            limits_V: dict[str, tuple[float, float]], max_step_V: float,
                            calibration: bool = True) -> WaveTable:
    """``table`` with each creep-stage axis's approach term taken out (module docstring),
    within ``limits_V`` and ``max_step_V`` per row again, one report line per corrected
    axis; ``table`` itself when nothing is taken out. ``models``: per axis x, y, z the
    model the table was planned with (or None); ``start_V``: the present output [V] per
    axis x, y, z; ``calibration``: include a recent calibration's creep (``afmctl learn``'s
    first table does not: its history term takes it out of every recording)."""
    prior = calibration_history(config) if calibration else {}
    rate = min(float(config.safety.ramp_V_per_s), float(config.slew_V_per_s()))
    settle_s = config.amplifier.hold_s()
    out = replace(table, u_V=table.u_V.copy(), report=list(table.report))
    for axis, (lo, hi) in limits_V.items():
        k = "xyz".index(axis)
        model = models[k]
        if model is None or creep_stages(model) is None or np.ptp(out.u_V[:, k]) == 0.0:
            continue
        u, term, ago = approach_corrected(model, config.dt_s, out.u_V[:, k], start_V[k], rate, settle_s,
                                          prior.get(axis))
        if float(np.max(np.abs(term))) < NEGLIGIBLE_NM:
            continue
        out.u_V[:, k], clipped, limited = rate_limit(u, lo, hi, max_step_V, None)
        out.clamped += clipped
        out.slew_limited += limited
        after = f", the calibration's of {ago:.0f} s ago included" if ago is not None else ""
        out.report.append(f"{axis}: the approach's creep (a ramp from {start_V[k]:.3g} V, a {settle_s:g} s hold"
                          f"{after}) adds {float(np.mean(term)):+.1f} nm (mean; the model's), taken out")
    return out if out.report != table.report else table
