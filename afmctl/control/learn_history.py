"""The voltage history of a learn run, play by play, for the history term of each
recording (:mod:`afmctl.compensators.learning_history`).

A play as :class:`afmctl.control.controller.Controller` makes it with ``output = "wave"``:
the output holds where the last play left it, ramps to the table's first row at the ramp
rate (``safety.ramp_V_per_s``, capped by the slew limit) once the table is uploaded (the
output rests meanwhile), holds there for ``amplifier.settle_s``, plays the table on the
device's clock, holds until the host sees the end, then
ramps to the safe value (``safety.on_finish = "safe"``) or holds. :class:`PlayTimeline`
rebuilds that per learned axis from host clock readings per play
(:attr:`afmctl.control.controller.Controller.wave_times`: the approach's start and end — on
a serial link host setpoints at the loop rate run late, so the ramp takes longer than its
rate says —, and the device's start) and gives, per play, the history
term relative to the *reference*: a play from rest at the voltage the axis had when
learning began — how ``afmctl run`` plays the learned table from a fresh start. Units: V, s,
nm.
"""
from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from afmctl.compensators.learning_history import SETTLE_S, VoltageHistory, history_term_nm

from ..config import LEARN_SETTLE_S

log = logging.getLogger(__name__)

#: a calibration's history is taken up only when the output is still within this of where
#: the calibration left it [V] (:meth:`PlayTimeline.resume`)
RESUME_TOL_V = 0.5


class PlayTimeline:
    """Per axis of ``models`` (axis → model with ``forward``) the history since learning
    began, the axis at rest at ``start_V`` (axis → V) before, with the hysteresis memory of
    a descent from ``peak_V`` (axis → V: the first table's highest voltage); ``config``:
    the run's."""

    def __init__(self, config: Any, models: dict[str, Any], start_V: dict[str, float],
                 peak_V: dict[str, float] | None = None) -> None:
        self.dt_s = float(config.dt_s)
        self.rate_V_per_s = min(float(config.safety.ramp_V_per_s), float(config.slew_V_per_s()))
        self.finish_safe = config.safety.on_finish == "safe"
        self.settle_s = config.amplifier.hold_s(unset=LEARN_SETTLE_S)
        self.safe_V = {a: config.safety.safe_value(a) for a in models}
        peak = peak_V or {}
        self.rest = {a: VoltageHistory(m, self.dt_s, start_V[a], peak_V=peak.get(a)) for a, m in models.items()}
        self.now = {a: h.copy() for a, h in self.rest.items()}
        self.t_last_s = time.monotonic()

    def played(self, u_V: dict[str, np.ndarray], times: dict[str, float], rows: int) -> dict[str, np.ndarray]:
        """Advance every axis through one play of its column ``u_V[axis]`` (``rows`` of it
        played); ``times``: host clock readings [s] of :func:`time.monotonic` — the approach
        began (``approach``), the settle hold began (``settle``), the device was told to
        start (``start``), saw the table end (``end``) and the finish ended (``finished``;
        without these two the finish ramp follows the last row at the ramp rate). The
        history term [nm] of this play per axis, over the whole column, against a play from
        rest with the nominal approach ramp and settle hold."""
        ramp_s = max(0.0, times["settle"] - times["approach"])
        hold_s = max(0.0, times["start"] - times["settle"])
        terms: dict[str, np.ndarray] = {}
        for axis, u in u_V.items():
            h = self.now[axis]
            h.hold(times["approach"] - self.t_last_s)      # rested, the table uploaded
            h.ramp_over(float(u[0]), ramp_s)
            h.hold(hold_s)
            reference = self.rest[axis].copy()           # as afmctl run plays: nominal ramp and settle
            reference.ramp(float(u[0]), self.rate_V_per_s)
            reference.hold(self.settle_s)
            terms[axis] = history_term_nm(h, reference, u)
            h.play(u[:rows])
            self._finish(h, axis, times, rows * self.dt_s)
        if "end" in times and "finished" in times:
            self.t_last_s = times["finished"]
        else:
            last = max((abs(float(u[max(rows, 1) - 1]) - self.safe_V[a]) for a, u in u_V.items()), default=0.0)
            finish_s = last / self.rate_V_per_s if self.finish_safe else 0.0
            self.t_last_s = times.get("end", times["start"] + rows * self.dt_s) + finish_s
        return terms

    def after(self, u_V: dict[str, np.ndarray], delays_s: tuple[float, ...]) -> dict[str, np.ndarray]:
        """Per axis the history term [nm] ``(len(delays_s), N)`` of a play of its column
        ``u_V[axis]`` that starts each delay [s] after the last play ended (the output held
        meanwhile; the approach ramp at the nominal rate and the settle hold, as ``afmctl
        run`` plays it), against the play from rest: what the learning's own plays still
        add when ``afmctl run`` plays the learned table that long after, on a device that
        kept its state."""
        out: dict[str, np.ndarray] = {}
        for axis, u in u_V.items():
            h = self.now[axis].copy()
            reference = self.rest[axis].copy()
            reference.ramp(float(u[0]), self.rate_V_per_s)
            reference.hold(self.settle_s)
            rows, waited = [], 0.0
            for delay in delays_s:
                h.hold(delay - waited)
                waited = delay
                play = h.copy()
                play.ramp(float(u[0]), self.rate_V_per_s)
                play.hold(self.settle_s)
                rows.append(history_term_nm(play, reference, u))
            out[axis] = np.array(rows)
        return out

    def ended_unix_s(self) -> float:
        """When the last play ended (its finish ramp), on the wall clock [s since the epoch]."""
        return time.time() - (time.monotonic() - self.t_last_s)

    def _finish(self, h: VoltageHistory, axis: str, times: dict[str, float], played_s: float) -> None:
        """After the last row (``played_s`` [s] after the start): held until the host saw
        the end (``end``), then the finish ramp to the safe value until ``finished`` (at the
        ramp rate when those were not read)."""
        if "end" in times:
            h.hold(times["end"] - times["start"] - played_s)
        if not self.finish_safe:
            return
        if "end" in times and "finished" in times:
            h.ramp_over(self.safe_V[axis], times["finished"] - times["end"])
        else:
            h.ramp(self.safe_V[axis], self.rate_V_per_s)

    def resume(self, prior: dict[str, dict[str, Any]]) -> dict[str, float]:
        """Start the history of each axis from what a calibration left (``prior``: axis →
        the ``history`` entry of the model's provenance, :func:`calibration_history`): its
        model's creep lag states when the calibration ended, then the output held at the
        present voltage until now. An axis is left at rest when the calibration ended more
        than :data:`SETTLE_S` ago, in the future, or at another voltage than the present
        output (something moved it since). Returns axis → seconds since it ended."""
        taken: dict[str, float] = {}
        for axis, h in self.now.items():
            ago = resume_calibration(h, prior.get(axis))
            if ago is not None:
                taken[axis] = ago
        return taken

    def rested(self, t_s: float) -> None:
        """Nothing played until ``t_s`` (host clock): the outputs held."""
        for h in self.now.values():
            h.hold(t_s - self.t_last_s)
        self.t_last_s = t_s


def resume_calibration(h: VoltageHistory, entry: dict[str, Any] | None) -> float | None:
    """``h`` (an axis at rest at its present output) continued from a calibration's
    ``history`` entry (:func:`calibration_history`): its model's creep lag states when the
    calibration ended, then the output held until now. Not taken (None, ``h`` unchanged)
    when it ended more than :data:`SETTLE_S` ago or in the future, at another voltage than
    the present output (something moved it since), or for other lags. Returns the seconds
    since it ended."""
    if not entry:
        return None
    try:
        ago = time.time() - float(entry["ended_unix_s"])
        at_V = float(entry["at_V"])
        state = [float(z) for z in entry["creep_state_nm"]]
    except (KeyError, TypeError, ValueError):
        return None
    if 0.0 <= ago < SETTLE_S and abs(at_V - h.last_V) <= RESUME_TOL_V and h.resume(state, h.last_V):
        h.hold(ago)
        return ago
    return None


def calibration_history(config: Any) -> dict[str, dict[str, Any]]:
    """Per axis what the calibration that wrote the configuration's ``scanner_model`` left
    in the model's creep stage (``provenance.history``,
    :meth:`afmctl.api.calibrate.Calibration._history`), when it ran on the device this
    configuration drives (same driver and port; not an in-process simulator, which starts
    at rest with every command); else empty."""
    scanner_file = config.compensation.scanner_model
    if not scanner_file:
        return {}
    try:
        prov = json.loads(Path(scanner_file).read_text(encoding="utf-8")).get("provenance") or {}
        device, history = prov.get("device") or {}, prov.get("history") or {}
    except (OSError, ValueError, AttributeError):
        return {}
    if not isinstance(device, dict) or not isinstance(history, dict):
        return {}
    same = (device.get("driver") == config.amplifier.driver and device.get("port") == str(config.amplifier.port)
            and not device.get("simulated") and not config.simulation.enabled)
    return {a: h for a, h in history.items() if isinstance(h, dict)} if same else {}


def history_offset_nm(moved_nm: np.ndarray, term_nm: np.ndarray) -> float:
    """The offset of a history term [nm]: the mean of what the scanner moved between two
    plays of one table (``moved_nm``: the second recording less the first [nm]) less what
    the model's history term says moved (``term_nm``: its change between the plays [nm])."""
    return float(np.mean(np.asarray(moved_nm, dtype=float) - np.asarray(term_nm, dtype=float)))


def settle_advice(config: Any) -> str | None:
    """One line when ``amplifier.settle_s`` is set shorter than
    :data:`~afmctl.config.LEARN_SETTLE_S` (a short hold leaves the approach's creep moving
    the scanner during the table, differently from play to play: the hold is host-timed)."""
    settle = config.amplifier.settle_s
    if settle is None or settle >= LEARN_SETTLE_S:
        return None
    return (f"amplifier.settle_s = {settle:g} s: the creep after each approach ramp still moves the scanner while the "
            f"table plays, a little differently every play; for plays that repeat to the sensor's noise (and "
            f"'afmctl run' repeating the learned error) hold {LEARN_SETTLE_S:g} s or more (the default when unset)")


def with_learning_hold(config: Any) -> Any:
    """``config``, or a copy of it holding :data:`~afmctl.config.LEARN_SETTLE_S` before each
    play when ``amplifier.settle_s`` is unset (the learned table records the hold, and
    ``afmctl run`` plays it with the same one)."""
    if config.amplifier.settle_s is not None:
        return config
    config = config.model_copy(deep=True)
    config.amplifier.settle_s = LEARN_SETTLE_S
    return config


class HistoryTerms:
    """What each play's history adds to its recording, per learned axis with a model's creep
    stage (the ``learn`` and ``calibrate`` steps of :mod:`afmctl.control.learn_run`): the
    model's history term from :class:`PlayTimeline` (None: no axis with a creep stage), plus
    its *offset* measured by playing the first table twice (:meth:`calibrate`). Other axes,
    and every axis when ``enabled`` is False: no terms (learning from the recordings as
    they are)."""

    def __init__(self, timeline: PlayTimeline | None, enabled: bool = True) -> None:
        self.timeline = timeline
        self.enabled = enabled
        self._terms: dict[str, np.ndarray] = {}
        self._first_play: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        #: per axis the history term's measured offset [nm] (step ``calibrate``)
        self.offsets: dict[str, float] = {}

    def played(self, u_V: dict[str, np.ndarray], rows: int, times: dict[str, float]) -> None:
        """A play (``rows`` of each column played; ``times``: the controller's ``wave_times``)
        into the voltage history; its term per axis."""
        self._terms = {}
        if self.timeline is None:
            return
        if not {"approach", "settle", "start"} <= set(times):   # nothing played: the outputs held (or ramped back)
            self.timeline.rested(time.monotonic())
            return
        self._terms = self.timeline.played({a: u_V[a] for a in self.timeline.now}, times, rows)

    def term(self, axis: str, k: int, shape: tuple[int, ...]) -> np.ndarray:
        """The history term [nm] of axis ``axis`` in iteration ``k``: the model's, offset as
        measured from the second play on (the first play is the one ``afmctl run``
        repeats from rest)."""
        offset = self.offsets.get(axis, 0.0) if k >= 1 else 0.0
        return np.broadcast_to(self._terms.get(axis, 0.0), shape) + offset

    def first_play(self, measured: dict[str, np.ndarray], terms: dict[str, np.ndarray]) -> None:
        """Keep the first play's recordings and terms of the axes with a model's creep stage
        (for :meth:`calibrate`). An axis without one is learned from its recordings as they
        are: nothing then says how its history decays after learning, so its table is made
        for the play that follows the learning's plays on the same device, as ``afmctl run``
        plays it there (a term measured once, against the first play, would stay in the table
        and show as an offset of that size in every run)."""
        if self.enabled and self.timeline is not None:
            self._first_play = {a: (measured[a].copy(), terms[a]) for a in terms if a in self.timeline.now}

    @property
    def wants_calibration(self) -> bool:
        return bool(self._first_play)

    def calibrate(self, again: dict[str, np.ndarray]) -> None:
        """The offsets from ``again`` (the first table's second play, per axis)."""
        for axis, (y0, h0) in self._first_play.items():
            moved, term = again[axis] - y0, self.term(axis, 0, y0.shape) - h0
            self.offsets[axis] = history_offset_nm(moved, term)
            log.info("learn: axis %s: the first table moved %.1f nm between its two plays where the model's history "
                     "term says %.1f nm: the term is offset by %+.1f nm", axis, float(np.mean(moved)),
                     float(np.mean(term)), self.offsets[axis])
