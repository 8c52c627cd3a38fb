"""The scanner's voltage history as a model sees it, and what that history adds to a play
(sans-I/O).

Creep remembers: the identified chain's creep stage (nonlinearities paper, eq. 21: a bank
of first-order lags, time constants up to minutes) carries every voltage the axis has had.
A table learned on a device is played many times in a row, with the finish ramp, the
read-back and the next upload in between; ``afmctl run`` later plays the learned table
once, from rest. The lags hold a different state at the table's first row in the two
cases, so the same table lands elsewhere (on the default simulated scanner 15–18 nm, a
constant-like offset over a 1 µm line: the learned 0.3 % became 2 %).

:class:`VoltageHistory` replays an axis's history (holds, ramps, played tables, at the
table's sample period) through the model's creep stage, starting settled at the voltage
the axis rested at. The *history term* of a play (:func:`history_term_nm`)

    Δy[n] = creep(x | lag states after this play's history)[n] − creep(x | reference's)[n]

for the creep input x of the table (the hysteresis stage's output), is what the model says
the past added to the recorded motion relative to a reference history (here: a play from
rest, as ``afmctl run`` plays a learned table). For the linear creep stage it is exact and
independent of the table: Δy[n] = Σ_k c_k·Δz_k·a_k^n (the lag states' difference decaying
through the table). Learning from ``y − Δy`` learns the table for the reference history.
Units: V, nm, s.
"""
from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np

#: the axis has rested at its start voltage this long before the history begins [s]
#: (settles creep lags up to ~2 min to within 1 %)
SETTLE_S = 600.0
#: each leg of the excursion to ``peak_V`` that sets the hysteresis stage's memory [s]
PEAK_RAMP_S = 1.0


def creep_stages(model: Any) -> tuple[Any, Any] | None:
    """``(hysteresis, creep)`` stage models of ``model`` — a chain with a creep stage, or a
    creep model alone (hysteresis None: the creep acts on the voltage) — else None: the
    model knows no creep, so it predicts no history term."""
    if getattr(model, "kind", None) == "creep":
        return None, model
    if getattr(model, "kind", None) == "chain" and getattr(model, "creep", None) is not None:
        return model.hysteresis, model.creep
    return None


class VoltageHistory:
    """An axis's voltages since it rested at ``start_V`` [V], at ``dt_s`` [s], played through
    the creep stage of ``model`` (:func:`creep_stages`; its hysteresis stage gives the creep
    stage's input). Only the creep stage's lag states make the history term. The
    hysteresis stage's memory matters through the creep input it gives: a model reset to
    its virgin state would give a first ascent unlike every later one, so with ``peak_V``
    [V] the history begins with a ramp up to ``peak_V`` and back (the memory a play
    peaking there leaves) before it settles at ``start_V`` for ``settle_s`` [s]."""

    def __init__(self, model: Any, dt_s: float, start_V: float, settle_s: float = SETTLE_S,
                 peak_V: float | None = None) -> None:
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s: {dt_s!r}; the sample period must be > 0 s")
        stages = creep_stages(model)
        if stages is None:
            raise ValueError(f"a {getattr(model, 'kind', type(model).__name__)} model has no creep stage: "
                             "it predicts no history term")
        self.dt_s = float(dt_s)
        self.hyst = stages[0].forward(self.dt_s) if stages[0] is not None else None
        self.creep = stages[1].forward(self.dt_s)
        self.last_V = float(start_V)
        if peak_V is not None and peak_V > start_V:      # the memory of a descent from peak_V
            self.ramp_over(peak_V, PEAK_RAMP_S)
            self.ramp_over(start_V, PEAK_RAMP_S)
        self._feed(np.full(max(1, int(round(settle_s / self.dt_s))), self.last_V))

    def creep_input(self, u_V: np.ndarray) -> np.ndarray:
        """The creep stage's input for ``u_V`` played next (the hysteresis stage's output
        [nm], or the voltage); the history does not advance."""
        u = np.ascontiguousarray(np.asarray(u_V, dtype=np.float64).ravel())
        return np.asarray(copy.deepcopy(self.hyst).block(u), dtype=float) if self.hyst is not None else u

    def _feed(self, u_V: np.ndarray) -> None:
        if u_V.size:
            u = np.ascontiguousarray(u_V, dtype=np.float64)
            self.creep.block(np.ascontiguousarray(self.hyst.block(u)) if self.hyst is not None else u)
            self.last_V = float(u_V[-1])

    def copy(self) -> "VoltageHistory":
        """An independent copy (the operators' states included)."""
        return copy.deepcopy(self)

    def hold(self, duration_s: float) -> None:
        """The output held at the last voltage for ``duration_s`` [s] (whole samples)."""
        n = int(round(max(0.0, duration_s) / self.dt_s))
        self._feed(np.full(n, self.last_V))

    def ramp(self, to_V: float, rate_V_per_s: float) -> None:
        """A ramp from the last voltage to ``to_V`` at ``rate_V_per_s`` [V/s], one step per
        sample (as the controller's start and finish ramps)."""
        step = abs(rate_V_per_s) * self.dt_s
        d = float(to_V) - self.last_V
        n = int(math.ceil(abs(d) / step)) if step > 0 and d != 0 else 0
        if n:
            ramp = self.last_V + np.sign(d) * step * np.arange(1, n + 1)
            ramp[-1] = float(to_V)
            self._feed(np.clip(ramp, min(self.last_V, to_V), max(self.last_V, to_V)))

    def ramp_over(self, to_V: float, duration_s: float) -> None:
        """A straight ramp from the last voltage to ``to_V`` taking ``duration_s`` [s] (at
        least one sample)."""
        n = max(1, int(round(max(0.0, duration_s) / self.dt_s)))
        self._feed(self.last_V + (float(to_V) - self.last_V) * np.arange(1, n + 1) / n)

    def play(self, u_V: np.ndarray) -> None:
        """A table played, one row per sample period."""
        self._feed(np.asarray(u_V, dtype=np.float64).ravel())

    def creep_state(self) -> list[float]:
        """The creep stage's lag states (its input's units, nm for a chain's), what the
        history so far leaves in them; :meth:`resume` takes them back. Empty for a creep
        stage that keeps no lag states."""
        return [float(z) for z in getattr(self.creep, "z", ())]

    def settle(self) -> None:
        """The lags settled at the present voltage, as after an endless hold there (a creep
        stage without lag states: unchanged)."""
        lags = getattr(self.creep, "z", None)
        if lags is not None:
            x = float(self.creep_input(np.array([self.last_V]))[0])
            lags[:] = x - float(getattr(self.creep, "in_offset", 0.0))

    def resume(self, state: list[float], at_V: float) -> bool:
        """Continue from lag states ``state`` (:meth:`creep_state` of an earlier history of
        the same model, e.g. the plays of ``afmctl calibrate``), the output at ``at_V`` [V].
        False, nothing changed, when ``state`` does not fit this model's lags."""
        z, lags = np.asarray(state, dtype=float), getattr(self.creep, "z", None)
        if lags is None or z.shape != lags.shape or not np.all(np.isfinite(z)):
            return False
        self.creep.z[:] = z
        self.last_V = float(at_V)
        return True


def history_term_nm(history: VoltageHistory, reference: VoltageHistory, u_V: np.ndarray) -> np.ndarray:
    """Δy [nm] per table row (module docstring): what ``history``'s creep states add to a
    play of ``u_V`` relative to ``reference``'s, both fed the creep input ``history`` gives
    for ``u_V`` (for the linear creep stage: Σ_k c_k·Δz_k·a_k^n, whatever the input)."""
    x = np.ascontiguousarray(history.creep_input(u_V))
    return (np.asarray(copy.deepcopy(history.creep).block(x), dtype=float)
            - np.asarray(copy.deepcopy(reference.creep).block(x), dtype=float))
