"""Feedforward: the voltages [V] that make a model follow a target path [nm] (the inverse of
any model kind, with an optional offline inverse of the linear dynamics). ``afmctl
compensate`` reads the target CSV, calls :func:`compensate` and writes the voltages."""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from afmctl.compensators.base import ModelError, StreamingOperator
from afmctl.compensators.models import HysteresisModel

from ..data.datafiles import uniform_period
from ..errors import AfmctlError
from .models import CHUNK, Compensated, LimitsExceeded, model_limits_V


def compensate(model: HysteresisModel, y_nm: np.ndarray, *, dt_s: float | None = None,
               t_s: np.ndarray | None = None, limits_V: tuple[float, float] | None = None, clip: bool = False,
               dynamics: HysteresisModel | None = None, slew_V_per_s: float | None = None,
               model_name: str = "model", where: str = "target",
               progress: Callable[[int], None] | None = None, start: str = "rest") -> Compensated:
    """Voltages u [V] for the target displacement ``y_nm`` [nm], one per sample, through the
    model's inverse. Time-dependent models (epi, creep, chains) and a
    ``dynamics`` inverse need the sample period: ``dt_s`` or uniform times ``t_s`` [s].

    ``start``: ``"rest"`` (default) — the scanner has rested at the target's first point, so
    a creep stage starts settled there (:func:`at_rest`); ``"model"`` — every stage from the
    state stored in the model file (a scanner at rest at the start of the recording it was
    identified on, usually the bottom of the range, and moved to the first point at once:
    its creep then still runs toward it, and the voltages lean against that).

    ``limits_V``: the allowed range (default: the model's voltage range, else 0..150 V); a
    voltage outside it raises :class:`LimitsExceeded` unless ``clip``. ``dynamics`` (a
    'dynamics' model) or a chain's own dynamics stage is inverted offline over the whole
    target within the limits and ``slew_V_per_s`` (docs/COMPENSATORS.md); any other model's
    voltages are rate-limited to ``slew_V_per_s`` [V/s] (the report says how many samples,
    and when the target itself is too fast). ``model_name`` and
    ``where`` name the model and the target in error messages; ``progress(n)`` is called as
    chunks of a long target are done."""
    _check_kinds(model, dynamics, slew_V_per_s, model_name)
    y = np.ascontiguousarray(y_nm, dtype=np.float64).reshape(-1)
    if start not in STARTS:
        raise AfmctlError(f"start: {start!r}; allowed {', '.join(STARTS)}")
    if start == "rest" and y.size:
        model = at_rest(model, float(y[0]))
    with_dynamics = dynamics is not None or getattr(model, "dynamics", None) is not None
    dt = _period(model, with_dynamics or slew_V_per_s is not None, dt_s, t_s, where)
    lo, hi, source = model_limits_V(model, limits_V)
    report = None
    inverse = None if with_dynamics else _inverse(model, dt, model_name)   # blamed on the model
    try:
        if inverse is not None:
            u = run_chunked(inverse, y, progress)
        else:
            assert dt is not None  # _period gives one whenever dynamics are inverted
            u, report, clipped = _with_dynamics(model, dynamics, y, dt, (lo, hi), slew_V_per_s)
            if clipped and not clip:
                raise LimitsExceeded(f"{where}: {clipped} samples need voltages outside the limits {lo:g}..{hi:g} V "
                                     "even with the lowest band limit; pass clip=True to clip them",
                                     -1, float("nan"), clipped)
    except ModelError as err:
        raise ModelError(f"{where}: {err}") from None
    if not np.all(np.isfinite(u)):
        raise AfmctlError(f"{model_name}: the inverse produced non-finite voltages for {where}; "
                          "is the target inside the model's range?")
    bad = (u < lo) | (u > hi)
    n_bad = int(bad.sum())
    if n_bad and not clip:
        i = int(np.flatnonzero(bad)[0])
        raise LimitsExceeded(f"{where}: sample {i} needs {u[i]:.6g} V, outside the limits {lo:g}..{hi:g} V "
                             f"({source}; {n_bad} samples); pass limits_V or clip=True", i, float(u[i]), n_bad)
    if inverse is not None and slew_V_per_s is not None:   # the static inverse within the amplifier's slew
        assert dt is not None  # _period gives one whenever a slew limit is given
        u, report = _within_slew(u, dt, (lo, hi), slew_V_per_s)
        return Compensated(u, (lo, hi), source, n_bad, report)
    return Compensated(np.clip(u, lo, hi) if n_bad else u, (lo, hi), source, n_bad, report)


#: where :func:`compensate` takes the scanner to start from
STARTS = ("rest", "model")


def at_rest(model: HysteresisModel, y0_nm: float) -> HysteresisModel:
    """``model`` (a copy) with its creep at rest at the output ``y0_nm`` [nm]: the lag states of
    a linear creep stage (kind ``creep``, alone or in a chain) settled at the input that holds
    the output there, ``(y0 − offset_nm) / gain_nm_per_V`` (a creep at rest passes its input
    through; a chain's dynamics stage has unit DC gain). Other stages keep their stored state:
    a hysteresis memory is the history before the first point, which the first sample then
    moves to it. A model without such a stage is returned as it is."""
    from afmctl.compensators.creep import LinearCreepModel

    creep = model if model.kind == "creep" else getattr(model, "creep", None)
    if not isinstance(creep, LinearCreepModel):
        return model
    rested = creep.model_copy(update={"initial_V": (y0_nm - creep.offset_nm) / creep.gain_nm_per_V})
    return rested if creep is model else model.model_copy(update={"creep": rested})


def _within_slew(u: np.ndarray, dt: float, limits: tuple[float, float], slew: float) -> tuple[np.ndarray, str]:
    """A model without dynamics: its voltages clipped to ``limits`` and rate-limited to
    ``slew`` [V/s], and the report of what that took (the too-fast share included)."""
    from afmctl.compensators.dynamics_limits import LimitedInverse, rate_limit

    fastest = float(np.max(np.abs(np.diff(u)))) / dt if u.size > 1 else 0.0
    out, clipped, limited = rate_limit(u, limits[0], limits[1], slew * dt)
    res = LimitedInverse(out, math.inf, math.inf, fastest, clipped, limited, 0.0, fastest, slew)
    return out, res.report()


def _check_kinds(model: HysteresisModel, dynamics: HysteresisModel | None, slew: float | None, name: str) -> None:
    if model.kind == "scanner":
        raise AfmctlError(f"{name}: a scanner model; compensate one axis: model.axis('x')")
    if model.kind == "dynamics":
        raise AfmctlError(f"{name}: field kind: a 'dynamics' model maps nm to nm, not to volts; give it as "
                          "dynamics= beside a model that maps volts (pi, epi, creep, preisach, bouc-wen, rate-pi, rate-bouc-wen, chain)")
    own = getattr(model, "dynamics", None) is not None
    if dynamics is not None and own:
        raise AfmctlError(f"dynamics: {name} already holds a dynamics stage ({getattr(model, 'structure', '')})")
    if dynamics is not None and dynamics.kind != "dynamics":
        raise AfmctlError(f"dynamics: kind {dynamics.kind!r}; a 'dynamics' model is needed")
    if slew is not None and not (math.isfinite(slew) and slew > 0):
        raise AfmctlError(f"slew_V_per_s: {slew}; need a finite rate > 0 V/s")


def _period(model: HysteresisModel, with_dynamics: bool, dt_s: float | None, t_s: np.ndarray | None,
            where: str) -> float | None:
    if not (getattr(model, "time_dependent", False) or with_dynamics):
        return None
    if dt_s is not None:
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise AfmctlError(f"dt_s: {dt_s}; need a finite sample period > 0 s")
        return float(dt_s)
    if t_s is None:
        raise AfmctlError(f"{where}: a time-dependent model (kind {model.kind}) needs dt_s or t_s")
    return uniform_period(np.asarray(t_s, dtype=np.float64), where)


def _inverse(model: HysteresisModel, dt: float | None, name: str) -> StreamingOperator:
    try:
        return model.inverse(dt)
    except ModelError as err:  # e.g. a Bouc–Wen model that is not invertible
        raise ModelError(f"{name}: {err}") from None


def _with_dynamics(model: HysteresisModel, dynamics: HysteresisModel | None, y: np.ndarray, dt: float,
                   limits: tuple[float, float], slew: float | None) -> tuple[np.ndarray, str, int]:
    """The offline inverse within the limits and slew: a chain's own dynamics stage, or
    ``dynamics`` then the model's inverse (the same :func:`invert_within_limits`)."""
    from afmctl.compensators.dynamics_limits import invert_within_limits

    lo, hi = limits
    if dynamics is None:
        res = model.inverse_within_limits(y, dt, lo, hi, slew)  # type: ignore[attr-defined]  # chains only
    else:
        res = invert_within_limits(dynamics, y, dt, lambda: model.inverse(dt), lo, hi, slew)
    return res.u_V, res.report(), int(res.clipped)


def run_chunked(op: StreamingOperator, y: np.ndarray, progress: Callable[[int], None] | None = None) -> np.ndarray:
    """``op.block(y)`` in chunks of :data:`CHUNK` samples (the state carries over, so the result
    is identical); ``progress(n)`` after each chunk."""
    if y.size <= CHUNK:
        return np.asarray(op.block(y))
    out = np.empty_like(y)
    for start in range(0, y.size, CHUNK):
        seg = y[start:start + CHUNK]
        out[start:start + seg.size] = op.block(seg)
        if progress is not None:
            progress(seg.size)
    return out
