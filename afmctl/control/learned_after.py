"""What the learning's own plays still add when ``afmctl run`` plays a learned table on the
device that learned it.

A learned table is learned for a play from rest (:mod:`afmctl.control.learn_history`: each
recording is freed of its history term). A device keeps its state between commands: right
after ``afmctl learn`` the scanner still creeps from the learning's plays, and a run then
lands off by what they left (the README tour on the simulated E-727: 1.1 nm learned,
11.4 nm played right after, with a history term of 17.7 nm at the last play; on a fresh
simulator, at rest, the same table played 0.8 nm). With a model that has a creep stage,
``afmctl learn`` keeps in the table the history term a play would meet at a few delays
after its last play (:data:`AFTER_S`, :class:`HistoryAfter`), and ``afmctl run`` takes out
the one for the time that has passed (:func:`corrected_for_history`), through the model's
static part: ``u' = u + S⁻¹(S(u) − Δy) − S⁻¹(S(u))``, as the learning law changes a table.
It assumes that nothing else has played on the device since the learning ended (the
report line says so); an in-process simulator starts at rest with every command, so there
nothing is taken out. An axis without a creep stage was learned for the play right after
the learning's (:class:`AsRecorded`): nothing is known to take out, and ``afmctl run``
says so when it plays the table later than :data:`AS_RECORDED_FRESH_S`. Units: V, nm, s.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from .wave_plan import WaveTable

log = logging.getLogger(__name__)

#: delays after the learning's last play [s] at which the history term is kept; after the
#: last the scanner counts as rested (the history term's own reference rests 600 s:
#: :data:`afmctl.compensators.learning_history.SETTLE_S`), and nothing is taken out
AFTER_S = (0.0, 2.0, 5.0, 10.0, 20.0, 40.0, 80.0, 160.0, 320.0, 640.0)
#: a history term whose largest value is below this [nm] is left alone
NEGLIGIBLE_NM = 0.05
#: a table whose axes were learned from their recordings as they are (no creep stage) is
#: right for a play this soon [s] after the learning's last play; later ``afmctl run`` says
#: how far the creep has moved on (measured on the simulated E-727, e727_tcp model-free, x:
#: 2.2 nm played about 4 s after; runs one after the other: 7.1 nm after 10 s of rest,
#: 10.2 nm after 30 s; docs/LEARNING.md)
AS_RECORDED_FRESH_S = 10.0
#: on a device, a play of a table learned as recorded starts this long [s] after the play
#: before it ended — every play of ``afmctl learn`` and the ``afmctl run`` after it — so
#: that each meets the creep of the plays before it at the same age. Back to back (0.25 s
#: apart) the plays of e727_tcp model-free piled up creep: y's kept column measured
#: 1.7 → 3.4 → 3.9 nm in three plays and 4.6 nm in the replay, and ``afmctl run`` 2.4 s
#: later 3.0 nm (2026-11-29, the simulated E-727). Longer than a run's start (~2.4 s from
#: the end of ``afmctl learn`` to the run's approach), shorter than :data:`AS_RECORDED_FRESH_S`.
AS_RECORDED_REST_S = 4.0


def rest_left_s(ended_unix_s: float, rest_s: float, now_unix_s: float | None = None) -> float:
    """What is left [s] of a rest of ``rest_s`` after a play that ended at ``ended_unix_s``
    (wall clock, s since the epoch): 0 once it has passed, at most ``rest_s`` (a clock
    stepped back)."""
    now = time.time() if now_unix_s is None else now_unix_s
    return max(0.0, min(rest_s, ended_unix_s + rest_s - now))


@dataclass(frozen=True)
class AsRecorded:
    """Axes learned on a device from their recordings as they are (no model's creep stage:
    :class:`afmctl.control.learn_history.HistoryTerms`), when the learning's last play
    ended (``ended_unix_s``, wall clock [s since the epoch]) and the rest [s] every play
    kept after the one before (``rest_s``, :data:`AS_RECORDED_REST_S`; 0 in a table from
    before it, which asks for no rest)."""

    axes: tuple[str, ...]
    ended_unix_s: float
    rest_s: float = 0.0

    def wait_s(self, now_unix_s: float | None = None) -> float:
        """How long [s] a play starting now waits so that it starts ``rest_s`` after the
        last play ended, as the learning's plays did (0 when that has passed)."""
        return rest_left_s(self.ended_unix_s, self.rest_s, now_unix_s) if self.axes else 0.0

    def waiting(self, wait_s: float) -> str:
        """The run's line for a wait of ``wait_s`` [s] (:meth:`wait_s`)."""
        return (f"{', '.join(self.axes)}: learned without a creep stage, with {self.rest_s:g} s of rest after every "
                f"play; holding the present output {wait_s:.1f} s so that this play starts as they did")

    def note(self, now_unix_s: float | None = None) -> str | None:
        """One line for the run when more than :data:`AS_RECORDED_FRESH_S` has passed, else None."""
        elapsed = (time.time() if now_unix_s is None else now_unix_s) - self.ended_unix_s
        if not self.axes or elapsed <= AS_RECORDED_FRESH_S:
            return None
        return (f"{', '.join(self.axes)}: learned without a creep stage {elapsed:.0f} s ago, for a play "
                f"{self.rest_s:g} s after the learning's last: the creep of its plays has moved on since, and the error grows with the wait "
                f"(e727_tcp on the simulated E-727: 2 nm right after, 7 nm after 10 s of rest, 10 nm after 30 s); play it right "
                f"after afmctl learn, or learn with a model that has a creep stage (afmctl calibrate)")


@dataclass(frozen=True)
class HistoryAfter:
    """The history term [nm] ``term_nm`` (D, N, 3) of a play of the learned table that
    starts ``delays_s[d]`` after the learning's last play ended at ``ended_unix_s`` (wall
    clock, s since the epoch)."""

    delays_s: tuple[float, ...]
    term_nm: np.ndarray
    ended_unix_s: float

    def at(self, elapsed_s: float) -> np.ndarray:
        """The term (N, 3) [nm] ``elapsed_s`` after the last play: linear between the kept
        delays, the first before them; zero after the last (rested, :data:`AFTER_S`)."""
        d = np.asarray(self.delays_s, dtype=float)
        if float(elapsed_s) > d[-1]:
            return np.zeros(self.term_nm.shape[1:])
        t = max(float(elapsed_s), d[0])
        k = int(np.clip(np.searchsorted(d, t, side="right") - 1, 0, d.size - 2)) if d.size > 1 else 0
        if d.size == 1:
            return np.array(self.term_nm[0])
        w = (t - d[k]) / (d[k + 1] - d[k])
        return (1.0 - w) * self.term_nm[k] + w * self.term_nm[k + 1]


def history_after(terms: dict[str, np.ndarray], rows: int, ended_unix_s: float,
                  delays_s: tuple[float, ...] = AFTER_S) -> HistoryAfter | None:
    """The :class:`HistoryAfter` of per-axis terms (D, N) [nm]; None without any."""
    if not terms:
        return None
    out = np.zeros((len(delays_s), rows, 3))
    for axis, term in terms.items():
        out[:, :, "xyz".index(axis)] = term
    return HistoryAfter(tuple(float(d) for d in delays_s), out, float(ended_unix_s))


def corrected_for_history(table: WaveTable, after: HistoryAfter | None, config: Any,
                          now_unix_s: float | None = None, as_recorded: AsRecorded | None = None) -> WaveTable:
    """``table`` with the history term of the learning's plays taken out for a play
    starting now (module docstring), one report line per corrected axis, and the line (and a
    warning) of :meth:`AsRecorded.note` for axes learned without a creep stage; ``table``
    itself when there is nothing to take out or say (no term kept, an in-process simulator,
    a term below :data:`NEGLIGIBLE_NM`, a table played soon enough)."""
    if config.simulation.enabled:
        return table
    now = time.time() if now_unix_s is None else now_unix_s
    report = list(table.report)
    u = table.u_V if after is None else _history_taken_out(table.u_V, after, config, now, report)
    note = as_recorded.note(now) if as_recorded is not None else None
    if note is not None:
        log.warning("%s", note)
        report.append(note)
    if report == table.report:
        return table
    return WaveTable(table.target_nm, table.corrected_nm, table.drift_nm, u, table.T_C, table.pad, report)


def take_out(u_V: np.ndarray, term_nm: np.ndarray, model: Any, dt_s: float) -> np.ndarray:
    """The column ``u_V`` [V] with a history term ``term_nm`` [nm] per row taken out through
    ``model``'s static part (module docstring): ``u + S⁻¹(S(u) − Δy) − S⁻¹(S(u))``."""
    from afmctl.compensators.learning_laws import static_ops
    forward, inverse = static_ops(model, dt_s)
    x = forward().block(np.ascontiguousarray(u_V, dtype=np.float64))
    return u_V + inverse().block(np.ascontiguousarray(x - term_nm)) - inverse().block(x)


def _history_taken_out(u_V: np.ndarray, after: HistoryAfter, config: Any, now_unix_s: float,
                       report: list[str]) -> np.ndarray:
    """``u_V`` (N, 3) [V] with the term ``after`` keeps for a play starting at ``now_unix_s``
    taken out through each axis's model's static part; a line per corrected axis appended
    to ``report``."""
    from .pipeline import axis_models
    elapsed = max(0.0, now_unix_s - after.ended_unix_s)
    term = after.at(elapsed)
    models = axis_models(config)[0]
    u = u_V.copy()
    for k, axis in enumerate("xyz"):
        model = models[k][0]
        if model is None or float(np.max(np.abs(term[:, k]))) < NEGLIGIBLE_NM:
            continue
        u[:, k] = take_out(u[:, k], term[:, k], model, config.dt_s)
        report.append(f"{axis}: the learning's plays ended {elapsed:.0f} s ago and still creep: their history term "
                      f"{float(np.mean(term[:, k])):+.1f} nm (mean; the model's) is taken out, assuming nothing else "
                      "played since")
    return u
