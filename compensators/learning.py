"""Iterative learning of a scan's voltages from its measured motion (sans-I/O).

AFM scans repeat: the same line, frame or ramp, thousands of times. :class:`Learner` holds
the target ``y_d`` [nm] of one repetitive trajectory and, per iteration, takes the
voltages sent ``u_k`` [V] and the motion measured ``y_k`` [nm] and returns the next
voltages ``u_{k+1}`` (:meth:`Learner.step` → :class:`LearnResult`):

1. *alignment* — the recording's lag behind the prediction (the model's, or the target's
   without a model) is estimated and reported
   (:func:`~afmctl.compensators.learning_spectra.estimate_lag_samples`); with
   ``align=True`` it is taken as a trigger offset and the recording shifted back by it
   (a plant's own delay is what the learning must compensate, so this is not the default);
2. *weighting* — the error ``e_k = y_d − y_k`` counts where accuracy matters
   (:func:`~afmctl.compensators.learning_weights.error_weights`: the central part of
   each raster line) and is judged
   (:func:`~afmctl.compensators.learning_weights.learning_weights`: nothing before the
   first judged line, no line between judged ones that is not judged itself);
3. *the law* — model-based (the identified chain as the learning filter) or model-free
   (the frequency response estimated from the iteration itself), equation (1) of
   :mod:`~afmctl.compensators.learning_laws`;
4. *limits* — the new table clipped to ``[u_min_V, u_max_V]`` and rate-limited to
   ``slew_V_per_s`` (:func:`~afmctl.compensators.dynamics_limits.rate_limit`; a periodic
   table includes the wrap from its last to its first sample): nothing beyond the limits
   is ever returned;
5. *guards* — the **divergence guard**: when the weighted error has risen on
   ``max_rises`` (2) iterations in a row, learning stops and the best table sent so far
   is returned; a table that did not beat the best is not learned from: the next one is
   learned from the best table with half the step (a quarter after two such, …; each
   better table gives one halving back); the
   **convergence check**: when the model's measured phase error
   exceeds 90° at learned harmonics that hold more than ``stall_share`` of the
   remaining weighted error, and the last table did not beat the best, the model-based
   law cannot converge there (``|1 − ρR| ≥ 1`` for every ρ > 0): learning stops and says
   so, keeping the best table.

The iteration state (:class:`LearnState`: history, best table, stop reason) is plain data
(:meth:`LearnState.to_dict` / :meth:`LearnState.from_dict`) so a command line can keep it
in a file between iterations; :meth:`Learner.reset` starts afresh.
"""
from __future__ import annotations

import hashlib
import logging
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from .base import ModelError
from .dynamics_limits import rate_limit
from .learning_laws import Increment, model_based_increment, model_free_increment, periodic_run
from .learning_spectra import Grid, estimate_lag_samples
from .learning_floor import Floor, name_floor
from .learning_noise import NO_NOISE, Noise, estimate_noise, noise_gain
from .learning_weights import (REPORT_CENTRAL_PCT, Line, error_figures, error_weights, find_lines, judged_lines,
                               learning_weights, line_span_nm, lines_mask, raster_lines, rounded_reference)

log = logging.getLogger(__name__)

LAWS = ("model", "model-free")
#: default largest step size per law: the model-based law measures the model's error and
#: sizes its steps from it; the model-free estimate of a hysteretic plant's response is
#: rougher (benchmarks/learning.py: ρ = 1 oscillates, 0.7 converges in about 8 steps)
DEFAULT_STEP = {"model": 1.0, "model-free": 0.7}
#: a rise of the judged error counts (towards the divergence guard) when it exceeds this
#: share of the noise's σ [% of the line]: the noise left in the figure scatters it
NOISE_TOLERANCE = 0.5
#: how a stop's reason names the table this learner keeps (its own best by its weighted
#: figure); a caller that keeps another table cuts the reason here
KEEPING = "; keeping the best table"


@dataclass(frozen=True)
class LearnSettings:
    """How the learner learns. ``rho_max``: largest step size (1 = a full inverse step;
    None: :data:`DEFAULT_STEP` of the law); ``q_cutoff_Hz``: the Q-filter's cut-off (None: the model's band limit, or the
    highest frequency the sent voltages excite without a model); ``central_pct``: the
    weighted share of each raster line [%] (100: no weighting); ``lines_only``: weight 0
    off the lines; ``periodic``: the table is played cyclically and recorded in steady
    state; ``u_min_V``/``u_max_V``/``slew_V_per_s``: the amplifier's limits;
    ``max_rises``: iterations of rising error in a row that stop learning; ``max_misses``:
    iterations in a row without a better table that stop it (the floor is reached);
    ``phase_limit_deg``: the convergence check's bound; ``stall_share``: the share of
    the weighted error energy beyond it that stops learning; ``align``: shift the
    recording by the estimated lag; ``turnaround_weight``: the weight of the error in the
    turnaround zones, where the target is replaced by its rounded copy
    (:func:`~afmctl.compensators.learning_weights.rounded_reference`)."""

    rho_max: float | None = None
    q_cutoff_Hz: float | None = None
    central_pct: float = REPORT_CENTRAL_PCT
    lines_only: bool = False
    periodic: bool = False
    u_min_V: float = -math.inf
    u_max_V: float = math.inf
    slew_V_per_s: float | None = None
    max_rises: int = 2
    max_misses: int = 4
    phase_limit_deg: float = 90.0
    stall_share: float = 0.5
    align: bool = False
    turnaround_weight: float = 1.0
    judge_lines: tuple[int, ...] | None = None

    def check(self) -> None:
        """:class:`ModelError` naming the first setting out of its range."""
        checks = [("rho_max", self.rho_max is None or 0 < self.rho_max <= 2, "0 < rho_max ≤ 2"),
                  ("q_cutoff_Hz", self.q_cutoff_Hz is None or self.q_cutoff_Hz > 0, "> 0 Hz"),
                  ("central_pct", 0 < self.central_pct <= 100, "0 < central_pct ≤ 100 %"),
                  ("u_min_V/u_max_V", self.u_min_V < self.u_max_V, "u_min_V < u_max_V"),
                  ("slew_V_per_s", self.slew_V_per_s is None or self.slew_V_per_s > 0, "> 0 V/s"),
                  ("max_rises", self.max_rises >= 1, "≥ 1"),
                  ("max_misses", self.max_misses >= 1, "≥ 1"),
                  ("phase_limit_deg", 0 < self.phase_limit_deg <= 180, "0 … 180°"),
                  ("stall_share", 0 < self.stall_share <= 1, "0 < stall_share ≤ 1"),
                  ("turnaround_weight", 0 <= self.turnaround_weight <= 1, "0 … 1")]
        for name, ok, allowed in checks:
            if not ok:
                raise ModelError(f"learning setting {name}: {getattr(self, name.split('/')[0])!r}; allowed {allowed}")


@dataclass
class LearnState:
    """What the learner carries between iterations: ``iteration`` (steps taken),
    ``history`` (one dict of error figures per step, of the table that was *sent*),
    ``best_u_V``/``best_metric_pct``/``best_iteration`` (the sent table with the least
    weighted error), ``rises`` (iterations of rising error in a row), ``misses``
    (iterations in a row that did not beat the best), ``halvings`` (how often the step is
    halved: one more per miss, one fewer per better table), ``stopped`` and
    ``reason``, ``target_digest`` (which target it belongs to), and the last iteration's
    table and recording ``previous_u_V``/``previous_y_nm`` (for the secant estimate of
    the model's error), ``best_y_nm`` (the best table's recording), and the model's error
    ``R`` measured so far on bins ``ratio_bins`` (``ratio_re`` + j ``ratio_im``)."""

    target_digest: str
    iteration: int = 0
    history: list[dict[str, float]] = field(default_factory=list)
    best_u_V: list[float] | None = None
    best_metric_pct: float = math.inf
    best_iteration: int = -1
    rises: int = 0
    misses: int = 0
    halvings: int = 0
    stopped: bool = False
    reason: str = ""
    previous_u_V: list[float] | None = None
    previous_y_nm: list[float] | None = None
    best_y_nm: list[float] | None = None
    ratio_bins: list[int] = field(default_factory=list)
    ratio_re: list[float] = field(default_factory=list)
    ratio_im: list[float] = field(default_factory=list)
    noise_nm: float | None = None
    noise_f_Hz: list[float] = field(default_factory=list)
    noise_psd_nm2: list[float] = field(default_factory=list)
    noise_source: str = ""
    floor: str = ""

    def noise(self) -> Noise | None:
        """The least noise measured so far (None before the first)."""
        if self.noise_nm is None:
            return None
        return Noise(self.noise_nm, np.asarray(self.noise_f_Hz or [0.0]), np.asarray(self.noise_psd_nm2 or [0.0]),
                     self.noise_source)

    def keep_noise(self, noise: Noise) -> Noise:
        """``noise``, or the smaller one measured before (deterministic differences between
        the lines only ever add to an estimate); kept."""
        old = self.noise()
        if old is not None and old.sigma_nm <= noise.sigma_nm:
            return old
        self.noise_nm, self.noise_source = float(noise.sigma_nm), noise.source
        self.noise_f_Hz, self.noise_psd_nm2 = noise.f_Hz.tolist(), noise.psd_nm2.tolist()
        return noise

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["best_metric_pct"] = None if not math.isfinite(self.best_metric_pct) else self.best_metric_pct
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "LearnState":
        """From :meth:`to_dict`'s output; :class:`ModelError` naming a bad field."""
        try:
            best = d.get("best_u_V")
            prev_u, prev_y, best_y = d.get("previous_u_V"), d.get("previous_y_nm"), d.get("best_y_nm")
            state = cls(target_digest=str(d["target_digest"]), iteration=int(d.get("iteration", 0)),
                        history=[{str(k): float(v) for k, v in h.items()} for h in d.get("history", [])],
                        best_u_V=None if best is None else [float(v) for v in best],
                        best_metric_pct=math.inf if d.get("best_metric_pct") is None else float(d["best_metric_pct"]),
                        best_iteration=int(d.get("best_iteration", -1)), rises=int(d.get("rises", 0)),
                        misses=int(d.get("misses", 0)), halvings=int(d.get("halvings", d.get("misses", 0))),
                        stopped=bool(d.get("stopped", False)), reason=str(d.get("reason", "")),
                        previous_u_V=None if prev_u is None else [float(v) for v in prev_u],
                        previous_y_nm=None if prev_y is None else [float(v) for v in prev_y],
                        best_y_nm=None if best_y is None else [float(v) for v in best_y],
                        ratio_bins=[int(v) for v in d.get("ratio_bins", [])],
                        ratio_re=[float(v) for v in d.get("ratio_re", [])],
                        ratio_im=[float(v) for v in d.get("ratio_im", [])],
                        noise_nm=None if d.get("noise_nm") is None else float(d["noise_nm"]),
                        noise_f_Hz=[float(v) for v in d.get("noise_f_Hz", [])],
                        noise_psd_nm2=[float(v) for v in d.get("noise_psd_nm2", [])],
                        noise_source=str(d.get("noise_source", "")), floor=str(d.get("floor", "")))
            if not len(state.ratio_bins) == len(state.ratio_re) == len(state.ratio_im):
                raise ValueError("ratio_bins, ratio_re and ratio_im differ in length")
            if len(state.noise_f_Hz) != len(state.noise_psd_nm2):
                raise ValueError("noise_f_Hz and noise_psd_nm2 differ in length")
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise ModelError(f"learning state: {err!r} is missing or malformed; delete the state file to start afresh") from None
        for name in ("best_u_V", "previous_u_V", "previous_y_nm", "best_y_nm", "ratio_re", "ratio_im", "noise_psd_nm2"):
            v = getattr(state, name)
            if v is not None and not np.all(np.isfinite(v)):
                raise ModelError(f"learning state: {name} holds non-finite values; delete the state file")
        return state


@dataclass(frozen=True)
class LearnResult:
    """One iteration: ``u_next_V`` [V] to send next (the best table when stopped), the
    sent table's error ``errors`` (:func:`error_figures`; % of the span, ``central_*`` over
    the central 80 % of each line, % of the line), the ``weighted_max_pct`` the guard
    watches, ``lag_samples`` (recording behind the prediction) and whether it was
    ``aligned``, the change ``du_max_V``/``du_rms_V`` [V], ``clipped``/``slew_limited``
    samples, the median step size over learned bins ``rho_median``, the Q cut-off
    ``q_cutoff_Hz``, the largest measured phase error at a learned harmonic
    ``phase_error_deg`` at ``phase_error_f_Hz``, ``stopped``/``reason``,
    ``best_iteration`` and ``law``; ``floor``: what a stop stands on (range / slew / noise /
    line rate / learning, :mod:`~afmctl.compensators.learning_floor`), ``noise_nm``: the
    recording's noise σ [nm] (not counted as error), ``judged``: which lines are judged."""

    u_next_V: np.ndarray
    iteration: int
    law: str
    errors: dict[str, float]
    weighted_max_pct: float
    lag_samples: float
    aligned: bool
    du_max_V: float
    du_rms_V: float
    clipped: int
    slew_limited: int
    rho_median: float
    q_cutoff_Hz: float
    phase_error_deg: float
    phase_error_f_Hz: float
    stopped: bool
    reason: str
    best_iteration: int
    floor: str = ""
    noise_nm: float = 0.0
    judged: str = ""


def target_digest(target_nm: np.ndarray, dt_s: float) -> str:
    """A short fingerprint of a target and its sample period."""
    h = hashlib.sha256(np.ascontiguousarray(target_nm, dtype=np.float64).tobytes())
    h.update(repr(float(dt_s)).encode())
    return h.hexdigest()[:16]


class Learner:
    """Learns the voltages of one target ``target_nm`` [nm] sampled at ``dt_s`` [s]
    (module docstring). ``model``: a chain (or static hysteresis) model, u [V] → y [nm];
    None: the model-free law. ``state``: continue from a saved :class:`LearnState`.
    ``lines``: the raster's lines (:func:`~afmctl.compensators.learning_weights.find_lines`
    of its fast axis's target) when this target is a slow axis of it: its error is then
    weighted and judged where the raster images, as ``afmctl run`` judges it, not on its
    own ramps (a trace-retrace raster's slow axis ramps during the retraces: on its own
    lines, the simulated E-727's y learned its ramps and left the traces 600 nm off); None:
    the lines found in ``target_nm``."""

    def __init__(self, target_nm: np.ndarray, dt_s: float, model: Any = None,
                 settings: LearnSettings | None = None, state: LearnState | None = None,
                 lines: list[Line] | None = None) -> None:
        self.target_nm = np.ascontiguousarray(target_nm, dtype=np.float64).ravel()
        if self.target_nm.size < 8 or not np.all(np.isfinite(self.target_nm)):
            raise ModelError("target: need at least 8 finite samples [nm]")
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ModelError(f"dt_s: {dt_s!r}; need a sample period > 0 s")
        self.dt_s = float(dt_s)
        self.model = model
        self.settings = settings or LearnSettings()
        self.settings.check()
        self.lines = find_lines(self.target_nm) if lines is None else list(lines)
        try:
            judged, self.judged_text = judged_lines(self.lines, self.settings.judge_lines)
        except ValueError as err:
            raise ModelError(str(err)) from None
        self.judged_ramps = judged
        self.judged_groups = raster_lines(judged)
        w = error_weights(self.target_nm, self.settings.central_pct, self.settings.lines_only, self.lines)
        self.reference_nm = rounded_reference(self.target_nm, w, self.lines)
        # a slow axis (``lines`` given) learns the first line too: its error there is near
        # DC, nothing a truncated non-causal step would spoil, and left out it made the second
        # line start from the first one's offset (570 nm on the simulated E-727's y)
        learned = self.lines if lines is not None and self.settings.judge_lines is None else judged
        self.weights = learning_weights(w, self.lines, learned, self.settings.turnaround_weight)
        #: where the guards judge the error: the central 80 % of each line of a raster (what an AFM
        #: images, and what the error report calls central), else the weighted parts
        self.judged = lines_mask(self.target_nm.size, judged, REPORT_CENTRAL_PCT) > 0 if self.lines else w > 0
        self.line_nm = line_span_nm(self.target_nm, self.lines) if self.lines else (float(np.ptp(self.target_nm)) or 1.0)
        self.grid = Grid.for_record(self.target_nm.size, self.dt_s, self.settings.periodic)
        self.digest = target_digest(self.target_nm, self.dt_s)
        if state is not None and state.target_digest != self.digest:
            raise ModelError("learning state: it belongs to another target or sample period; delete it or give "
                             "another state file")
        if state is not None and any(b < 0 or b >= self.grid.f_Hz.size for b in state.ratio_bins):
            raise ModelError("learning state: ratio_bins outside the frequency grid of this target")
        for name in ("best_u_V", "previous_u_V", "previous_y_nm", "best_y_nm"):
            v = None if state is None else getattr(state, name)
            if v is not None and len(v) != self.target_nm.size:
                raise ModelError(f"learning state: {name} has another length than the target")
        self.state = state or LearnState(self.digest)

    @property
    def diverging(self) -> bool:
        """The divergence guard stopped learning (the error rose ``max_rises`` times in a
        row), not the floor or the convergence check."""
        return self.state.stopped and self.state.rises >= self.settings.max_rises

    @property
    def law(self) -> str:
        return "model" if self.model is not None else "model-free"

    def reset(self) -> None:
        """Forget every iteration (a fresh state)."""
        self.state = LearnState(self.digest)

    def step(self, sent_V: np.ndarray, measured_nm: np.ndarray) -> LearnResult:
        """One iteration (module docstring): ``sent_V`` [V] the table that was played (one
        sample per target sample), ``measured_nm`` [nm] the motion recorded with it,
        resampled onto the target's samples."""
        u = self._samples("sent_V", sent_V)
        y = self._samples("measured_nm", measured_nm)
        if self.state.stopped:
            return self._stopped_result(u, y)
        s = self.settings
        ref = self._reference(u)
        lag = estimate_lag_samples(ref, y, max(1, self.target_nm.size // 10))
        aligned = bool(s.align and round(lag) != 0)
        if aligned:
            y = _shift(y, -int(round(lag)), s.periodic)
        errors = error_figures(y, self.target_nm, self.lines, self.judged_ramps)
        e = self.reference_nm - y
        noise = self.state.keep_noise(estimate_noise(y - ref + self.target_nm if self.model is not None else y,
                                                     self.target_nm, self.judged_groups, self.dt_s, e))
        metric = self._judged_pct(e, noise)
        errors.update(noise_nm=noise.sigma_nm, judged_clean_max_pct=metric)
        previous = self._previous()
        stop_reason = self._record(u, y, errors, metric)
        base = self._base(u, y)
        werr = self._without_noise((self.reference_nm - base[1]) * self.weights, noise)
        inc = self._increment(base, werr, (u, y) + previous if previous else None, noise, (u, y))
        self._remember(inc)
        phase_deg, phase_f, stalled = self._phase_check(inc, werr)
        if not stop_reason and stalled and self.state.misses > 0:
            stop_reason = (f"the model's phase error is {phase_deg:.0f}° (over {s.phase_limit_deg:g}°) at "
                           f"{phase_f:.4g} Hz, and most of the remaining error lies where it is: the model-based law "
                           "cannot converge there (re-identify the model, or learn without --model)")
        if stop_reason and not self.state.stopped:
            floor = self._floor(noise, inc, werr)
            self.state.stopped, self.state.floor = True, floor.kind
            self.state.reason = f"{stop_reason}; the floor: {floor.phrase}"
        best = np.asarray(self.state.best_u_V, dtype=float) if self.state.stopped else base[0] + inc.du_V
        nxt, clipped, limited = self._within_limits(best)    # a user's first table may be beyond them
        du = nxt - u
        band = (self.grid.f_Hz > 0) & (self.grid.f_Hz <= inc.q_cutoff_Hz)
        return LearnResult(nxt, self.state.iteration, self.law, errors, metric, float(lag), aligned,
                           float(np.max(np.abs(du))), float(np.sqrt(np.mean(du * du))), clipped, limited,
                           float(np.median(inc.rho[band])) if np.any(band) else 0.0, inc.q_cutoff_Hz,
                           phase_deg, phase_f, self.state.stopped, self.state.reason, self.state.best_iteration,
                           self.state.floor, noise.sigma_nm, self.judged_text)

    def _floor(self, noise: Noise, inc: Increment, werr: np.ndarray) -> Floor:
        """What the best table's remaining error stands on (:mod:`~afmctl.compensators.learning_floor`)."""
        st, s = self.state, self.settings
        best_u = np.asarray(st.best_u_V, dtype=float)
        best_y = np.asarray(st.best_y_nm if st.best_y_nm is not None else st.previous_y_nm, dtype=float)
        power = np.abs(self.grid.spectrum(werr)) ** 2
        f = self.grid.f_Hz
        total = float(np.sum(power[f > 0]))
        high = float(np.sum(power[f > inc.q_cutoff_Hz])) / total if total > 0 else 0.0
        step = (s.slew_V_per_s or math.inf) * self.dt_s
        return name_floor(best_u, self.target_nm - best_y, self.judged, noise.sigma_nm, self.line_nm, s.u_min_V,
                          s.u_max_V, step, high, inc.q_cutoff_Hz)

    def floor(self) -> Floor | None:
        """What the best table so far stands on (:mod:`~afmctl.compensators.learning_floor`),
        for a caller that stops learning by its own rule; None before the first step."""
        st = self.state
        last = getattr(self, "_last", None)
        if st.best_u_V is None or last is None:
            return st.floor and Floor(st.floor, st.reason) or None
        noise = st.noise() or NO_NOISE
        best_y = np.asarray(st.best_y_nm if st.best_y_nm is not None else st.previous_y_nm, dtype=float)
        return self._floor(noise, last, self._without_noise((self.reference_nm - best_y) * self.weights, noise))

    def _stopped_result(self, u: np.ndarray, y: np.ndarray) -> LearnResult:
        """After a stop: the best table again, nothing learned, nothing recorded."""
        st = self.state
        best = self._within_limits(np.asarray(st.best_u_V if st.best_u_V is not None else u, dtype=float))[0]
        errors = error_figures(y, self.target_nm, self.lines, self.judged_ramps)
        e = self.reference_nm - y
        metric = self._judged_pct(e, st.noise() or estimate_noise(y, self.target_nm, self.judged_groups, self.dt_s, e))
        du = best - u
        return LearnResult(best, st.iteration, self.law, errors, metric, 0.0, False, float(np.max(np.abs(du))),
                           float(np.sqrt(np.mean(du * du))), 0, 0, 0.0, math.nan, 0.0, 0.0, True, st.reason,
                           st.best_iteration, st.floor, st.noise_nm or 0.0, self.judged_text)

    # ------------------------------------------------------------------ parts of a step
    def _without_noise(self, e: np.ndarray, noise: Noise) -> np.ndarray:
        """``e`` [nm] less what stands no higher than the noise (spectral subtraction,
        :func:`~afmctl.compensators.learning_noise.noise_gain`)."""
        if noise is NO_NOISE or noise.sigma_nm <= 0:
            return e
        spec = self.grid.spectrum(e)
        n_w = float(np.count_nonzero(e))
        return self.grid.apply(noise_gain(spec, n_w * noise.at(self.grid.f_Hz)), e)

    def _judged_pct(self, e: np.ndarray, noise: Noise) -> float:
        """The largest error [% of the line] over the judged parts, its noise left out."""
        sel = self.judged
        if not np.any(sel):
            return 0.0
        clean = self._without_noise(np.where(sel, e, 0.0), noise)
        return float(100.0 * np.max(np.abs(clean[sel])) / self.line_nm)

    def _samples(self, name: str, x: np.ndarray) -> np.ndarray:
        a = np.ascontiguousarray(x, dtype=np.float64).ravel()
        if a.size != self.target_nm.size:
            raise ModelError(f"{name}: {a.size} samples; the target has {self.target_nm.size}")
        if not np.all(np.isfinite(a)):
            raise ModelError(f"{name}: non-finite values; all values must be finite")
        return a

    def _reference(self, u: np.ndarray) -> np.ndarray:
        """What the recording's lag is measured against: the model's prediction for ``u``,
        else the target."""
        if self.model is None:
            return self.target_nm
        try:
            return periodic_run(lambda: self.model.forward(self.dt_s), u, self.settings.periodic)
        except ModelError:
            return self.target_nm

    def _previous(self) -> tuple[np.ndarray, np.ndarray] | None:
        st = self.state
        if st.previous_u_V is None or st.previous_y_nm is None:
            return None
        return np.asarray(st.previous_u_V, dtype=float), np.asarray(st.previous_y_nm, dtype=float)

    def _record(self, u: np.ndarray, y: np.ndarray, errors: dict[str, float], metric: float) -> str:
        """Book-keeping of the sent table's error; the divergence guard's verdict."""
        st = self.state
        st.previous_u_V, st.previous_y_nm = u.tolist(), y.tolist()
        prev = st.history[-1]["weighted_max_pct"] if st.history else math.inf
        st.history.append({**errors, "weighted_max_pct": metric})
        st.iteration += 1
        better = metric < st.best_metric_pct
        st.misses = 0 if better else st.misses + 1
        st.halvings = max(0, st.halvings - 1) if better else st.halvings + 1
        if metric < st.best_metric_pct:
            st.best_metric_pct, st.best_u_V, st.best_iteration = metric, u.tolist(), st.iteration - 1
            st.best_y_nm = y.tolist()
        tol = NOISE_TOLERANCE * 100.0 * (st.noise_nm or 0.0) / self.line_nm
        st.rises = st.rises + 1 if metric > prev * (1 + 1e-6) + tol else 0
        if st.rises >= self.settings.max_rises:
            return (f"the weighted error rose {st.rises} times in a row (to {metric:.3g} %): diverging"
                    f"{KEEPING} (iteration {st.best_iteration}, {st.best_metric_pct:.3g} %)")
        if st.misses >= self.settings.max_misses:
            return (f"no better table in {st.misses} iterations (steps down to 1/{2 ** st.halvings}): the floor is "
                    f"reached{KEEPING} (iteration {st.best_iteration}, {st.best_metric_pct:.3g} %)")
        return ""

    def _base(self, u: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The table the next one is learned from: this one, or — when it came out worse
        than the best so far — the best one (a step back, with what the worse step taught
        about the model's error)."""
        st = self.state
        if st.best_iteration != st.iteration - 1 and st.best_u_V is not None and st.best_y_nm is not None:
            log.info("iteration %d is worse than iteration %d: learning from the best table", st.iteration - 1,
                     st.best_iteration)
            return np.asarray(st.best_u_V, dtype=float), np.asarray(st.best_y_nm, dtype=float)
        return u, y

    def _increment(self, base: tuple[np.ndarray, np.ndarray], werr: np.ndarray,
                   secant: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None, noise: Noise,
                   play: tuple[np.ndarray, np.ndarray]) -> Increment:
        s = self.settings
        full = s.rho_max if s.rho_max is not None else DEFAULT_STEP[self.law]
        rho = full * 0.5 ** self.state.halvings
        psd = noise.at(self.grid.f_Hz) if noise.sigma_nm > 0 else None
        if self.model is None:
            return model_free_increment(self.grid, base, werr, rho, s.q_cutoff_Hz, secant, self._known(), psd)
        return model_based_increment(self.grid, self.model, self.dt_s, base, werr, rho, s.q_cutoff_Hz, secant,
                                     self._known(), psd, play, full)

    def _known(self) -> tuple[np.ndarray, np.ndarray] | None:
        st = self.state
        if not st.ratio_bins:
            return None
        ratio = np.ones(self.grid.f_Hz.size, dtype=complex)
        mask = np.zeros(self.grid.f_Hz.size, dtype=bool)
        idx = np.asarray(st.ratio_bins, dtype=int)
        ratio[idx] = np.asarray(st.ratio_re) + 1j * np.asarray(st.ratio_im)
        mask[idx] = True
        return ratio, mask

    def _remember(self, inc: Increment) -> None:
        """Keep the model's measured error for the next iterations (model-based law)."""
        self._last = inc
        idx = np.flatnonzero(inc.reliable)
        self.state.ratio_bins = idx.tolist()
        self.state.ratio_re = inc.ratio.real[idx].tolist()
        self.state.ratio_im = inc.ratio.imag[idx].tolist()

    def _phase_check(self, inc: Increment, werr: np.ndarray) -> tuple[float, float, bool]:
        """(largest measured phase error [°] at a learned harmonic, its frequency [Hz],
        whether the bins over the limit hold more than ``stall_share`` of the weighted
        error energy inside the Q-filter's band)."""
        f = self.grid.f_Hz
        band = inc.reliable & (f > 0) & (f <= inc.q_cutoff_Hz)
        if self.model is None or not np.any(band):
            return 0.0, 0.0, False
        err_pow = np.abs(self.grid.spectrum(werr)) ** 2
        significant = band & (err_pow >= 1e-3 * float(np.max(err_pow[band])))
        if not np.any(significant):
            return 0.0, 0.0, False
        theta = np.degrees(np.abs(np.angle(inc.ratio)))
        j = int(np.flatnonzero(significant)[np.argmax(theta[significant])])
        over = band & (theta >= self.settings.phase_limit_deg)
        share = float(np.sum(err_pow[over]) / max(np.sum(err_pow[band]), 1e-300))
        return float(theta[j]), float(f[j]), share > self.settings.stall_share

    def _within_limits(self, u: np.ndarray) -> tuple[np.ndarray, int, int]:
        s = self.settings
        step = (s.slew_V_per_s or math.inf) * self.dt_s
        if not s.periodic:
            return rate_limit(u, s.u_min_V, s.u_max_V, step)
        out, clipped, limited = rate_limit(np.tile(u, 2), s.u_min_V, s.u_max_V, step)
        out = out[u.size:]
        for _ in range(4):       # the wrap from the last sample to the first
            if abs(out[0] - out[-1]) <= step:
                break
            out, _, extra = rate_limit(out, s.u_min_V, s.u_max_V, step, u_start_V=float(out[-1]))
            limited += extra
        return out, clipped // 2, limited


def _shift(y: np.ndarray, k: int, periodic: bool) -> np.ndarray:
    """``y`` moved by ``k`` samples (later for k > 0); ends held unless periodic."""
    if periodic:
        return np.roll(y, k)
    out = np.empty_like(y)
    if k >= 0:
        out[k:], out[:k] = y[:y.size - k], y[0]
    else:
        out[:k], out[k:] = y[-k:], y[-1]
    return out
