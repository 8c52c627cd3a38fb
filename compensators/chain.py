"""The composite per-axis model: amplifier → hysteresis → creep → linear dynamics.

One model file (``kind = "chain"``) holds up to four stages, each itself a model of
:data:`afmctl.compensators.models.KINDS`:

* ``amplifier`` (optional) — the voltage amplifier before the piezo (kind ``amplifier``,
  :mod:`afmctl.compensators.amplifier`): command ``u`` [V] → piezo voltage ``v`` [V], its
  bandwidth and slew limit;
* ``hysteresis`` — pi, epi, preisach, bouc-wen, rate-pi or rate-bouc-wen: ``v`` [V] → ``h`` [nm] (``u`` itself
  without an amplifier stage);
* ``creep`` (optional) — a linear creep model (kind ``creep``) from ``h`` [nm] to the
  displacement [nm]; its ``gain_nm_per_V`` is here a unit-less gain ≈ 1 (nm per nm);
* ``dynamics`` (optional) — a linear dynamics model (kind ``dynamics``) [nm] → [nm].

The forward operator is ``dynamics(creep(hysteresis(amplifier(u))))``, the inverse (the
feedforward compensator) ``amplifier⁻¹(hysteresis⁻¹(creep⁻¹(dynamics⁻¹(y))))``. The chain's
*structure* is the string ``[amplifier+]<hysteresis>[+creep][+dynamics]``, e.g.
``preisach+creep`` or ``amplifier+preisach+creep+dynamics``; that is what the CLI accepts as
``--model`` and what ``afmctl run`` prints.

The amplifier stage is identified first: from a recorded piezo voltage ``v_V`` when the
record has one (:func:`~afmctl.compensators.amplifier.fit_amplifier`), otherwise from the
record itself, linear → hysteresis → linear (a "sandwich"): the first-order lag below the
first structural mode that the dynamics stage finds is moved before the hysteresis
(:func:`amplifier_from_dynamics`). The other stages are then identified on the piezo
voltage the amplifier stage gives for the record's commands.

Identification (:meth:`ChainModel.identify`) follows the Hammerstein structure. Preisach +
creep are fitted jointly in one nonnegative least-squares problem per round
(:mod:`afmctl.compensators.joint_creep_fit`); the other hysteresis kinds by alternation:
the hysteresis on the creep-corrected output, then the creep from the hysteresis output to
the measured output; ``rounds`` times (default 2) either way. The dynamics last,
from the static chain's output to the measured output; then the static stages again on the
record through the dynamics' stable inverse and the dynamics again, while the chain's error
over the record falls (:func:`refine_with_dynamics`). A Preisach stage is fitted on every
sample (:data:`FULL_RATE_KINDS`), the samples just after a jump of the command left out
(:mod:`afmctl.compensators.record_steps`).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, SerializeAsAny, field_validator

from .base import Chain, ModelError, StreamingOperator, check_finite
from .input_checks import number_option, sample_mask
from .dynamics_limits import LimitedInverse, invert_within_limits, rate_limit
from .models import HysteresisModel, model_class, model_from_dict

log = logging.getLogger(__name__)

#: hysteresis kinds a chain may start with
HYSTERESIS_KINDS: tuple[str, ...] = ("pi", "epi", "preisach", "bouc-wen", "rate-pi", "rate-bouc-wen")
#: optional stages after the hysteresis, in chain order
STAGES: tuple[str, ...] = ("creep", "dynamics")
#: the optional stage before the hysteresis
AMPLIFIER = "amplifier"

#: creep stage identification: lags between 10 ms and 100 s (5 of them)
CREEP_OPTIONS: dict[str, Any] = {"n_operators": 5, "tau_min_s": 0.01, "tau_max_s": 100.0}
#: preisach+creep fitted jointly: two lags per decade from 10 ms to 100 s, and a 64-level
#: Preisach grid (the speed ladder's static floor: 0.97 → 0.42 % at 1 line/s from 32 levels)
JOINT_CREEP_OPTIONS: dict[str, Any] = {"n_operators": 9, "tau_min_s": 0.01, "tau_max_s": 100.0}
JOINT_PREISACH_LEVELS = 64
#: highest sample rate the hysteresis and creep stages are fitted at [Hz] (block means;
#: not for :data:`FULL_RATE_KINDS`)
STATIC_RATE_HZ = 2000.0
#: a long record's block-mean static record keeps at most this many means: its blocks grow
#: (the rate falls below STATIC_RATE_HZ) ...
STATIC_MAX_SAMPLES = 50_000
#: ... down to this rate [Hz] at the lowest (the creep stage's fastest lag, 10 ms, still spans
#: five means). Calibrating the E-727 (0.79 M rows at 10 kHz): bouc-wen's two candidates were
#: a fifth of ``auto``'s time at 2 kHz (158,000 means, each of ~2000 residuals a pass over them)
STATIC_MIN_RATE_HZ = 500.0
#: hysteresis kinds whose static fit takes the record at its own rate. The
#: Preisach memory of a block mean is not the mean of the memories: a fast chirp or fast
#: triangles averaged to 2 kHz misstate the minor loops. Measured on the user-style records of
#: four unseen plants (static output only, no creep or dynamics; raster at 1 line/s, max %):
#: 2 kHz block means 1.21 / 1.74 % (capacitive, soft), every sample 0.19 / 0.39 %
FULL_RATE_KINDS: tuple[str, ...] = ("preisach",)


def parse_structure(text: str) -> tuple[str, tuple[str, ...]]:
    """``"preisach+creep+dynamics"`` → ``("preisach", ("creep", "dynamics"))``;
    ``"amplifier+preisach+dynamics"`` → ``("preisach", ("amplifier", "dynamics"))`` (the
    amplifier stage, when there is one, first among the stages).

    :class:`ModelError` naming the allowed parts for anything else (stages in chain order,
    each at most once)."""
    parts = [p.strip() for p in str(text).split("+")]
    pre = parts[:1] == [AMPLIFIER]
    hyst, stages = (parts[1] if pre and len(parts) > 1 else parts[0]), tuple(parts[2:] if pre else parts[1:])
    allowed = f"[{AMPLIFIER}+]<{'|'.join(HYSTERESIS_KINDS)}>[+creep][+dynamics]"
    if hyst not in HYSTERESIS_KINDS:
        raise ModelError(f"model: {text!r}: the chain must start with a hysteresis kind (after the optional "
                         f"amplifier stage); allowed {allowed}")
    order = [STAGES.index(s) if s in STAGES else -1 for s in stages]
    if -1 in order or order != sorted(set(order)):
        raise ModelError(f"model: {text!r}: stages must be creep and/or dynamics, in that order; allowed {allowed}")
    return hyst, ((AMPLIFIER,) if pre else ()) + stages


def join_structure(hyst: str, stages: Sequence[str]) -> str:
    """The structure string of ``hyst`` and ``stages`` (any order): the amplifier first."""
    return "+".join(([AMPLIFIER] if AMPLIFIER in stages else []) + [hyst] + [s for s in STAGES if s in stages])


def _as_model(value: Any, where: str, allowed: tuple[str, ...]) -> Any:
    if value is None or isinstance(value, HysteresisModel):
        model = value
    else:
        model = model_from_dict(value, where=where)
    if model is not None and model.kind not in allowed:
        raise ValueError(f"kind {model.kind!r} is not allowed here; allowed: {', '.join(allowed)}")
    return model


class ChainModel(HysteresisModel):
    """Per-axis chain ``amplifier → hysteresis → creep → dynamics`` (module docstring); u [V] → y [nm]."""

    kind: Literal["chain"] = "chain"
    time_dependent: ClassVar[bool] = True
    amplifier: SerializeAsAny[HysteresisModel] | None = Field(
        None, description="amplifier stage: command u [V] → piezo voltage v [V] (bandwidth, slew limit)")
    hysteresis: SerializeAsAny[HysteresisModel] = Field(description="pi|epi|preisach|bouc-wen|rate-pi|rate-bouc-wen model: u [V] → h [nm]")
    creep: SerializeAsAny[HysteresisModel] | None = Field(None, description="creep model: h [nm] → y [nm], gain ≈ 1")
    dynamics: SerializeAsAny[HysteresisModel] | None = Field(None, description="linear dynamics model [nm] → [nm]")
    selection: list[dict[str, Any]] | None = Field(
        None, description="afmctl identify --model auto: held-out score of every candidate (nm, %)")

    @field_validator("amplifier", mode="before")
    @classmethod
    def _amp(cls, v: Any) -> Any:
        return _as_model(v, "amplifier", (AMPLIFIER,))

    @field_validator("hysteresis", mode="before")
    @classmethod
    def _hyst(cls, v: Any) -> Any:
        return _as_model(v, "hysteresis", HYSTERESIS_KINDS)

    @field_validator("creep", mode="before")
    @classmethod
    def _creep(cls, v: Any) -> Any:
        return _as_model(v, "creep", ("creep",))

    @field_validator("dynamics", mode="before")
    @classmethod
    def _dyn(cls, v: Any) -> Any:
        return _as_model(v, "dynamics", ("dynamics",))

    @property
    def structure(self) -> str:
        """``[amplifier+]<hysteresis>[+creep][+dynamics]``."""
        present = [s for s in (AMPLIFIER, *STAGES) if getattr(self, s) is not None]
        return join_structure(self.hysteresis.kind, present)

    def voltage_range_V(self) -> tuple[float, float] | None:
        """The chain's own identified range, else its hysteresis stage's [V]."""
        return self.u_range_V or self.hysteresis.voltage_range_V()

    def stages(self) -> list[HysteresisModel]:
        """The stage models in chain (forward) order."""
        return [m for m in (self.amplifier, self.hysteresis, self.creep, self.dynamics) if m is not None]

    def forward(self, dt_s: float | None = None) -> StreamingOperator:
        """Operator u [V] → y [nm] at sample period ``dt_s`` [s]."""
        return Chain(*(m.forward(dt_s) for m in self.stages()))

    def inverse(self, dt_s: float | None = None) -> StreamingOperator:
        """Compensator y [nm] → u [V] at sample period ``dt_s`` [s]: the stages' inverses in
        reverse order. A dynamics stage makes it a preview inverse: the operator's
        ``latency_samples`` (0 without dynamics) is how many samples its output lags the
        target; feed it the target that many samples ahead."""
        op = Chain(*(m.inverse(dt_s) for m in reversed(self.stages())))
        op.latency_samples = sum(int(getattr(o, "latency_samples", 0)) for o in op.ops)  # type: ignore[attr-defined]
        return op

    def static_inverse(self, dt_s: float | None = None) -> StreamingOperator:
        """A fresh compensator of what follows the dynamics' inverse, y [nm] → u [V]:
        ``creep⁻¹``, ``hysteresis⁻¹`` and ``amplifier⁻¹`` (the amplifier stage's inverse
        counts the piezo-voltage steps it had to cut to its slew limit: ``n_limited``)."""
        return Chain(*(m.inverse(dt_s) for m in (self.creep, self.hysteresis, self.amplifier) if m is not None))

    def static_forward(self, dt_s: float | None = None) -> StreamingOperator:
        """A fresh forward operator of what comes before the dynamics, u [V] → nm: the
        amplifier, hysteresis and creep stages (:meth:`static_inverse` inverts it)."""
        return Chain(*(m.forward(dt_s) for m in (self.amplifier, self.hysteresis, self.creep) if m is not None))

    def piezo_inverse(self, dt_s: float | None = None) -> StreamingOperator:
        """A fresh ``creep⁻¹`` then ``hysteresis⁻¹``, nm → the piezo voltage [V] (the
        command itself without an amplifier stage)."""
        return Chain(*(m.inverse(dt_s) for m in (self.creep, self.hysteresis) if m is not None))

    def inverse_within_limits(self, y_nm: np.ndarray, dt_s: float, u_min_V: float = -math.inf,
                              u_max_V: float = math.inf, slew_V_per_s: float | None = None,
                              u_start_V: float | None = None) -> LimitedInverse:
        """The chain's one offline inverse: voltages [V] for a whole known target ``y_nm``
        [nm] at ``dt_s`` [s], no latency, within [u_min_V, u_max_V] and ``slew_V_per_s``
        [V/s] (None: unlimited). With a dynamics stage its stable non-causal inverse runs
        over the whole target with the band limit lowered until the voltages fit
        (:func:`~afmctl.compensators.dynamics_limits.invert_within_limits`), then the static
        inverse; without one, the static inverse. What is still out of reach is clipped and
        rate-limited, starting from ``u_start_V`` (the voltage held before the first
        sample; None: the first sample), and counted in the result."""
        y = np.ascontiguousarray(check_finite("y_nm", y_nm).ravel())
        if self.dynamics is not None:
            return invert_within_limits(self.dynamics, y, dt_s, lambda: self.piezo_inverse(dt_s),
                                        u_min_V, u_max_V, slew_V_per_s, u_start_V=u_start_V,
                                        forward=lambda: self.forward(dt_s), amplifier=self.amplifier)
        u = self.static_inverse(dt_s).block(y)
        max_step = (slew_V_per_s or math.inf) * dt_s
        slew = float(np.max(np.abs(np.diff(u)))) / dt_s if u.size > 1 else 0.0
        out, clipped, limited = rate_limit(u, u_min_V, u_max_V, max_step, u_start_V)
        return LimitedInverse(out, math.inf, math.inf, slew, clipped, limited, 0.0, slew, slew_V_per_s)

    def inverse_offline(self, y_nm: np.ndarray, dt_s: float) -> np.ndarray:
        """Voltages [V] for a whole known target ``y_nm`` [nm] at ``dt_s`` [s], no latency,
        without voltage or slew limits (:meth:`inverse_within_limits` with none)."""
        return self.inverse_within_limits(y_nm, dt_s).u_V

    def summary(self) -> str:
        lines = [f"model            : chain {self.structure} (kind chain)"]
        for m in self.stages():
            lines += ["  " + line for line in m.summary().splitlines()]
        if self.selection:
            lines += ["selection (held-out prediction error):"] + ["  " + ln for ln in format_table(self.selection).splitlines()]
        return "\n".join(lines)

    @classmethod
    def identify(cls, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, n_operators: int | None = None,
                 structure: str = "preisach+creep", rounds: int = 2,
                 dynamics_options: dict[str, Any] | None = None, fit_from_index: int = 0,
                 left_out: np.ndarray | None = None, v_V: np.ndarray | None = None,
                 measured: np.ndarray | None = None, **options: Any) -> "ChainModel":
        """Fit the chain ``structure`` jointly (module docstring). ``n_operators`` and
        ``options`` go to the hysteresis kind's ``identify``, ``dynamics_options`` to the
        dynamics kind's; data uniformly sampled (t [s], u [V], y [nm]). ``v_V``: the
        recorded piezo voltage [V] (an amplifier stage is fitted to it; without it, the
        amplifier stage comes from the record itself: :func:`amplifier_from_dynamics`).

        ``fit_from_index`` is a burn-in: the whole record runs through every stage (so the
        hysteresis memory and the creep lags hold the state the recording put them in), but
        only samples from that index on are fitted. Kinds with ``fits_with_burn_in`` get it
        passed through; the others are fitted on the part after it.

        ``left_out``: one boolean per sample, True where the static stages of a kind that fits
        sample rows (:data:`FULL_RATE_KINDS`) leave the record out of their fit, besides the
        jumps' transients (:func:`_without_transients`); the memory still runs through them.

        ``measured``: one boolean per sample, False where ``y`` was not measured (the holds
        ``afmctl calibrate`` puts between recorded pieces, their ``y`` interpolated). Every
        stage that fits rows leaves those out (:func:`_StageFit`, a block mean with one of
        them in it too), and so does the judging of the refinements; the record, holds
        included, still runs through every stage (the creep of a hold is in what follows)."""
        hyst_kind, stages = parse_structure(structure)
        if AMPLIFIER in stages:
            rest = join_structure(hyst_kind, [s for s in stages if s != AMPLIFIER])
            return _with_amplifier(cls, rest, t_s, u_V, y_nm, v_V, dict(
                n_operators=n_operators, rounds=rounds, dynamics_options=dynamics_options,
                fit_from_index=fit_from_index, left_out=left_out, measured=measured, **options))
        hcls = model_class(hyst_kind)
        t = check_finite("t_s", t_s).ravel()
        u = np.ascontiguousarray(check_finite("u_V", u_V).ravel())
        y = np.ascontiguousarray(check_finite("y_nm", y_nm).ravel())
        if not (t.size == u.size == y.size) or t.size < 8:
            raise ModelError("data: need equal-length columns t, u, y with at least 8 samples")
        k0 = int(number_option("fit_from_index", fit_from_index, lo=0, hi=t.size - 8, integer=True))
        measured = measured_rows(measured, t.size)
        dt = float(np.median(np.diff(t)))
        td, ud, _, k0d, dtd = record_for_static(t, u, y, k0, dt, hyst_kind)
        fit = _StageFit(td, ud, k0d, None if measured is None else ~block_all(measured, ud.size))
        caller = dict(options)                 # a mask of the caller's own is kept as it is
        options = {**_without_transients(hyst_kind, options, u, dt), **options}
        rows = hyst_kind in FULL_RATE_KINDS
        if left_out is not None and rows:
            options["exclude"] = _also_left_out(options, left_out)
        if measured is not None and rows:
            options["exclude"] = _also_left_out(options, ~measured)
        fast = (_fast_parts_to_leave_out(t, u, k0)
                if rows and "dynamics" in stages and "exclude" not in caller else None)
        if fast is not None:
            options["exclude"] = _also_left_out(options, fast)
        n_rounds, with_creep = max(1, int(rounds)), "creep" in stages

        def static(y_static: np.ndarray, exclude: np.ndarray | None = None) -> tuple[Any, Any]:
            y_fit = record_for_static(t, u, y_static, k0, dt, hyst_kind)[2]
            opts = options if exclude is None or not rows else {**options, "exclude": _also_left_out(options, exclude)}
            return _fit_static(hcls, fit, y_fit, dtd, with_creep, n_rounds, n_operators, opts)

        hyst, creep = static(y)
        if "dynamics" not in stages:
            return cls(hysteresis=hyst, creep=creep)
        model = cls(hysteresis=hyst, creep=creep, dynamics=fit_dynamics_stage(hyst, creep, t, u, y, k0, dynamics_options))
        return refine_with_dynamics(model, static, t, u, y, k0, dynamics_options, measured=measured)


def _with_amplifier(cls: Any, rest: str, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray,
                    v_V: np.ndarray | None, kw: dict[str, Any]) -> "ChainModel":
    """``amplifier+<rest>``: the amplifier stage from the recorded piezo voltage ``v_V``, or,
    without it, from the lag the dynamics of ``rest`` fitted on the commands find
    (:func:`amplifier_from_dynamics`); then ``rest`` on the piezo voltage the stage gives
    for the commands. The transients after the commands' jumps stay left out of the static
    fit (the stage smooths the jumps it would be found by)."""
    from .amplifier import fit_amplifier
    from .record_steps import step_transients

    t = check_finite("t_s", t_s).ravel()
    u = np.ascontiguousarray(check_finite("u_V", u_V).ravel())
    dt = float(np.median(np.diff(t)))
    k0 = int(kw.get("fit_from_index", 0) or 0)
    if v_V is not None:
        amp = fit_amplifier(t, u, v_V, fit_from_index=k0)
    else:
        if "dynamics" not in parse_structure(rest)[1]:
            raise ModelError(f"model: amplifier+{rest}: without a recorded piezo voltage (column v) the amplifier "
                             f"stage is found from the dynamics: use amplifier+{rest}+dynamics")
        first = cls.identify(t, u, y_nm, structure=rest, **kw)
        amp = amplifier_from_dynamics(first.dynamics)
        if amp is None:
            raise ModelError(f"model: amplifier+{rest}: the record shows no first-order lag below the first "
                             "structural mode to put before the hysteresis")
    x = amp.forward(dt).block(u)
    jumps = step_transients(u, dt)
    given = kw.pop("left_out", None)
    left_out = jumps if given is None else (np.asarray(given, dtype=bool) | jumps)
    model = cls.identify(t, x, y_nm, structure=rest, left_out=left_out if left_out.any() else None, **kw)
    model.amplifier = amp
    model.u_range_V = (float(np.min(u)), float(np.max(u)))
    return model


def amplifier_from_dynamics(dynamics: Any) -> Any:
    """The amplifier stage a dynamics stage fitted on the commands holds (linear →
    hysteresis → linear, the "sandwich"): its slowest first-order lag below the first
    structural mode (a voltage amplifier's bandwidth under the piezo's capacitance), as an
    :class:`~afmctl.compensators.amplifier.AmplifierModel` without a slew limit (the record
    alone does not tell it); None when the dynamics have no such lag."""
    from .amplifier import AmplifierModel
    from .dynamics import first_mode_Hz

    if dynamics is None:
        return None
    p = dynamics.poles()
    mode = first_mode_Hz(p) if np.any(np.abs(p.imag) > 0) else math.inf
    lags = [abs(float(q.real)) / (2 * math.pi) for q in p if q.imag == 0]
    below = [f for f in lags if f < mode]
    if not below:
        return None
    return AmplifierModel.from_lag(min(below), fit_info={"fitted_from": "the lag of a dynamics stage fitted on the "
                                                         "commands (no recorded piezo voltage)"})


#: where the chain's dynamics stage is identified from (``dynamics_options["from"]``)
DYNAMICS_SOURCES: tuple[str, ...] = ("voltage", "static")
#: the default source: the static stages' output. From the voltage the lag of a constructed
#: plant comes out right (tests/test_dynamics_source.py) but on the unseen-plant test
#: (tests/test_unseen_plant.py) the chain's compensation got worse (3.1 % max at 10 lines/s
#: against ≤ 1 %): the static stages' small-signal response and the voltage-based dynamics
#: are not consistent; choosing between them by held-out fast data is still open (#24)
DEFAULT_DYNAMICS_SOURCE = "static"


#: Hammerstein refinements of a chain with dynamics (#24), at most this many: the static
#: stages fitted again on the output the identified dynamics imply (the record through their
#: stable inverse), then the dynamics again from the new static stages' output ...
DYNAMICS_REFINEMENTS = 4
#: ... while the last improved the whole chain's RMS error over the record by at least this
#: fraction. After a smaller gain the next round gained < 0.2 % or made it worse on every
#: record measured (#38: the E-727 calibrate recordings 4.7, 3.3, 11.5 and 10.1 % then 0.0 %;
#: two-modes from excite 7.9 % then 0.0 %; amp-first from excite and from lab records 22 %
#: and 24 % then 0.0 %, lumpy-noisy 20 % then worse; 2.5–8.5 % then < 0.1 %), and it cost as
#: much as the first (2–5 s a fit); after a larger one it can still gain (lumpy-noisy: 61 %
#: then 9.5 % or 2.7 %, amp-first 50 % then 0.8 %)
REFINE_MIN_GAIN = 0.25


def refine_with_dynamics(model: "ChainModel", static: Any, t: np.ndarray, u: np.ndarray, y: np.ndarray, k0: int,
                         dynamics_options: dict[str, Any] | None, stop: int | None = None,
                         measured: np.ndarray | None = None) -> "ChainModel":
    """The chain ``model`` (with a dynamics stage) refined (:data:`DYNAMICS_REFINEMENTS`): the
    static stages ``static(y_static)`` — a function returning ``(hysteresis, creep)`` fitted to
    an output ``y_static`` [nm] of the whole record — fitted again on the record ``y`` [nm]
    through the dynamics' stable non-causal inverse (the fast parts' ringing and lag no longer
    bent into hysteresis and creep), then the dynamics again from their output; repeated while
    the whole chain's RMS error over ``y[k0:stop]`` falls by at least :data:`REFINE_MIN_GAIN`.
    A round that does not lower it is not kept.

    A stage that fits sample rows (:data:`FULL_RATE_KINDS`) is refitted without the stretches
    the chain before the round does not explain (:func:`~.record_steps.unexplained`; e.g. a
    mode above the recorded band ringing after every corner of fast triangles):
    ``static(y_static, exclude)`` takes that mask, and the round is judged on the rest.
    ``measured``: False on the samples whose ``y`` was not measured (not judged either)."""
    dt = float(np.median(np.diff(t)))
    rows = getattr(model.hysteresis, "kind", "") in FULL_RATE_KINDS

    def residual(m: "ChainModel") -> np.ndarray:   # the chain's prediction error over the record [nm]
        return m.forward(dt).block(u) - y

    def rms(r: np.ndarray, keep: np.ndarray) -> float:
        if measured is not None:
            keep = keep & measured[:keep.size]
        return float(np.sqrt(np.mean(r[k0:stop][keep[k0:stop]] ** 2)))

    resid, span = residual(model), float(np.ptp(y[k0:stop]))
    for _ in range(DYNAMICS_REFINEMENTS):
        skip = _unexplained_by(model, resid, dt, k0, stop, span) if rows else np.zeros(u.size, dtype=bool)
        before = rms(resid, ~skip)
        dynamics: Any = model.dynamics           # a LinearDynamicsModel
        hyst, creep = static(dynamics.inverse_offline(y, dt), skip if skip.any() else None)
        refined = ChainModel(hysteresis=hyst, creep=creep,
                             dynamics=fit_dynamics_stage(hyst, creep, t, u, y, k0, dynamics_options))
        refined_resid = residual(refined)
        after = rms(refined_resid, ~skip)
        log.info("chain: static stages refitted through the dynamics' inverse: RMS %.4g -> %.4g nm", before, after)
        if not after < before:
            break
        model, resid, gained = refined, refined_resid, after < (1.0 - REFINE_MIN_GAIN) * before
        if not gained:
            break
    return model


def _unexplained_by(model: "ChainModel", resid: np.ndarray, dt: float, k0: int, stop: int | None,
                    span_nm: float) -> np.ndarray:
    """The samples of ``resid[k0:stop]`` (the chain ``model``'s prediction error over the
    record [nm], whose output spans ``span_nm``) the chain cannot explain, as a mask over the
    whole record; logged: where
    the residual above the top of the band its dynamics were identified in
    (``fit_info["f_max_Hz"]``: a mode there is outside the model's reach) is large
    (:func:`~.record_steps.unexplained`). A slower misfit (rate-dependent hysteresis, a
    creep) is the static stages' to fit and stays in."""
    from scipy.signal import butter, sosfiltfilt

    from .record_steps import unexplained

    end = resid.size if stop is None else stop
    mask = np.zeros(resid.size, dtype=bool)
    f_top = float((model.dynamics.fit_info or {}).get("f_max_Hz", 0.0) or 0.0)  # type: ignore[union-attr]
    if not 0.0 < f_top < 0.4 / dt or end - k0 < 64:
        return mask
    above = sosfiltfilt(butter(4, f_top, "highpass", fs=1.0 / dt, output="sos"), resid[k0:end])
    mask[k0:end] = unexplained(above, dt, span_nm)
    if mask.any():
        edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
        spans = ", ".join(f"{a * dt:.2f}–{b * dt:.2f} s" for a, b in zip(edges[::2], edges[1::2]))
        log.info("chain: %.3g s the chain does not explain left out of the static refit: %s",
                 float(mask.sum()) * dt, spans)
    return mask


def fit_dynamics_stage(hyst: Any, creep: Any, t: np.ndarray, u: np.ndarray, y: np.ndarray, k0: int,
                       options: dict[str, Any] | None = None) -> Any:
    """The chain's linear dynamics stage (unit DC gain), from the record after ``k0``; the
    dynamics kind picks the parts with fast content (afmctl's multisine, a chirp, fast triangles) itself.

    ``options["from"]``: ``"voltage"`` — the frequency response ``y/u`` from the voltage, its
    small-signal gain divided out; ``"static"`` (default, :data:`DEFAULT_DYNAMICS_SOURCE`) —
    ``y/x`` from the static stages' output ``x``. On a small-signal segment the static stages' own small-signal
    response (a ±2 % multisine spans about one cell of a 64-level Preisach grid; the creep
    stage has lags of its own) differs from the scanner's, and ``y/x`` folds that error into
    the dynamics (#24: an amplifier lag 60 % too fast through preisach+creep, within 3 % from
    the voltage). The source is recorded in ``fit_info["fitted_from"]``."""
    opts = dict(options or {})
    given = "from" in opts
    source = opts.pop("from", DEFAULT_DYNAMICS_SOURCE)
    if source not in DYNAMICS_SOURCES:
        raise ModelError(f"dynamics_options from: {source!r}; allowed {', '.join(DYNAMICS_SOURCES)}")
    fitted_from = "voltage"
    if source == "voltage":
        x = u
    else:
        dt = float(np.median(np.diff(t)))
        x = hyst.forward(dt).block(u)
        if creep is not None:
            x = creep.forward(dt).block(x)
        fitted_from = "static stages' output"
        if not given:
            x, fitted_from = _coherent_source(t, u, x, y, k0, opts)
    dyn: Any = model_class("dynamics").identify(t[k0:], np.ascontiguousarray(x[k0:]), y[k0:], **opts)
    dyn.fit_info = {**(dyn.fit_info or {}), "fitted_from": fitted_from}
    if x is u:   # the stage runs on nm: its initial state is the output's
        dyn.initial_nm = float(y[k0])
    return dyn


#: the static stages' output is the default source unless the output follows it coherently
#: only up to less than this share of the band over which it follows the voltage
COHERENT_BAND_SHARE = 0.7
#: the dynamics options that say how the response is measured (the rest say how it is fitted)
MEASURE_OPTIONS: tuple[str, ...] = ("segment", "nperseg", "f_min_Hz", "f_max_Hz", "min_coherence")


def _coherent_source(t: np.ndarray, u: np.ndarray, x: np.ndarray, y: np.ndarray, k0: int,
                     opts: dict[str, Any]) -> tuple[np.ndarray, str]:
    """The input the dynamics stage is measured from: the static stages' output ``x`` [nm],
    unless the record's output ``y`` [nm] follows it coherently over less than
    :data:`COHERENT_BAND_SHARE` of the band over which it follows the voltage ``u`` [V]
    (times ``t`` [s]; both from sample ``k0`` on). A hysteresis stage that does not resolve a small
    signal (a chirp behind a 260 Hz amplifier moves the piezo voltage by a fraction of a
    64-level Preisach cell at 1 kHz) turns it into steps the scanner never made: the static
    output was coherent to 576 Hz, the voltage to 1587 Hz, and the mode at 1.25 kHz was lost."""
    from .dynamics_identify import coherent_band_Hz

    measure = {k: v for k, v in opts.items() if k in MEASURE_OPTIONS}
    band_x = coherent_band_Hz(t[k0:], x[k0:], y[k0:], **measure)
    band_u = coherent_band_Hz(t[k0:], u[k0:], y[k0:], **measure)
    if band_x >= COHERENT_BAND_SHARE * band_u:
        return x, "static stages' output"
    log.info("chain: dynamics from the voltage: the output follows the static stages' output coherently up to "
             "%.4g Hz, the voltage up to %.4g Hz", band_x, band_u)
    return u, (f"voltage (the output follows the static stages' output coherently up to {band_x:.4g} Hz, "
               f"the voltage up to {band_u:.4g} Hz)")


def record_for_static(t: np.ndarray, u: np.ndarray, y: np.ndarray, k0: int, dt: float, kind: str = ""
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, float]:
    """The record the static stages of hysteresis ``kind`` are fitted on. A Preisach fit
    takes it as it is: it traces its memory sample by sample and fits rows spread over
    the record (:data:`FULL_RATE_KINDS`). For the other kinds, a record sampled faster than
    :data:`STATIC_RATE_HZ` becomes block means of ``m`` samples (``m`` the whole number that
    brings the rate to at most that; what a sensor averaging over ``m·dt`` reports): hysteresis
    and creep need no more (the fastest lag is 10 ms), the averaging takes the structural
    modes' ringing out, and a 50 kHz recording fits ~25 times faster. A long record gets
    longer blocks, at most :data:`STATIC_MAX_SAMPLES` means but never below
    :data:`STATIC_MIN_RATE_HZ`. Returns ``t, u, y, fit_from_index, dt`` of that record."""
    m = int(1.0 / (dt * STATIC_RATE_HZ) + 1e-9)
    m = max(m, min(math.ceil(u.size / STATIC_MAX_SAMPLES), int(1.0 / (dt * STATIC_MIN_RATE_HZ) + 1e-9)))
    n = (u.size // m) * m if m > 1 else 0
    if kind in FULL_RATE_KINDS or m <= 1 or n // m < 64:
        return t, u, y, k0, dt
    log.info("chain: static stages fitted on %d-sample means (%.4g Hz)", m, 1.0 / (m * dt))
    ud = u[:n].reshape(-1, m).mean(axis=1)
    yd = y[:n].reshape(-1, m).mean(axis=1)
    return t[0] + np.arange(ud.size) * (m * dt), ud, yd, min(k0 // m, ud.size - 8), m * dt


#: the slow rest of a record must cover this share of the input's range (after the burn-in)
#: for its fast parts to be left out of a Preisach stage's fit
SLOW_COVERAGE = 0.95


def _fast_parts_to_leave_out(t: np.ndarray, u: np.ndarray, k0: int) -> np.ndarray | None:
    """One boolean per sample, True in the record's fast parts
    (:func:`~.dynamics_identify.fast_parts`: input content above ~10 Hz), for the static
    stages of a chain with a dynamics stage (which is fitted on them), when the rest of
    the record after the burn-in ``k0`` still covers :data:`SLOW_COVERAGE` of the input's
    range; None otherwise (a record of fast parts only keeps them; a caller's own
    ``exclude`` mask is used as given). A lag before or after
    the hysteresis turns fast triangles into wider loops, which a static fit takes for
    hysteresis: on the lumpy-Preisach reference scanner (a 260 Hz amplifier) recorded the
    way a lab does, without the piezo voltage, the Preisach stage fitted on the whole record
    left 2.97 % max at 1 line/s, fitted on its slow part 0.55 %. The fast parts are what the
    dynamics stage is fitted on."""
    from .dynamics_identify import fast_parts, is_uniform, parts_mask

    if not is_uniform(t):
        return None
    parts = fast_parts(u, t)
    if not parts:
        return None
    mask = parts_mask(u.size, parts)
    slow = u[k0:][~mask[k0:]]
    span = float(np.ptp(u[k0:]))
    if slow.size < 1000 or span <= 0 or float(np.ptp(slow)) < SLOW_COVERAGE * span:
        return None
    log.info("chain: the record's fast parts (%.3g s) left out of the static fit", float(mask.sum()) * float(t[1] - t[0]))
    return mask


def _without_transients(kind: str, options: dict[str, Any], u: np.ndarray, dt: float) -> dict[str, Any]:
    """``{"exclude": mask}`` for a Preisach fit of a record whose command ``u`` (sampled every
    ``dt`` [s], the static record itself: :data:`FULL_RATE_KINDS`) jumps
    (:mod:`afmctl.compensators.record_steps`): the samples within the settling time after a
    jump are left out of the fit. Empty otherwise, or when the caller gave its own mask."""
    from .record_steps import jumps, step_transients

    if kind not in FULL_RATE_KINDS or options.get("method", "nnls") == "for" or "exclude" in options:
        return {}
    mask = step_transients(u, dt)
    if mask.any():
        log.info("chain: %d jump(s) in the command; %.3g s after them left out of the static fit",
                 jumps(u).size, float(mask.sum()) * dt)
        return {"exclude": mask}
    return {}


def _also_left_out(options: dict[str, Any], exclude: Any) -> np.ndarray:
    """``exclude`` together with the samples ``options["exclude"]`` already leaves out (the
    jumps' transients, or the caller's own mask). A mask that is not one boolean per sample
    is passed on as it is, for the fit to name it in its one-line error."""
    exclude = np.asarray(exclude)
    given = options.get("exclude")
    if given is None:
        return exclude
    given = np.asarray(given)
    if given.dtype != bool or given.ndim != 1:
        return given
    if exclude.dtype != bool or exclude.shape != given.shape:
        return exclude
    return given | exclude


class _StageFit:
    """Identify one stage with a burn-in of ``k0`` samples: passed through to kinds with
    ``fits_with_burn_in``, cut off for the others. ``exclude``: True on the samples not
    measured, passed to the kinds that leave rows out of their fit (``fits_exclude``)."""

    def __init__(self, t: np.ndarray, u: np.ndarray, k0: int, exclude: np.ndarray | None = None) -> None:
        self.t, self.u, self.k0, self.exclude = t, u, k0, exclude

    def __call__(self, mcls: Any, x: np.ndarray, y: np.ndarray, **options: Any) -> Any:
        own = self.exclude is not None and getattr(mcls, "fits_exclude", False) and "exclude" not in options
        if self.k0 and getattr(mcls, "fits_with_burn_in", False):
            if own:
                options["exclude"] = self.exclude
            return mcls.identify(self.t, x, y, fit_from_index=self.k0, **options)
        k = self.k0
        if own:
            options["exclude"] = np.ascontiguousarray(self.exclude[k:])   # type: ignore[index]
        return mcls.identify(self.t[k:], np.ascontiguousarray(x[k:]), np.ascontiguousarray(y[k:]), **options)


def measured_rows(measured: Any, n: int) -> np.ndarray | None:
    """The ``measured`` mask of :meth:`ChainModel.identify` checked (one boolean per sample
    of ``n``); None when it is absent or all True."""
    if measured is None:
        return None
    m = sample_mask("measured", measured, n)
    if m.all():
        return None
    if np.count_nonzero(m) < 8:
        raise ModelError(f"measured: {np.count_nonzero(m)} sample(s) measured; at least 8 are needed")
    return m


def block_all(mask: np.ndarray, blocks: int) -> np.ndarray:
    """``mask`` reduced to ``blocks`` consecutive blocks of equal length (the block means of
    :func:`record_for_static`; the rest after the last whole block dropped): True where every
    sample of a block is True. The mask itself when ``blocks`` is its length."""
    if blocks == mask.size:
        return mask
    m = mask.size // blocks
    return np.asarray(mask[:blocks * m].reshape(blocks, m).all(axis=1))


def _fit_static(hcls: Any, fit: _StageFit, y: np.ndarray, dt: float, with_creep: bool,
                rounds: int, n_operators: int | None, options: dict[str, Any]) -> tuple[Any, Any]:
    """Preisach + creep: one joint fit (:mod:`afmctl.compensators.joint_creep_fit`). Other
    kinds alternate: hysteresis on the creep-corrected output, creep from its output to
    ``y`` (each stage run over the whole record, fitted after the burn-in)."""
    if with_creep and hcls is model_class("preisach") and options.get("method", "nnls") == "nnls":
        from .joint_creep_fit import fit_preisach_creep
        n = n_operators if n_operators is not None else JOINT_PREISACH_LEVELS
        return fit_preisach_creep(hcls, fit.t, fit.u, y, rounds=rounds, n_operators=n, options=options,
                                  creep_options=JOINT_CREEP_OPTIONS, fit_from_index=fit.k0)
    creep_cls = model_class("creep") if with_creep else None
    u = fit.u
    target = y
    hyst = creep = None
    for _ in range(rounds if with_creep else 1):
        hyst = fit(hcls, u, target, n_operators=n_operators, **dict(options))
        if creep_cls is None:
            break
        h = hyst.forward(dt).block(u)
        creep = fit(creep_cls, h, y, **CREEP_OPTIONS)
        target = creep.inverse(dt).block(y)
    return hyst, creep


def format_table(table: Sequence[dict[str, Any]]) -> str:
    """The selection table as text, selected first (what ``identify --model auto`` prints;
    rows from :func:`afmctl.compensators.selection.score_candidate`): the main split's
    held-out max and RMS, the mean RMS over the folds with their spread, the training RMS;
    under the selected row, why it won."""
    lines = [f"{'candidate':<34} {'held-out max':>14} {'held-out rms':>15} {'folds: mean rms [min–max]':>28} "
             f"{'train rms':>10}",
             f"{'':<34} {'[nm] (%)':>14} {'[nm] (%)':>15} {'[nm]':>28} {'[nm]':>10}"]
    for row in table:
        if "error" in row:
            lines.append(f"{row['structure']:<34} failed: {row['error']}"
                         + (f" (held-out rms {row['heldout_rms_nm']:.4g} nm)" if "heldout_rms_nm" in row else ""))
            continue
        folds = row.get("fold_rms_nm")
        fold_text = (f"{row['mean_rms_nm']:.4g} [{min(folds):.4g}–{max(folds):.4g}] ({len(folds)})"
                     if folds else "–")
        lines.append(f"{row['structure']:<34} {row['heldout_max_nm']:>7.4g} ({row['heldout_max_pct']:.3g}) "
                     f"{row['heldout_rms_nm']:>7.4g} ({row['heldout_rms_pct']:.3g}) {fold_text:>28} "
                     f"{row['train_rms_nm']:>10.4g}")
        if "why" in row:
            lines.append(f"  ↳ why: {row['why']}")
    return "\n".join(lines)
