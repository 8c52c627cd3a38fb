"""``afmctl learn --config``: learn a scan's voltages on a device that records its own
motion — play the table on the amplifier's clock, read the scanner's measured motion back
through the device's data recorder, compute the next table, repeat.

One iteration (:meth:`LearnRun.iterate`), in named steps:

1. ``check`` — the table is checked before anything is sent: every driven column finite,
   inside the configured limits and within the slew limit per sample, and short enough for
   the recorder (the wave player checks it again against the device's capacity);
2. ``play`` — a :class:`afmctl.control.controller.Controller` plays the table exactly as
   ``afmctl run`` plays a learned table (``output = "wave"``: the upload, approach ramp and
   settle hold, the table on the amplifier's clock, the finish ramp), with every safety
   check of a run; ``arm``: once the table is on the device and before the approach ramp,
   the device's recorder is armed (it starts with the wave generator or the stream) to record the measured position and the output of
   the learned axes, one point per table row
   (:meth:`afmctl.drivers.base.Amplifier.configure_recorder`); a stop or an
   estop during the play stops the device (wave generator stopped, FIFO flushed) and ramps
   within the slew limit, and learning ends with the best table so far;
3. ``read`` — the recording is read back and refused (not learned from) unless it holds one
   point per row of the whole table and the output voltages it recorded are the table's
   (no trigger offset), and unless its lag behind the prediction stays below
   :data:`MAX_LAG_SHARE` of the table;
4. ``learn`` — per learned axis the :class:`afmctl.compensators.learning.Learner` (the
   configured model as the learning filter, or the model-free law) gives the next column.
   An in-process simulator is brought to rest before every play (``LearnOptions.rest``),
   as ``afmctl run`` starts on a fresh one: no play carries a history. On a device, an
   axis whose model has a creep stage has its recording first freed of its *history
   term*: what the model says the axis's voltages before this play (the earlier plays,
   ramps and uploads) add to it, relative to a play from rest
   (:mod:`afmctl.compensators.learning_history`; the creep of the earlier plays). The
   table is so learned for a play from rest, and ``afmctl run`` takes out what the plays
   still add when it plays (:mod:`afmctl.control.learned_after`).
   The first play is not like the later ones (the scanner's state before learning began
   is unknown to the model): after the
   first iteration the first table is played once more (``calibrate``), and what the
   scanner moved between the two plays of one table — only the history differs — less
   what the model's history term says is the term's *offset* per axis, added from the
   second play on (:func:`history_offset_nm`). On the default simulated scanner with the
   demo's model it is 6 nm on the CAN amplifier and under 1 nm on the E-727. An axis
   without a creep stage learns from its recordings as they are: its table is right for
   the play that follows the learning's, as ``afmctl run`` right after meets it.

When learning ends (not on a stop), the learned table is played once more as ``afmctl
run`` plays it (:meth:`LearnRun.replay`, step ``replay``): each axis's best play is the
smallest of several noisy figures, and this play's figures are the ones a run meets.

Each axis is learned and judged on its own (:mod:`afmctl.control.learn_axes`): an axis
finishes — it plays its best column from then on — when its error over the judged part is
at the noise floor (``noise_floor_pct``), when it stopped improving, or when its learner's
guard stops it (error rising twice, or a model whose phase is more than 90° off where the
error lies). A raster's slow axis is weighted and judged on the raster's lines, as
``afmctl run`` judges it. Learning ends when every axis has finished, after
``iterations``, or on a stop. The result is made of each axis's best column *measured*,
as a :class:`LearnedTable` that ``afmctl run`` plays (``[trajectory] kind = "learned"``).
Units: nm, V, s; errors in nm and in % of each axis's line or step (or of its span when its
target has no lines).

One job per class: :class:`LearnRun` iterates and decides (stop rules, the learned table);
:class:`~afmctl.control.learn_setup.LearnSetup` holds what it starts from (the configuration
checked, the models, the first table, the learners);
:class:`~afmctl.control.learn_axes.AxisBook` keeps each axis's figures and best column;
:class:`~afmctl.control.learn_play.TablePlayer` plays a table and reads the recording back
(steps check, arm, play, read); :class:`~afmctl.control.learn_history.HistoryTerms` keeps
what each play's history adds to its recording (step calibrate).
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from afmctl.compensators.learning import KEEPING, Learner, LearnSettings
from afmctl.compensators.learning_history import creep_stages

from ..data.axis_errors import ErrorReport, axis_errors
from ..errors import AfmctlError
from .learn_axes import AxisBook
from .learn_history import (HistoryTerms, PlayTimeline, calibration_history, history_offset_nm,  # noqa: F401
                            settle_advice, with_learning_hold)
from .learn_play import (OUTPUT_TOL_V, RecordingRefused, Step, TablePlayer, arm_recorder,  # noqa: F401
                         play_recorded, read_aligned, read_at_sample_start)
from .learn_setup import MIN_SPAN_NM, SLEW_RESERVE, LearnSetup  # noqa: F401 (re-exported)
from .learned_after import AFTER_S, AS_RECORDED_REST_S, AsRecorded, HistoryAfter, corrected_for_history, history_after
from .learned_table import LearnedTable, make_learned
from .wave_plan import WaveTable, driven_steps_ok

log = logging.getLogger(__name__)

#: a recording lagging the prediction by more than this share of the table is refused
MAX_LAG_SHARE = 0.25


def axis_metric(errors: dict[str, float]) -> float:
    """An axis's figure [%]: max over its judged lines, else over the central part of each
    line, else over the whole table."""
    for key in ("judged_max_pct", "central_max_pct", "max_pct"):
        if key in errors:
            return float(errors[key])
    return float("nan")


@dataclass(frozen=True)
class LearnOptions:
    """``iterations``: most tables to play; ``noise_floor_pct``: stop when the error over the
    central part of each line is at or below it [% of the line]; ``settings``: the learning
    law's (step size, weighting; limits are set from the configuration);
    ``use_model``: learn through the configured model (False: model-free);
    ``record_timeout_s``: longest wait for a recording after the play [s];
    ``link_retries``: plays of the same table after a link fault (reconnected first);
    ``replay``: play the learned table once more at the end, as ``afmctl run`` plays it,
    and report that play's figures (:attr:`LearnRun.replayed`);
    ``history_term``: with a model, learn from the recording minus the history term
    (module docstring, step ``learn``); ``rest``: called before every play to bring an
    in-process simulated scanner to rest (:meth:`afmctl.sim_backend.scanner.Scanner.rest`),
    so that every play starts as ``afmctl run`` starts on a fresh simulator — then no play
    carries a history and no term is taken out (None: a device, which keeps its state)."""

    iterations: int = 10
    noise_floor_pct: float = 0.0
    settings: LearnSettings = field(default_factory=LearnSettings)
    use_model: bool = True
    record_timeout_s: float = 30.0
    link_retries: int = 2
    history_term: bool = True
    rest: Callable[[], None] | None = None
    replay: bool = True


@dataclass
class IterationReport:
    """One played table: ``iteration`` (0: the model's table), per learned axis the error
    figures of :func:`afmctl.compensators.learning_weights.error_figures` (the learning
    law's own: % of the axis's span and of the lines it finds in that axis's target),
    ``judged``: the errors a user checks (:func:`afmctl.data.axis_errors.axis_errors`: per
    axis in nm and % of its line or step, over the central part of the raster's lines, as
    ``afmctl run`` reports them), ``metric_pct`` (the worst axis's max % of ``judged``), the next step's ``rho``, the
    recording's ``lag_samples``, ``state`` (learning / converged / stopped / diverged /
    fault), ``detail``, ``history_nm``: the largest history term taken out of the
    recording [nm] (0 without a model), and ``history_offset_nm``: its offset as measured
    (:func:`history_offset_nm`; the largest of the axes')."""

    iteration: int
    errors: dict[str, dict[str, float]]
    metric_pct: float
    rho: float | None = None
    lag_samples: float = 0.0
    state: str = "learning"
    detail: str = ""
    history_nm: float = 0.0
    history_offset_nm: float = 0.0
    judged: ErrorReport | None = None

    def summary(self) -> dict[str, float | None]:
        """The figures of the worst axis (the largest max % of ``judged``), all from that
        one axis, as :class:`afmctl.zenoh_api.messages.LearnMsg` takes them: ``max_pct`` /
        ``rms_pct`` over the whole table in % of its span, ``central_*`` over the judged part
        in % of its line or step."""
        keys = ("max_pct", "rms_pct", "central_max_pct", "central_rms_pct")
        if not self.errors:
            return dict.fromkeys(keys)
        axis = self.worst_axis()
        out: dict[str, float | None] = {k: self.errors[axis].get(k) for k in keys[:2]}
        a = self.judged.axis(axis) if self.judged is not None else None
        out["central_max_pct"] = a.max_pct if a is not None else None
        out["central_rms_pct"] = a.rms_pct if a is not None else None
        return out

    def worst_axis(self) -> str:
        """The learned axis with the largest max error in % (of ``judged``, else of the
        learning law's figures)."""
        def pct(axis: str) -> float:
            a = self.judged.axis(axis) if self.judged is not None else None
            if a is not None and a.max_pct is not None:
                return a.max_pct
            return self.errors[axis]["max_pct"]
        return max(self.errors, key=pct)


def judged_errors(target_nm: np.ndarray, measured_nm: dict[str, np.ndarray]) -> ErrorReport:
    """The per-axis errors a user checks (:func:`afmctl.data.axis_errors.axis_errors`) of
    the measured position [nm] per learned axis (``measured_nm``, the history term taken
    out: the play from rest ``afmctl run`` makes) against the table's target (N, 3) [nm]."""
    pos = np.array(target_nm, dtype=float)
    for axis, y in measured_nm.items():
        pos[:, "xyz".index(axis)] = y
    return axis_errors(target_nm, pos, "".join(a for a in "xyz" if a in measured_nm))


class LearnRun:
    """Learning on one open amplifier (module docstring): iterations and stop rules; its
    start (configuration checked, models, first table, learners) in a :class:`LearnSetup`,
    each axis's figures and best column in an :class:`AxisBook`, the plays through a
    :class:`TablePlayer`, the history terms through :class:`HistoryTerms`. ``config``: the run's configuration (``amplifier.output =
    "wave"``, a finite trajectory); ``amplifier``: open, with a data recorder;
    ``on_iteration``: called with each :class:`IterationReport`."""

    def __init__(self, config: Any, amplifier: Any, options: LearnOptions | None = None,
                 on_iteration: Callable[[IterationReport], None] | None = None) -> None:
        self.config = with_learning_hold(config)
        self.amp = amplifier
        self.options = options or LearnOptions()
        self.on_iteration = on_iteration
        self.reports: list[IterationReport] = []
        #: the first table played to the end: the learned table is it with each axis's best column
        self.played: WaveTable | None = None
        self.book = AxisBook([])
        self.history = HistoryTerms(None, self.options.history_term and self.options.rest is None)
        self.setup = LearnSetup(self.config, amplifier, self.options.settings, self.options.use_model)
        #: the recorder's points per signal for the learned axes (asked before the first play)
        self._capacity: int | None = None
        #: the learned table played once more at the end (step ``replay``): its figures, as
        #: ``afmctl run`` measures them (None: not played, stopped or incomplete)
        self.replayed: ErrorReport | None = None
        #: axis → seconds since the calibration that wrote the model ended on this device,
        #: for the axes whose history starts from what it left (:meth:`PlayTimeline.resume`)
        self.after_calibration: dict[str, float] = {}
        self.spec = config.trajectory.model_dump(mode="json")
        self.player = TablePlayer(self.config, amplifier, self.spec, self._played, self.options.record_timeout_s,
                                  self.options.rest)

    @property
    def step(self) -> Step:
        """Where the iteration is (module docstring)."""
        return self.player.step

    @property
    def history_offsets(self) -> dict[str, float]:
        """Per axis the history term's measured offset [nm] (step ``calibrate``)."""
        return self.history.offsets

    # ------------------------------------------------------------------ the first table
    def recorder_models(self) -> tuple:
        """The models as the device's recorder sees the scanner (:class:`LearnSetup`)."""
        return self.setup.recorder_models()

    def first_table(self) -> WaveTable:
        """The configured compensation's table for the trajectory (:class:`LearnSetup`)."""
        return self.setup.first_table()

    def learners(self, table: WaveTable) -> dict[str, Learner]:
        """One learner per axis whose target moves (:meth:`LearnSetup.learners`); each
        axis's book, and the history of the axes whose model has a creep stage."""
        out = self.setup.learners(table)
        self.book = AxisBook(list(out))
        models = self.setup.learned_models()
        with_model = {a: models["xyz".index(a)] for a in out if creep_stages(models["xyz".index(a)])}
        if self.history.enabled and with_model:
            peak = {a: float(np.max(table.u_V[:, "xyz".index(a)])) for a in with_model}
            self.history.timeline = PlayTimeline(self.config, with_model,
                                                 self.setup.present_output(list(with_model)), peak)
            self.after_calibration = self.history.timeline.resume(calibration_history(self.config))
        self.player.spaced_axes = self._as_recorded_axes()
        return out

    # ------------------------------------------------------------------ iterations
    def run(self) -> LearnedTable:
        """Iterate until converged, stopped or done; the best measured table, learned."""
        table = self.first_table()
        learners = self.learners(table)
        for k in range(self.options.iterations + 1):
            report, table_next = self.iterate(k, table, learners)
            self.reports.append(report)
            if self.on_iteration is not None:
                self.on_iteration(report)
            if report.state != "learning" or table_next is None or k == self.options.iterations:
                break
            if k == 0:
                self.calibrate(table, list(learners))
            table = table_next
        if self.played is None:
            raise AfmctlError("learn: no table was played to the end; nothing learned")
        history = [{"iteration": r.iteration, "metric_pct": r.metric_pct, "state": r.state, **r.summary()}
                   for r in self.reports]
        best = self.book.best_table(self.played)
        self.replayed = self.replay(best)
        return make_learned(self.config, best, self.spec, history, self._after(best), self._as_recorded())

    def _as_recorded(self) -> AsRecorded | None:
        """The axes learned on a device from their recordings as they are (no model's creep
        stage), with when the last play ended (:class:`AsRecorded`); None on an in-process
        simulator (every play from rest) or when every axis has a creep stage."""
        axes = self._as_recorded_axes()
        if not axes or self.player.ended_unix_s is None:
            return None
        return AsRecorded(axes, self.player.ended_unix_s, AS_RECORDED_REST_S)

    def _as_recorded_axes(self) -> tuple[str, ...]:
        """The learned axes without a model's creep stage, on a device (none on an
        in-process simulator, where every play starts from rest)."""
        if self.options.rest is not None:
            return ()
        timeline = self.history.timeline
        return tuple(a for a in self.book.axes if timeline is None or a not in timeline.now)

    def replay(self, best: WaveTable) -> ErrorReport | None:
        """Step ``replay``: the learned table played once more as ``afmctl run`` plays it
        — on an in-process simulator from rest, on a device with what the learning's plays
        still add taken out (:func:`corrected_for_history`) — and judged as ``afmctl run``
        judges it, with nothing taken out of the recording. The best plays' figures are the
        smallest of several noisy ones; this one is what a run meets. On a device it starts
        :data:`AS_RECORDED_REST_S` after the last play, no sooner than a run can (the README
        tour's table, with a creep stage: 2.7 nm replayed 0.3 s after, 1.8 nm in the run
        about 3 s after). None when learning was stopped or ended on a fault, or the play
        did not complete."""
        ended = self.reports[-1].state if self.reports else "fault"
        if not self.options.replay or self.player.stopping or ended in ("fault", "stopped"):
            return None
        if self.options.rest is None:       # on a device: no sooner than afmctl run can start
            self.player.rest_after_last_play(AS_RECORDED_REST_S)
        table = corrected_for_history(best, self._after(best), self.config)
        try:
            self._check(table)
        except AfmctlError as err:
            log.warning("learn: the learned table is not played once more: %s", err)
            return None
        self.player.step = Step.REPLAY
        got = self.player.play_and_read(table, list(self.book.axes))
        if not isinstance(got, dict):
            log.warning("learn: the learned table's last play did not complete (%s)", got[1])
            if got[0] == "fault" and not self.player.stopping:
                self.player.reconnect()
            return None
        return judged_errors(best.target_nm, got)

    def _after(self, best: WaveTable) -> HistoryAfter | None:
        """What the plays leave after them for a play of ``best``
        (:mod:`afmctl.control.learned_after`), with a model's creep stage."""
        timeline = self.history.timeline
        if timeline is None or not self.history.enabled:
            return None
        columns = {a: best.u_V[:, "xyz".index(a)] for a in timeline.now}
        return history_after(timeline.after(columns, AFTER_S), len(best), timeline.ended_unix_s())

    def iterate(self, k: int, table: WaveTable, learners: dict[str, Learner]
                ) -> tuple[IterationReport, WaveTable | None]:
        """Steps check → play (arm) → read → learn of iteration ``k`` (module docstring). A
        link fault during the play or the read-back reconnects and plays the table again,
        at most ``link_retries`` times."""
        self.player.step = Step.CHECK
        self._check(table)
        ended = ("fault", "no play")
        for attempt in range(self.options.link_retries + 1):
            got = self.player.play_and_read(table, list(learners))
            if isinstance(got, dict):
                self.player.step = Step.LEARN
                return self._learn(k, table, learners, got)
            ended = got
            if got[0] != "fault" or attempt == self.options.link_retries or self.player.stopping:
                break
            log.warning("learn: iteration %d: %s; reconnecting and playing the table again", k, got[1])
            self.player.reconnect()
        return IterationReport(k, {}, float("nan"), state=ended[0], detail=ended[1]), None

    def calibrate(self, table: WaveTable, axes: list[str]) -> None:
        """Step ``calibrate`` (module docstring): play the first table once more and
        measure the history term's offset of each axis with a model's creep stage. A play
        that does not complete (a fault, a stop) leaves the terms as the model gives them."""
        if not self.history.wants_calibration:
            return
        self.player.step = Step.CALIBRATE
        got = self.player.play_and_read(table, axes)
        if not isinstance(got, dict):
            log.warning("learn: the first table's second play did not complete (%s); the model's history term is "
                        "used as it is", got[1])
            if got[0] == "fault" and not self.player.stopping:
                self.player.reconnect()
            return
        self.history.calibrate(got)

    def _played(self, table: WaveTable, rows: int, times: dict[str, float]) -> None:
        self.history.played({a: table.u_V[:, "xyz".index(a)] for a in self.setup.axes}, rows, times)

    def _check(self, table: WaveTable) -> None:
        if self._capacity is None:          # asked once, before the first play (a link may be down later)
            self._capacity = int(self.amp.recorder_capacity(self.setup.axes))
        capacity = self._capacity
        if len(table) > capacity:
            raise AfmctlError(f"learn: the table's {len(table)} rows do not fit the {self.config.amplifier.driver} "
                              f"recorder's {capacity} points per signal; nothing was played (shorten the trajectory "
                              "or lower loop.rate_Hz)")
        setup = self.setup
        start = table.u_V[0, ["xyz".index(a) for a in setup.axes]]
        if not driven_steps_ok(table.u_V, setup.axes, setup.limits_V, setup.max_step_V / (1.0 - SLEW_RESERVE), start):
            raise AfmctlError("learn: the next table breaks the limits or the slew limit; nothing was sent")

    def _learn(self, k: int, table: WaveTable, learners: dict[str, Learner], measured: dict[str, np.ndarray]
               ) -> tuple[IterationReport, WaveTable | None]:
        nxt = WaveTable(table.target_nm, table.corrected_nm, table.drift_nm, table.u_V.copy(), table.T_C, table.pad,
                        list(table.report))
        terms = {a: self.history.term(a, k, measured[a].shape) for a in learners}
        if k == 0:
            self.history.first_play(measured, terms)
        judged = judged_errors(table.target_nm, {a: measured[a] - terms[a] for a in learners})
        self.book.record(k, table, judged)
        if self.played is None:
            self.played = table
        errors, rhos, lags = {}, [], []
        learning = self.book.learning()
        for axis, learner in learners.items():
            c = "xyz".index(axis)
            res = learner.step(table.u_V[:, c], measured[axis] - terms[axis])
            if abs(res.lag_samples) > MAX_LAG_SHARE * len(table):
                raise RecordingRefused(f"learn: the recording of axis {axis} lags the table by "
                                       f"{res.lag_samples:.0f} samples (trigger?); not learned from")
            errors[axis] = res.errors
            lags.append(res.lag_samples)
            if axis in learning:
                rhos.append(res.rho_median)
                nxt.u_V[:, c] = res.u_next_V
                if res.stopped:
                    # the book keeps its own best column (max nm judged), not the learner's
                    self.book.finish(axis, res.reason.split(KEEPING)[0], diverged=learner.diverging)
        metric = judged.worst_pct()
        if metric != metric:      # no learned axis has a length to refer to: the law's own figure
            metric = max(axis_metric(e) for e in errors.values())
        report = IterationReport(k, errors, metric, float(np.median(rhos)) if rhos else None,
                                 float(max(lags, key=abs)),
                                 history_nm=max((float(np.max(np.abs(d))) for d in terms.values()), default=0.0),
                                 history_offset_nm=max(self.history.offsets.values(), key=abs, default=0.0),
                                 judged=judged)
        self._finish_axes(judged, learners, learning)
        finished = [a for a in learning if self.book.axes[a].done]
        for axis in self.book.axes:
            if self.book.axes[axis].done:
                nxt.u_V[:, "xyz".index(axis)] = self.book.best_column(axis)
        if self.book.all_done():
            report.state = "diverged" if self.book.any_diverged() else "converged"
            report.detail = self.book.done_text()
            return report, None
        report.detail = self.book.done_text(finished)
        return report, nxt

    def _finish_axes(self, judged: ErrorReport, learners: dict[str, Learner], learning: list[str]) -> None:
        """Each axis that still learns finishes (keeps its best column) when its error is
        at ``noise_floor_pct`` or, without one, stopped improving (:class:`AxisBook`)."""
        floor_pct = self.options.noise_floor_pct
        for axis in learning:
            progress = self.book.axes[axis]
            if progress.done:
                continue
            pct = judged.axis(axis).max_pct
            if floor_pct > 0.0 and pct is not None and pct <= floor_pct:
                self.book.finish(axis, f"at the noise floor ({pct:.3g} % <= {floor_pct:g} %)")
            elif floor_pct <= 0.0 and progress.stalled():
                floor = learners[axis].floor()
                self.book.finish(axis, "no further improvement in two iterations; the floor: "
                                 + (floor.phrase if floor is not None else "not named (no step learned)"))

    # ------------------------------------------------------------------ requests
    def stop(self) -> None:
        """End learning: the table playing (if any) stops as a run stops; the best table so
        far is the result."""
        self.player.stop()

    def estop(self) -> None:
        """Emergency stop: the device stops at once (FIFO flushed / generator stopped) and the
        output ramps to the safe value at the slew limit; learning ends."""
        self.player.estop()
