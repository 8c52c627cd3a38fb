"""Fit a model of the scanner to a recording t [s], u [V], y [nm]: any kind, a chain
(``preisach+creep``...) or ``auto`` (held-out selection). The same steps as ``afmctl identify
--data``: the recording is conditioned (units, spikes, uniform sampling, burn-in, sensor
delay: :func:`afmctl.data.identdata.condition`), then fitted by the kind's own ``identify``
(:mod:`afmctl.compensators`) or :func:`afmctl.compensators.selection.select_model`; the fit
residual is counted after the burn-in, as the command prints it."""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from afmctl.compensators.base import ModelError
from afmctl.compensators.models import HysteresisModel, model_class

from ..data.datafiles import read_csv
from ..data.identdata import Y_UNITS, Conditioned, condition, delayed, excitation_notes
from ..data.prediction import predict_nm
from ..errors import AfmctlError


@dataclass
class Identified:
    """A fitted ``model`` and how well it fits: ``y_fit_nm`` is its output over ``t_s`` (the
    conditioned record from sample ``first``); ``rms_nm``/``max_nm`` the residual from the
    end of the burn-in, ``span_nm`` the measured span there; ``notes`` what conditioning did,
    ``excitation`` what the input cannot identify; ``table`` the held-out ranking (auto)."""

    model: HysteresisModel
    t_s: np.ndarray
    u_V: np.ndarray
    y_nm: np.ndarray
    y_fit_nm: np.ndarray
    fit_from_s: float | None
    rms_nm: float
    max_nm: float
    span_nm: float
    notes: list[str] = field(default_factory=list)
    excitation: list[str] = field(default_factory=list)
    table: list[Any] | None = None
    fit_from: int = 0
    holdout_fraction: float | None = None
    criterion: str | None = None

    def residual(self) -> str:
        """The fit residual as ``afmctl identify`` prints it."""
        return (f"rms {self.rms_nm:.4g} nm, max {self.max_nm:.4g} nm ({100 * self.max_nm / self.span_nm:.3g} % of "
                f"the {self.span_nm:.4g} nm span)"
                + (f", from t = {self.fit_from_s:.4g} s" if self.fit_from_s is not None else ""))


@dataclass(frozen=True)
class Names:
    """What errors call the inputs: the Python arguments (these defaults) or the options of
    ``afmctl identify`` (:data:`OPTIONS`); ``option`` prefixes a ``params`` key, ``chain``
    names a chain's kind (``{kind}`` is replaced)."""

    params: str = "params"
    option: str = ""
    y_unit: str = "y_unit"
    n_operators: str = "n_operators"
    burn_in_none: str = "burn_in='none'"
    chain: str = "kind {kind!r}"


#: ``jobs`` of ``auto``: at most this many worker processes
MAX_JOBS = 16

OPTIONS = Names("--param", "--param ", "--y-unit", "--operators", "--burn-in none", "--model {kind}")


def read_recording(path: str | Path, columns: tuple[str, ...] = ("t", "u", "y"),
                   optional: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """The named columns of a CSV file (header row) as float64 arrays (``optional`` ones
    when present, e.g. ``v``: the recorded piezo voltage [V]); ``t`` strictly increasing.
    Errors name the file, the row and the column."""
    return read_csv(path, columns, min_rows=2, optional=optional)


def identify(kind: str, data: str | Path | None = None, *, t_s: np.ndarray | None = None,
             u_V: np.ndarray | None = None, y_nm: np.ndarray | None = None, v_V: np.ndarray | None = None,
             n_operators: int | None = None,
             y_unit: str = "nm", burn_in: str = "auto", delay: str = "auto", despike: bool = True,
             name: str | None = None, measured: np.ndarray | None = None, **params: Any) -> Identified:
    """Fit ``kind`` (pi, epi, creep, preisach, bouc-wen, rate-pi, rate-bouc-wen, dynamics, amplifier,
    ``[amplifier+]KIND[+creep][+dynamics]`` or ``auto``) to a CSV file ``data`` (columns t,u,y
    and, when the recording has it, v: the piezo voltage [V]) or to arrays ``t_s``, ``u_V``,
    ``y_nm`` (y in ``y_unit``: nm or um) and optionally ``v_V``. A chain or ``auto`` with the
    piezo voltage identifies an amplifier stage before the hysteresis from it. ``burn_in``: ``auto`` (until the input has passed
    both extremes), ``none`` or seconds; ``delay``: ``auto`` or seconds; ``params``: the
    kind's options (``afmctl identify --help``, ``--param``), for auto also ``candidates``,
    ``holdout_fraction``, ``criterion``, ``with_dynamics`` and ``jobs`` (worker processes
    fitting the candidates side by side, at most :data:`MAX_JOBS`; the same model as one).
    ``name``: what messages call the arrays (default ``data``; a CSV is called by its path).
    ``measured``: one 0/1 per sample (or the CSV's column ``measured``), 0 where ``y`` was not
    measured (``afmctl calibrate``'s holds between pieces): those samples are left out of
    the fit and the residual, the model's memory runs through them."""
    c, where = prepare(kind, data, t_s=t_s, u_V=u_V, y_nm=y_nm, v_V=v_V, n_operators=n_operators, y_unit=y_unit,
                       burn_in=burn_in, delay=delay, despike=despike, name=name, measured=measured)
    return fit(kind, c, where, n_operators, params)


def is_chain(kind: str) -> bool:
    """``auto`` and ``KIND+creep[+dynamics]`` are fitted as chains (uniform samples, whole record)."""
    return kind == "auto" or "+" in kind


def prepare(kind: str, data: str | Path | None = None, *, t_s: np.ndarray | None = None,
            u_V: np.ndarray | None = None, y_nm: np.ndarray | None = None, v_V: np.ndarray | None = None,
            n_operators: int | None = None,
            y_unit: str = "nm", burn_in: str = "auto", delay: str = "auto", despike: bool = True,
            names: Names = Names(), name: str | None = None,
            measured: np.ndarray | None = None) -> tuple[Conditioned, str]:
    """The first step of :func:`identify`: the options checked, the recording read (a CSV
    path, or arrays t [s], u [V], y [``y_unit``]) and conditioned as ``kind`` needs it
    (:func:`afmctl.data.identdata.condition`); returns it and the name errors give it."""
    if n_operators is not None and n_operators < 1:
        raise AfmctlError(f"{names.n_operators}: {n_operators} must be ≥ 1")
    if y_unit not in Y_UNITS:
        raise AfmctlError(f"{names.y_unit}: {y_unit!r} is not known; allowed: nm, um")
    uniform = True
    if not is_chain(kind):
        cls = model_class(kind)
        if cls.has_own_delay and delay == "auto":  # the kind fits its delay itself
            delay = "0"
        uniform = getattr(cls, "time_dependent", False)
    t, u, y, v, where, read = _inputs(data, t_s, u_V, y_nm, v_V)
    where = name or where
    if measured is not None and read is not None:
        raise AfmctlError("identify: give measured with the arrays, not with a CSV (its column measured)")
    return condition(t, u, y * Y_UNITS[y_unit], where, burn_in=burn_in, delay=delay, despike=despike,
                     uniform=uniform, dynamics_delay=kind == "auto" or "dynamics" in kind, v_V=v,
                     measured=read if measured is None else measured), where


def fit(kind: str, c: Conditioned, where: str, n_operators: int | None = None, params: dict[str, Any] | None = None,
        names: Names = Names()) -> Identified:
    """The second step of :func:`identify`: fit ``kind`` to the conditioned recording ``c``
    (from :func:`prepare`; ``where`` names it in errors) and count the residual."""
    if is_chain(kind):
        return _chain(kind, c, n_operators, dict(params or {}), where, names)
    return _single(model_class(kind), kind, c, n_operators, dict(params or {}), where, names)


def _inputs(data: str | Path | None, t_s: np.ndarray | None, u_V: np.ndarray | None, y_nm: np.ndarray | None,
            v_V: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, str, np.ndarray | None]:
    """``t, u, y, v, where, measured``: the arrays, or the CSV's columns (``v`` and
    ``measured`` when it has them)."""
    arrays = (t_s, u_V, y_nm, v_V)
    if data is not None:
        if any(a is not None for a in arrays):
            raise AfmctlError("identify: give either data (a CSV path) or the arrays t_s, u_V, y_nm, not both")
        d = read_recording(data, optional=("v", "measured"))
        return d["t"], d["u"], d["y"], d.get("v"), str(data), d.get("measured")
    if t_s is None or u_V is None or y_nm is None:
        raise AfmctlError("identify: give data (a CSV path with columns t,u,y) or all of t_s, u_V, y_nm")
    t, u, y = (np.ascontiguousarray(a, dtype=np.float64).reshape(-1) for a in (t_s, u_V, y_nm))
    v = None if v_V is None else np.ascontiguousarray(v_V, dtype=np.float64).reshape(-1)
    if not t.size == u.size == y.size or t.size < 2 or (v is not None and v.size != t.size):
        names = "t_s, u_V, y_nm" + ("" if v is None else ", v_V")
        sizes = ", ".join(str(a.size) for a in (t, u, y) + (() if v is None else (v,)))
        raise AfmctlError(f"identify: {names} need one equal length ≥ 2 (got {sizes})")
    cols = np.concatenate([t, u, y] + ([] if v is None else [v]))
    if not np.all(np.isfinite(cols)) or np.any(np.diff(t) <= 0):
        raise AfmctlError("identify: t_s, u_V, y_nm" + ("" if v is None else ", v_V")
                          + " must be finite and t_s strictly increasing")
    return t, u, y, v, "data", None


def _fit_errors(kind: str, where: str, err: Exception, names: Names) -> Exception:
    """A fit's exception as the one clear error the command line shows too."""
    if isinstance(err, TypeError):
        label = names.chain.format(kind=kind) if is_chain(kind) else f"kind {kind!r}"
        return AfmctlError(f"{names.params}: not accepted by {label} ({err})")
    if isinstance(err, np.linalg.LinAlgError):
        return ModelError(f"{where}: the fit failed ({err}); is the input excited over its range?")
    if isinstance(err, ValueError) and not isinstance(err, ModelError):
        return AfmctlError(f"{names.params}: a value is not accepted by kind {kind!r} ({err})")
    return ModelError(f"{where}: {err}")


def _burn_in_too_long(err: BaseException, opts: dict[str, Any], params: dict[str, Any]) -> bool:
    """The fit refused the ``fit_from_index`` the burn-in set (not one the user passed, and
    not another error whose text merely lists the option, e.g. an unknown ``--param``)."""
    return (isinstance(err, ModelError) and str(err).startswith("fit_from_index:")
            and "fit_from_index" in opts and "fit_from_index" not in params)


def _single(cls: type[HysteresisModel], kind: str, c: Conditioned, n_operators: int | None,
            params: dict[str, Any], where: str, names: Names) -> Identified:
    """One kind, as ``afmctl identify`` fits it: kinds that take ``fit_from_index`` run
    through the burn-in, others are fitted after it."""
    opts = dict(params)
    if kind == "amplifier":           # command → piezo voltage: fitted to the column v (its "y", in V)
        if c.v_V is None:
            raise AfmctlError(f"{where}: kind amplifier is fitted to the recorded piezo voltage: the data need a "
                              "column v (V); without it, identify a chain amplifier+KIND[+creep]+dynamics")
        c = replace(c, y_nm=c.v_V, delay_s=0.0)
    t, u, y, k0 = c.t_s, delayed(c.t_s, c.u_V, c.delay_s), c.y_nm, c.fit_from
    skip = None if kind == "amplifier" else c.left_out
    if skip is not None and not cls.fits_exclude:
        c.notes.append(f"measured: {np.count_nonzero(skip)} sample(s) were not measured (column measured 0) and kind "
                       f"{kind} fits them as if they were; a chain or kind pi, preisach or creep leaves them out")
        skip = None
    if k0 and getattr(cls, "fits_with_burn_in", False):
        opts.setdefault("fit_from_index", k0)
    elif k0:
        t, u, y, k0 = t[k0:], u[k0:], y[k0:], 0
        skip = None if skip is None else skip[c.fit_from:]
    if skip is not None and "exclude" not in opts:
        opts["exclude"] = np.ascontiguousarray(skip)
    try:
        model = cls.identify(t, u, y, n_operators=n_operators, **opts)
    except (TypeError, ValueError, ModelError, np.linalg.LinAlgError) as err:
        if _burn_in_too_long(err, opts, params):
            raise ModelError(f"{where}: after the burn-in ({float(c.t_s[k0] - c.t_s[0]):.4g} s, until the input "
                             f"passed both extremes) too few samples remain ({err}); record more cycles or pass "
                             f"{names.burn_in_none}") from None
        raise _fit_errors(kind, where, err, names) from None
    if not cls.has_own_delay:
        model.delay_s = c.delay_s
    if model.u_range_V is None:        # compensate's default limits
        model.u_range_V = (float(c.u_V.min()), float(c.u_V.max()))
    first = c.u_V.size - t.size
    predict = getattr(model, "predict_linear", None)  # dynamics: nm → nm, needs the fitted gain
    y_fit = (predict(t, u, y, float(np.median(np.diff(t)))) if predict is not None
             else predict_nm(model, t, c.u_V[first:], where))
    return _result(model, c, first, np.asarray(y_fit))


def _result(model: HysteresisModel, c: Conditioned, first: int, y_fit: np.ndarray,
            table: list[Any] | None = None) -> Identified:
    t, u, y = c.t_s[first:], c.u_V[first:], c.y_nm[first:]
    k = c.fit_from - first
    seen = np.isfinite(y_fit[k:])          # dynamics: only its fitted segment is predicted
    if c.measured is not None:             # samples not measured are not residuals
        seen &= c.measured[first:][k:]
    res = (y_fit - y)[k:][seen]
    span = float(np.ptp(y[k:][seen])) or 1.0
    return Identified(model, t, u, y, y_fit, float(c.t_s[c.fit_from]) if c.fit_from else None,
                      float(np.sqrt(np.mean(res ** 2))), float(np.max(np.abs(res))), span, list(c.notes),
                      excitation_notes(c.t_s, c.u_V), table, k)


def _chain(kind: str, c: Conditioned, n_operators: int | None, params: dict[str, Any], where: str,
           names: Names) -> Identified:
    """A chain or ``auto``, as ``afmctl identify`` fits them (the whole record, the burn-in
    only setting the memory)."""
    from afmctl.compensators.chain import ChainModel, parse_structure
    from afmctl.compensators.selection import CRITERIA, select_model

    opts = dict(params)
    if n_operators is not None:
        opts["n_operators"] = n_operators
    t, u, y, k = c.t_s, delayed(c.t_s, c.u_V, c.delay_s), c.y_nm, c.fit_from
    v = None if c.v_V is None else delayed(c.t_s, c.v_V, c.delay_s)
    table: list[Any] | None = None
    holdout: float | None = None
    criterion: str | None = None
    try:
        if kind == "auto":
            holdout = float(opts.pop("holdout_fraction", 0.3))
            candidates = opts.pop("candidates", None)
            criterion = opts.pop("criterion", "rms")
            with_dynamics = opts.pop("with_dynamics", True)
            if not isinstance(with_dynamics, bool):
                raise AfmctlError(f"{names.option}with_dynamics: {with_dynamics!r}; allowed true or false")
            if criterion not in CRITERIA:
                raise AfmctlError(f"{names.option}criterion: {criterion!r}; allowed {', '.join(CRITERIA)} "
                                  "(held-out error)")
            jobs = opts.pop("jobs", 1)
            if isinstance(jobs, bool) or not isinstance(jobs, int) or not 1 <= jobs <= MAX_JOBS:
                raise AfmctlError(f"{names.option}jobs: {jobs!r}; allowed a whole number 1 … {MAX_JOBS} "
                                  "(worker processes fitting the candidates side by side)")
            extra = {"candidates": tuple(candidates)} if candidates else {}
            model, table = select_model(t, u, y, holdout_fraction=holdout, options=opts, fit_from_index=k,
                                        criterion=criterion, with_dynamics=with_dynamics, v_V=v, jobs=jobs,
                                        measured=c.measured, **extra)
        else:
            parse_structure(kind)
            model = ChainModel.identify(t, u, y, structure=kind, fit_from_index=k, v_V=v, measured=c.measured,
                                        **opts)
    except (TypeError, ModelError, np.linalg.LinAlgError) as err:
        raise _fit_errors(kind, where, err, names) from None
    y_fit = np.asarray(model.forward(float(np.median(np.diff(t)))).block(np.ascontiguousarray(u)))
    model.delay_s = c.delay_s
    if model.u_range_V is None:        # compensate's default limits
        model.u_range_V = (float(np.min(u)), float(np.max(u)))
    out = _result(model, c, 0, y_fit, table)
    out.u_V, out.holdout_fraction, out.criterion = u, holdout, criterion
    return out
