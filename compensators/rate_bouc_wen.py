"""Rate-dependent Bouc–Wen hysteresis (kind ``rate-bouc-wen``): loops that widen with the
scan rate, without moving while the input rests.

The Bouc–Wen model (:mod:`afmctl.compensators.bouc_wen`, seeds/000 eq. 20) with its
amplitude ``A`` grown by the input's smoothed rate, the rate law of the rate-dependent PI
model (:mod:`afmctl.compensators.rate_pi`; rate-dependent Bouc–Wen models of piezo stacks
let ``A`` depend on the input's rate or frequency the same way), the rate taken from the
input itself rather than from its low-passed copy: a line of a fast raster moves ``A`` by
its own speed, where the low-passed copy of a 50 Hz triangle hardly moves at all::

    ρ(t) = |du/dt| [V/s] through a first-order low-pass of time constant ``rate_tau_s``
    A(t) = A·(1 + c·min(ρ(t), ρ_max))                 c = ``rate_gain_s_per_V`` [s/V]
    ḣ    = A(t)·u̇ − β·|u̇|·h·|h|^(n−1) − γ·u̇·|h|^n,   y = d·u − h + offset_nm

``A(t)`` scales only what a move adds to ``h``: at rest nothing moves (where the
rate-dependent PI model's thresholds shrink back and drag its plays along, a creep of its
own). ``ρ_max`` (``rate_max_V_per_s``) is the identification record's highest rate: how the
loop grows past it is not known. A sample's ``A`` depends only on the inputs before it, so
the inverse is the Bouc–Wen inverse with that sample's ``A``: exact, and unique while
``d > 2·A·(1 + c·ρ_max)·β/(β+γ)``.

**Identification** (:meth:`RateBoucWenModel.identify`): the Bouc–Wen fit, then for each
time constant of :data:`RATE_TAUS_S` the same least squares with the growth ``c·ρ_max`` as
one more parameter (its Jacobian from the simulation's sensitivities, ``dh/dc`` among them:
:mod:`._bouc_wen_kernels`), started from the Bouc–Wen fit. The lowest residual is kept;
``c = 0`` (Bouc–Wen itself) is among the candidates. A record at one rate cannot tell
``c``: ``identify --model auto`` tries this kind only on a record that sweeps at several
rates (:mod:`.coverage`).
"""
from __future__ import annotations

import logging
import math
from typing import Any, ClassVar, Literal

import numpy as np
from numba import njit
from pydantic import Field, model_validator

from ._rate_pi_kernels import smoothing_factor
from .base import ModelError, StreamingOperator
from .bouc_wen import BoucWenModel, ReferenceBoucWen, _advance, _identify, _problem, _solve_u
from .input_checks import block_samples, finite_sample, number_option, sample_period

log = logging.getLogger(__name__)

#: smoothing time constants of the input rate tried by identification [s]
RATE_TAUS_S: tuple[float, ...] = (0.01, 0.03, 0.1)
#: the growth ``c·ρ_max`` the search starts from, and the most it may reach
START_GROWTH, MAX_GROWTH = 0.2, 3.0


def rate_step(v, aux, dt, a):
    """``aux = [ρ, u_prev]`` after the input ``v`` [V]: ρ ← ρ + a·(|v − u_prev|/dt − ρ)."""
    aux[0] = aux[0] + a * (abs(v - aux[1]) / dt - aux[0])
    aux[1] = v


_rate_step = njit(cache=True, nogil=True)(rate_step)


@njit(cache=True, nogil=True)
def _amplitude(A, c, rmax, aux):  # pragma: no cover - compiled
    return A * (1.0 + c * min(aux[0], rmax))


@njit(cache=True, nogil=True)
def _rates(u, aux, dt, a, out):  # pragma: no cover - compiled
    for k in range(u.shape[0]):
        out[k] = aux[0]
        _rate_step(u[k], aux, dt, a)


def rate_series(u: np.ndarray, dt_s: float, tau_s: float, u0_V: float) -> np.ndarray:
    """ρ [V/s] the operator sees at every sample of ``u`` [V] (the smoothed rate of the
    samples before it), from rest at ``u0_V``."""
    out = np.empty(u.size)
    _rates(np.ascontiguousarray(u, dtype=np.float64), np.array([0.0, float(u0_V)]), dt_s,
           smoothing_factor(dt_s, tau_s), out)
    return out


@njit(cache=True, nogil=True)
def rbw_forward_block(u, state, aux, p, c, rmax, a, dt, out):  # pragma: no cover - compiled
    """``u`` [V] → ``out`` [nm]; ``state = [h, u_prev]``, ``aux = [ρ, u_prev]`` carried in place,
    ``p = [d, A, β, γ, n, offset, du_sub]``."""
    for k in range(u.shape[0]):
        x = u[k]
        h = _advance(state[0], state[1], x, _amplitude(p[1], c, rmax, aux), p[2], p[3], p[4], p[6])
        state[0] = h
        state[1] = x
        out[k] = p[0] * x - h + p[5]
        _rate_step(x, aux, dt, a)


@njit(cache=True, nogil=True)
def rbw_inverse_block(y, state, aux, p, c, rmax, a, dt, out):  # pragma: no cover - compiled
    """Targets ``y`` [nm] → voltages ``out`` [V] whose forward output they are; state as
    :func:`rbw_forward_block`."""
    for k in range(y.shape[0]):
        A = _amplitude(p[1], c, rmax, aux)
        up = state[1]
        x = _solve_u(y[k], state[0], up, p[0], A, p[2], p[3], p[4], p[5], p[6])
        state[0] = _advance(state[0], up, x, A, p[2], p[3], p[4], p[6])
        state[1] = x
        out[k] = x
        _rate_step(x, aux, dt, a)


class RateBoucWenModel(BoucWenModel):
    """Rate-dependent Bouc–Wen model file (``kind = "rate-bouc-wen"``; module docstring):
    u [V] → y [nm]."""

    kind: Literal["rate-bouc-wen"] = "rate-bouc-wen"  # type: ignore[assignment]
    time_dependent: ClassVar[bool] = True
    rate_gain_s_per_V: float = Field(default=0.0, ge=0.0, le=1.0, allow_inf_nan=False,
                                     description="c: A grows by c·ρ, ρ the smoothed input rate [V/s]; 0 … 1 s/V")
    rate_max_V_per_s: float | None = Field(
        default=None, gt=0.0, allow_inf_nan=False,
        description="the rate [V/s] the growth stops at (the identification record's highest); None: none")
    rate_tau_s: float = Field(default=0.01, ge=1e-4, le=100.0, allow_inf_nan=False,
                              description="time constant of the rate's low-pass [s], 1e-4 … 100 s")

    @model_validator(mode="after")
    def _check_rate(self) -> "RateBoucWenModel":
        if self.rate_gain_s_per_V > 0 and self.rate_max_V_per_s is None:
            raise ValueError("rate_max_V_per_s is needed when rate_gain_s_per_V > 0 (the growth must stop)")
        return self

    def max_growth(self) -> float:
        """``1 + c·ρ_max``: the largest factor on ``A``."""
        return 1.0 + self.rate_gain_s_per_V * (self.rate_max_V_per_s or 0.0)

    LARGEST_A_TEXT: ClassVar[str] = "A·(1 + c·ρ_max)"

    def largest_A_nm_per_V(self) -> float:
        """``A·(1 + c·ρ_max)`` [nm/V]: the amplitude at the highest rate."""
        return self.A_nm_per_V * self.max_growth()

    def forward(self, dt_s: float | None = None) -> "RateBoucWenOperator":  # type: ignore[override]
        """Operator u [V] → y [nm] at sample period ``dt_s`` [s]."""
        return RateBoucWenOperator(self, sample_period(dt_s, "rate-dependent Bouc–Wen model"))

    def inverse(self, dt_s: float | None = None) -> "RateBoucWenOperator":  # type: ignore[override]
        """Exact inverse y [nm] → u [V] at sample period ``dt_s`` [s]."""
        self.check_invertible()
        return RateBoucWenOperator(self, sample_period(dt_s, "rate-dependent Bouc–Wen model"), inverse=True)

    def summary(self) -> str:
        return "\n".join([
            "rate-dependent Bouc–Wen model (kind rate-bouc-wen)",
            BoucWenModel.summary(self).split("\n", 1)[1],
            f"  rate dependence: A × (1 + {self.rate_gain_s_per_V:.4g} s/V · ρ), ρ = |du/dt| of the input low-passed "
            f"over {self.rate_tau_s * 1e3:.4g} ms, × {self.max_growth():.4g} at "
            f"{self.rate_max_V_per_s or 0.0:.4g} V/s and above"])

    @classmethod
    def identify(cls, t_s: Any, u_V: Any, y_nm: Any, n_operators: int | None = None,
                 **options: Any) -> "RateBoucWenModel":
        """Fit (d, A, β, γ, n, offset, c, τ) to uniformly sampled ``(t [s], u [V], y [nm])``
        (module docstring). Options as :meth:`BoucWenModel.identify`, and ``rate_tau_s`` to fix
        τ [s] instead of trying :data:`RATE_TAUS_S`; ``rate_gain_s_per_V`` with
        ``rate_max_V_per_s`` (and ``rate_tau_s``) fix the growth too, so that only the
        Bouc–Wen parameters are fitted (``auto`` takes the growth from the whole record when
        its training part sweeps at one rate: :mod:`.selection`); ``rate_start``, a dict of
        Bouc–Wen parameters (``d_nm_per_V``, ``A_nm_per_V``, ``beta``, ``gamma``, ``n``,
        ``offset_nm``), then starts that fit from them instead of from a Bouc–Wen fit."""
        opts = dict(options)
        start = opts.pop("rate_start", None)
        tau = opts.pop("rate_tau_s", None)
        gain, cap = opts.pop("rate_gain_s_per_V", None), opts.pop("rate_max_V_per_s", None)
        if opts.get("jacobian", "sensitivities") != "sensitivities":
            raise ModelError("jacobian: a rate-dependent Bouc–Wen fit uses the sensitivities; drop the option")
        if t_s is None:
            raise ModelError("t_s: a rate-dependent model needs the sample times")
        if (gain is None) != (cap is None) or (gain is not None and tau is None):
            raise ModelError("rate_gain_s_per_V, rate_max_V_per_s: give both with rate_tau_s, or neither")
        dt = sample_period(float(np.median(np.diff(np.asarray(t_s, dtype=float).ravel()))),
                           "rate-dependent Bouc–Wen model")
        taus = RATE_TAUS_S if tau is None else (number_option("rate_tau_s", tau, lo=1e-4, hi=100.0),)
        fixed = None if gain is None else (number_option("rate_gain_s_per_V", gain, lo=0.0, hi=1.0),
                                           number_option("rate_max_V_per_s", cap, lo=1e-9, hi=1e12))
        if fixed is not None and start is not None:
            fit = _fit_rate(cls, _start_model(start), t_s, u_V, y_nm, dt, taus[0], opts, fixed)
            if fit is not None:
                return fit
        base = _identify(BoucWenModel, t_s, u_V, y_nm, **opts)
        best = (base.fit_residual_nm or math.inf, cls(**base.model_dump(exclude={"kind"})))
        for tau_s in taus:
            fit = _fit_rate(cls, base, t_s, u_V, y_nm, dt, tau_s, opts, fixed)
            if fit is not None and (fixed is not None or (fit.fit_residual_nm or math.inf) < best[0]):
                best = (fit.fit_residual_nm or math.inf, fit)
        model = best[1]
        log.info("identify rate-bouc-wen: %s", model.summary().replace("\n", "; "))
        return model


def _start_model(start: Any) -> BoucWenModel:
    """The Bouc–Wen model of the parameters ``start`` (option ``rate_start``)."""
    if not isinstance(start, dict):
        raise ModelError(f"rate_start: {start!r}; need a dict of Bouc–Wen parameters")
    try:
        return BoucWenModel(**start)
    except ValueError as err:
        raise ModelError(f"rate_start: not a Bouc–Wen model ({' '.join(str(err).split())})") from None


def _fit_rate(cls: type[RateBoucWenModel], base: BoucWenModel, t_s: Any, u_V: Any, y_nm: Any, dt: float,
              tau_s: float, opts: dict[str, Any], fixed: tuple[float, float] | None = None
              ) -> RateBoucWenModel | None:
    """The least squares of the Bouc–Wen fit with the growth at the record's highest rate as
    one more parameter, at rate time constant ``tau_s`` [s], started from ``base``; with
    ``fixed = (c [s/V], ρ_max [V/s])`` that growth is kept as given. None when the record
    never moves or the fit is not an invertible model."""
    from scipy.optimize import least_squares

    prob, _ = _problem(t_s, u_V, y_nm, opts.get("n"), opts.get("max_rows", 20000), opts.get("u0_V"),
                       opts.get("fit_from_index", 0), "sensitivities")
    rho = rate_series(prob.u, dt, tau_s, prob.u0)
    top = float(np.max(rho)) if fixed is None else fixed[1]
    if not top > 0:
        return None
    prob.q, prob.top = np.ascontiguousarray(np.minimum(rho, top)), top
    prob.fixed_gain = None if fixed is None else fixed[0]
    d, A = base.d_nm_per_V, base.A_nm_per_V
    shape = [math.log(d), math.log(A / d), math.log(base.h_max_nm()), base.gamma / base.beta]
    p0, lb, ub = prob.start(shape, base.n, base.offset_nm, None if fixed else START_GROWTH, MAX_GROWTH)
    try:
        sol = least_squares(prob.resid, p0, jac=prob.jac, bounds=(lb, ub), x_scale="jac", max_nfev=100)
    except (ValueError, FloatingPointError, OverflowError):
        return None
    d, A, beta, gamma, nn, off = prob.unpack(sol.x)
    c = min(prob.rate_gain(sol.x), 1.0)
    try:
        model = cls(d_nm_per_V=d, A_nm_per_V=A, beta=beta, gamma=gamma, n=nn, offset_nm=off, u0_V=prob.u0,
                    rate_gain_s_per_V=c, rate_tau_s=tau_s, rate_max_V_per_s=top)
        res = (model.forward(dt).block(prob.u) - prob.y)[prob.k0:]
        model.inverse(dt)
    except (ValueError, ModelError) as err:
        log.info("rate-bouc-wen: tau %.4g s: not kept (%s)", tau_s, err)
        return None
    model.fit_residual_nm = float(np.sqrt(np.mean(res * res)))
    log.info("rate-bouc-wen: tau %.4g s: growth %.4g at %.4g V/s, residual %.4g nm", tau_s, model.max_growth(),
             top, model.fit_residual_nm)
    return model


class RateBoucWenOperator(StreamingOperator):
    """Forward (u [V] → y [nm]) or inverse (y [nm] → u [V]) rate-dependent Bouc–Wen operator
    at sample period ``dt_s`` [s]. ``use_numba=False`` runs the plain-Python reference
    (:class:`RateReference`: bit-identical, slower)."""

    def __init__(self, model: RateBoucWenModel, dt_s: float, inverse: bool = False, use_numba: bool = True) -> None:
        self.model, self.inverse, self.use_numba = model, inverse, use_numba
        self.dt = float(number_option("dt_s", dt_s, lo=1e-9, hi=10.0))
        self.a = smoothing_factor(self.dt, float(model.rate_tau_s))
        self.c = float(model.rate_gain_s_per_V)
        self.rmax = math.inf if model.rate_max_V_per_s is None else float(model.rate_max_V_per_s)
        self.p = model.kernel_params()
        self.state, self.aux = np.zeros(2), np.zeros(2)
        self.ref = None if use_numba else RateReference(self)
        self.reset()

    def reset(self) -> None:
        self.state[:] = (self.model.h0_nm, self.model.u0_V)
        self.aux[:] = (0.0, self.model.u0_V)

    def step(self, x: float) -> float:
        return float(self.block(np.array([finite_sample("y_nm" if self.inverse else "u_V", x)]))[0])

    def block(self, x: np.ndarray) -> np.ndarray:
        x = block_samples("y_nm" if self.inverse else "u_V", x)
        if self.ref is not None:
            return self.ref.run(x)
        out = np.empty_like(x)
        (rbw_inverse_block if self.inverse else rbw_forward_block)(x, self.state, self.aux, self.p, self.c,
                                                                   self.rmax, self.a, self.dt, out)
        return out


class RateReference(ReferenceBoucWen):
    """Plain-Python reference of :class:`RateBoucWenOperator` on its state arrays (the same
    operations in the same order: bit-identical, tested)."""

    def __init__(self, op: RateBoucWenOperator) -> None:
        super().__init__(op.model)
        self.op, self.du_sub = op, float(op.p[6])

    def run(self, x: np.ndarray) -> np.ndarray:
        op, out = self.op, np.empty(x.shape[0])
        for k, v in enumerate(x.tolist()):
            self.h, self.up = float(op.state[0]), float(op.state[1])
            self.A = op.p[1] * (1.0 + op.c * min(op.aux[0], op.rmax))
            if op.inverse:
                v = self.solve(v)
            self.h = self.advance(self.h, self.up, v)
            op.state[:] = (self.h, v)
            out[k] = v if op.inverse else self.d * v - self.h + self.off
            rate_step(v, op.aux, op.dt, op.a)
        return out

