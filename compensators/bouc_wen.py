"""Bouc–Wen hysteresis: forward operator, exact inverse and identification.

Source: Sadeghzadeh & Korayem, *Role of mechanical and thermal nonlinearities in imaging
by AFM* (seeds/000), eq. 20::

    ḣ = A·u̇ − β·|u̇|·h·|h|^(n−1) − γ·u̇·|h|^n,      y = d·u − h  (+ offset_nm)

u [V] input, h [nm] hysteretic part, y [nm] displacement; ``d`` and ``A`` in nm/V,
``β`` and ``γ`` in nm^(1−n)/V, ``n ≥ 1`` dimensionless.

Rate independence. Dividing by u̇ gives ``dh/du = A − (β·sgn(Δu)·sgn(h) + γ)·|h|^n``:
the model only depends on the path of u, not on time. The operator integrates this ODE
over the input increment of each sample with classical RK4 on ``m = ceil(|Δu|/du_sub)``
equal sub-steps, where ``du_sub = 0.1 / k_max`` and ``k_max = n·(β+|γ|)·h_max^(n−1)`` is
the largest stiffness (``h_max = (A/(β+γ))^(1/n)`` the saturation of h). Every sub-step
is therefore inside RK4's stability region whatever the sample step: the update is
stable for any step size and the result does not depend on the sampling rate beyond
the integration error (RK4; near h = 0 the term h·|h|^(n−1) is not smooth, so in
practice ~1e-6 of the output range between a 1-sample and a 2000-sample path).
A move longer than 10⁶ sub-steps integrates only its last 10⁶ sub-steps (10⁵ stiffness
lengths, long after h has reached its branch), so absurd inputs (1e300 V) or very stiff
models cost at most 10⁶ sub-steps per sample and still give finite outputs.

Initial state (``reset``): input ``u0_V`` with ``h = h0_nm`` (defaults 0 V, 0 nm).

Stability conditions checked on load: ``A > 0``, ``β + γ > 0``, ``β − γ ≥ 0``, ``n ≥ 1``.

Inverse (multiplicative structure): ``u = (y_d − offset + ĥ)/d`` where ``ĥ`` is the model's
h driven by that same u. The implicit equation is solved per sample by safeguarded
Newton iterations (to rounding), and the state then advances with the forward update, so
``forward(inverse(y)) == y`` to ~1e-12 relative. It is unique when ``d`` exceeds the largest
slope of h, ``d > 2·A·β/(β+γ)``; :meth:`BoucWenModel.inverse` refuses models violating that.
"""
from __future__ import annotations

import logging
import math
from typing import Any, ClassVar, Literal

import numpy as np
from numba import njit
from pydantic import Field, model_validator

from ._bouc_wen_kernels import bw_sens_nb, substeps_nb, substeps_py
from .base import ModelError, StreamingOperator, check_finite
from .errortext import plain_repr
from .input_checks import block_samples, finite_sample, number_option
from .models import HysteresisModel

log = logging.getLogger(__name__)

#: sub-step as a fraction of the inverse largest stiffness (RK4 is stable below 2.78)
_SUB = 0.1
#: most RK4 sub-steps per sample; longer moves integrate only their last _MAX_SUB sub-steps
_MAX_SUB = 1000000
#: the sensitivity kernel's rates for a rate-independent fit: none
_NO_RATE = np.zeros(0)


class BoucWenModel(HysteresisModel):
    """Bouc–Wen model (eq. 20), input u [V] → displacement y [nm]."""

    kind: Literal["bouc-wen"] = "bouc-wen"
    d_nm_per_V: float = Field(description="linear gain d [nm/V]")
    A_nm_per_V: float = Field(description="hysteresis amplitude A [nm/V], > 0")
    beta: float = Field(description="shape parameter β [nm^(1−n)/V]")
    gamma: float = Field(description="shape parameter γ [nm^(1−n)/V]")
    n: float = Field(1.0, ge=1.0, le=10.0, description="exponent n (≥ 1)")
    offset_nm: float = Field(0.0, description="output offset [nm]")
    u0_V: float = Field(0.0, description="input at reset [V]")
    h0_nm: float = Field(0.0, description="hysteretic state h at reset [nm]")
    fit_residual_nm: float | None = Field(None, description="RMS fit residual on the data [nm]")

    time_dependent: ClassVar[bool] = False
    fits_with_burn_in: ClassVar[bool] = True

    @model_validator(mode="after")
    def _check(self) -> "BoucWenModel":
        for name in ("d_nm_per_V", "A_nm_per_V", "beta", "gamma", "n", "offset_nm", "u0_V", "h0_nm"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite")
        if self.A_nm_per_V <= 0:
            raise ValueError(f"A_nm_per_V must be > 0 (got {self.A_nm_per_V})")
        if self.beta + self.gamma <= 0:
            raise ValueError(f"beta + gamma must be > 0 (got beta={self.beta}, gamma={self.gamma})")
        if self.beta - self.gamma < 0:
            raise ValueError(f"beta − gamma must be >= 0 (got beta={self.beta}, gamma={self.gamma})")
        if self.d_nm_per_V <= 0:
            raise ValueError(f"d_nm_per_V must be > 0 (got {self.d_nm_per_V})")
        return self

    #: the largest amplitude (:meth:`largest_A_nm_per_V`) in the inverse's uniqueness bound, in words
    LARGEST_A_TEXT: ClassVar[str] = "A"

    def largest_A_nm_per_V(self) -> float:
        """The largest amplitude ``A`` the model integrates with [nm/V] (``A`` itself here)."""
        return self.A_nm_per_V

    def h_max_nm(self) -> float:
        """Saturation of |h| at the largest amplitude: (A/(β+γ))^(1/n) [nm]."""
        return (self.largest_A_nm_per_V() / (self.beta + self.gamma)) ** (1.0 / self.n)

    def du_sub_V(self) -> float:
        """Integration sub-step [V] (see module docstring)."""
        hm = max(self.h_max_nm(), abs(self.h0_nm))
        k = self.n * (self.beta + abs(self.gamma)) * hm ** (self.n - 1.0)
        k = max(k, 1e-300)
        return _SUB / k

    def params(self) -> np.ndarray:
        return np.array([self.d_nm_per_V, self.A_nm_per_V, self.beta, self.gamma, self.n, self.offset_nm])

    def kernel_params(self) -> np.ndarray:
        """``p = [d, A, β, γ, n, offset, du_sub]`` of the compiled kernels."""
        return np.append(self.params(), self.du_sub_V()).astype(np.float64)

    def check_invertible(self) -> None:
        """:class:`ModelError` unless ``d`` exceeds the largest slope of h, 2·A·β/(β+γ) at the
        largest amplitude: the inverse is then unique (module docstring)."""
        lim = 2.0 * self.largest_A_nm_per_V() * self.beta / (self.beta + self.gamma)
        if self.d_nm_per_V <= lim:
            raise ModelError(f"d_nm_per_V: {self.d_nm_per_V:g} is too small for an invertible model; "
                             f"allowed: > 2·{self.LARGEST_A_TEXT}·β/(β+γ) = {lim:g} nm/V")

    def forward(self, dt_s: float | None = None) -> "BoucWenOperator":
        """Streaming operator u [V] → y [nm]. ``dt_s`` is ignored (rate-independent)."""
        return BoucWenOperator(self)

    def inverse(self, dt_s: float | None = None) -> "BoucWenInverse":
        """Exact inverse y [nm] → u [V] (see module docstring)."""
        self.check_invertible()
        return BoucWenInverse(self)

    @classmethod
    def identify(cls, t_s: Any, u_V: Any, y_nm: Any, n_operators: int | None = None, **options: Any) -> "BoucWenModel":
        """Fit (d, A, β, γ, n, offset) by nonlinear least squares (scipy.optimize.least_squares).

        ``n_operators`` is ignored (Bouc–Wen has no operators). Options: ``n`` (fix the
        exponent instead of fitting it), ``max_rows`` (subsample the data for speed,
        default 20000 — the model is always simulated on every sample), ``u0_V`` (input at
        which h = 0, default the first sample), ``fit_from_index`` (samples before it
        only drive the state: a burn-in).
        """
        return _identify(cls, t_s, u_V, y_nm, **options)

    def summary(self) -> str:
        lines = [
            "Bouc–Wen model (eq. 20): ḣ = A·u̇ − β|u̇|h|h|^(n−1) − γ·u̇|h|^n,  y = d·u − h + offset",
            f"  d = {self.d_nm_per_V:.6g} nm/V, A = {self.A_nm_per_V:.6g} nm/V, beta = {self.beta:.6g}, "
            f"gamma = {self.gamma:.6g} (nm^(1−n)/V), n = {self.n:.4g}, offset = {self.offset_nm:.6g} nm",
            f"  saturation of h: {self.h_max_nm():.6g} nm; integration sub-step {self.du_sub_V():.4g} V",
        ]
        if self.fit_residual_nm is not None:
            lines.append(f"  identified by nonlinear least squares: residual {self.fit_residual_nm:.4g} nm RMS")
        return "\n".join(lines)


# ------------------------------------------------------------------------ kernels
@njit(cache=True)
def _rhs(h, sgn, A, beta, gamma, n):
    ah = abs(h)
    p = ah ** n
    s = 1.0 if h > 0.0 else (-1.0 if h < 0.0 else 0.0)
    return A - (beta * sgn * s + gamma) * p


@njit(cache=True)
def _advance(h, u_from, u_to, A, beta, gamma, n, du_sub):
    """h after moving the input from u_from to u_to (RK4 on dh/du, equal sub-steps)."""
    du = u_to - u_from
    if du == 0.0:
        return h
    sgn, m, dx = substeps_nb(du, du_sub, _MAX_SUB)  # a huge move: only its last _MAX_SUB sub-steps
    for _ in range(m):
        k1 = _rhs(h, sgn, A, beta, gamma, n)
        k2 = _rhs(h + 0.5 * dx * k1, sgn, A, beta, gamma, n)
        k3 = _rhs(h + 0.5 * dx * k2, sgn, A, beta, gamma, n)
        k4 = _rhs(h + dx * k3, sgn, A, beta, gamma, n)
        h = h + dx / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return h


@njit(cache=True)
def bw_forward_step(x, state, p):
    """One sample u [V] → y [nm]; ``state = [h, u_prev]`` updated in place,
    ``p = [d, A, β, γ, n, offset, du_sub]``."""
    h = _advance(state[0], state[1], x, p[1], p[2], p[3], p[4], p[6])
    state[0] = h
    state[1] = x
    return p[0] * x - h + p[5]


@njit(cache=True)
def bw_forward_block(u, state, p):
    """:func:`bw_forward_step` over a block; returns y [nm]."""
    y = np.empty(u.shape[0])
    for k in range(u.shape[0]):
        y[k] = bw_forward_step(u[k], state, p)
    return y


@njit(cache=True)
def _solve_u(yd, h, up, d, A, beta, gamma, n, off, du_sub):
    """u with d·u − h(u) + off = yd from state (h, up); safeguarded Newton."""
    y_prev = d * up - h + off
    if yd == y_prev:
        return up
    sgn = 1.0 if yd > y_prev else -1.0
    slope = d - _rhs(h, sgn, A, beta, gamma, n)
    u = up + (yd - y_prev) / slope
    # bracket: g(up) has the sign of (y_prev − yd)
    if sgn > 0:
        a = up
        b = math.inf
    else:
        a = -math.inf
        b = up
    scale = abs(yd) + abs(d) * (abs(up) + 1.0)
    for _ in range(100):
        hu = _advance(h, up, u, A, beta, gamma, n, du_sub)
        g = d * u - hu + off - yd
        if abs(g) <= 1e-15 * scale:
            return u
        if g > 0.0:
            b = u
        else:
            a = u
        s2 = 1.0 if u >= up else -1.0
        gp = d - _rhs(hu, s2, A, beta, gamma, n)
        un = u - g / gp
        if not (un > a and un < b):
            if math.isinf(a) or math.isinf(b):
                un = u - 2.0 * g / gp
            else:
                un = 0.5 * (a + b)
        if un == u:
            return u
        u = un
    return u


@njit(cache=True)
def bw_inverse_step(yd, state, p):
    """One target y [nm] → u [V] with forward(u) == y; ``state``/``p`` as for
    :func:`bw_forward_step`."""
    h = state[0]
    up = state[1]
    u = _solve_u(yd, h, up, p[0], p[1], p[2], p[3], p[4], p[5], p[6])
    state[0] = _advance(h, up, u, p[1], p[2], p[3], p[4], p[6])
    state[1] = u
    return u


@njit(cache=True)
def bw_inverse_block(yd, state, p):
    """:func:`bw_inverse_step` over a block; returns u [V]."""
    out = np.empty(yd.shape[0])
    for k in range(yd.shape[0]):
        out[k] = bw_inverse_step(yd[k], state, p)
    return out


class ReferenceBoucWen:
    """Plain-Python reference of the forward operator and its inverse (no numba): the
    same arithmetic in the same order as the kernels, tested bit for bit."""

    def __init__(self, model: BoucWenModel) -> None:
        self.d, self.A, self.beta, self.gamma = model.d_nm_per_V, model.A_nm_per_V, model.beta, model.gamma
        self.n, self.off, self.du_sub = model.n, model.offset_nm, model.du_sub_V()
        self.h0, self.u0 = model.h0_nm, model.u0_V
        self.reset()

    def reset(self) -> None:
        self.h, self.up = float(self.h0), float(self.u0)

    def rhs(self, h: float, sgn: float) -> float:
        s = 1.0 if h > 0.0 else (-1.0 if h < 0.0 else 0.0)
        return self.A - (self.beta * sgn * s + self.gamma) * abs(h) ** self.n

    def advance(self, h: float, u_from: float, u_to: float) -> float:
        du = u_to - u_from
        if du == 0.0:
            return h
        sgn, m, dx = substeps_py(du, self.du_sub, _MAX_SUB)
        for _ in range(m):
            k1 = self.rhs(h, sgn)
            k2 = self.rhs(h + 0.5 * dx * k1, sgn)
            k3 = self.rhs(h + 0.5 * dx * k2, sgn)
            k4 = self.rhs(h + dx * k3, sgn)
            h = h + dx / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return h

    def forward(self, u: np.ndarray) -> np.ndarray:
        out = np.empty(len(u))
        for k, x in enumerate(np.asarray(u, dtype=float).tolist()):
            self.h = self.advance(self.h, self.up, x)
            self.up = x
            out[k] = self.d * x - self.h + self.off
        return out

    def solve(self, yd: float) -> float:
        """Safeguarded Newton for d·u − h(u) + off = yd (mirrors the kernel's _solve_u)."""
        d, h, up, off = self.d, self.h, self.up, self.off
        y_prev = d * up - h + off
        if yd == y_prev:
            return up
        sgn = 1.0 if yd > y_prev else -1.0
        u = up + (yd - y_prev) / (d - self.rhs(h, sgn))
        a, b = (up, math.inf) if sgn > 0 else (-math.inf, up)
        scale = abs(yd) + abs(d) * (abs(up) + 1.0)
        for _ in range(100):
            hu = self.advance(h, up, u)
            g = d * u - hu + off - yd
            if abs(g) <= 1e-15 * scale:
                return u
            if g > 0.0:
                b = u
            else:
                a = u
            gp = d - self.rhs(hu, 1.0 if u >= up else -1.0)
            un = u - g / gp
            if not (un > a and un < b):
                un = u - 2.0 * g / gp if (math.isinf(a) or math.isinf(b)) else 0.5 * (a + b)
            if un == u:
                return u
            u = un
        return u

    def inverse(self, y: np.ndarray) -> np.ndarray:
        out = np.empty(len(y))
        for k, target in enumerate(np.asarray(y, dtype=float).tolist()):
            u = self.solve(target)
            self.h = self.advance(self.h, self.up, u)
            self.up = u
            out[k] = u
        return out


def reference_forward(model: BoucWenModel, u: np.ndarray) -> np.ndarray:
    """Plain-Python reference of the forward operator from the reset state."""
    return ReferenceBoucWen(model).forward(u)


class _BWBase(StreamingOperator):
    def __init__(self, model: BoucWenModel) -> None:
        self.model = model
        self.p = model.kernel_params()
        self.state = np.zeros(2)
        self.reset()

    def reset(self) -> None:
        self.state[0] = self.model.h0_nm
        self.state[1] = self.model.u0_V

    @property
    def h_nm(self) -> float:
        return float(self.state[0])


class BoucWenOperator(_BWBase):
    """Forward streaming operator u [V] → y [nm]."""

    def step(self, x: float) -> float:
        return bw_forward_step(finite_sample("u_V", x), self.state, self.p)

    def block(self, x: np.ndarray) -> np.ndarray:
        x = block_samples("u_V", x)
        return bw_forward_block(x, self.state, self.p)


class BoucWenInverse(_BWBase):
    """Exact inverse y [nm] → u [V]."""

    def step(self, x: float) -> float:
        return bw_inverse_step(finite_sample("y_nm", x), self.state, self.p)

    def block(self, x: np.ndarray) -> np.ndarray:
        x = block_samples("y_nm", x)
        return bw_inverse_block(x, self.state, self.p)


# ------------------------------------------------------------------------ identification
def _identify(cls: type, t_s: Any, u_V: Any, y_nm: Any, n: float | None = None, max_rows: int = 20000,
              u0_V: float | None = None, fit_from_index: int = 0, jacobian: str = "sensitivities") -> BoucWenModel:
    """Nonlinear least squares over p = [log d, log(A/d), log h_sat, c, (n), offset/ŷ] with
    β + γ = A/h_sat^n and γ = c·β; bounds keep the fit inside the admissible, reasonably
    non-stiff region (h_sat ≥ 0.5 % of the output range, −0.8 ≤ c ≤ 1, 1 ≤ n ≤ 4).

    ``jacobian``: "sensitivities" (default: from the simulation's forward sensitivities, one
    pass per iteration) or "2-point" (finite differences, one simulation per parameter: the
    slower reference the sensitivities are checked against)."""
    from scipy.optimize import least_squares
    prob, icpt = _problem(t_s, u_V, y_nm, n, max_rows, u0_V, fit_from_index, jacobian)
    u, y, nfix, yscale, u0, k0 = prob.u, prob.y, prob.nfix, prob.yscale, prob.u0, prob.k0
    d0 = max(abs(float(prob.slope)), 1e-12)
    jac: Any = prob.jac if prob.sensitivities else "2-point"

    best = None
    n_starts = [nfix] if nfix is not None else [1.0, 2.0]
    starts = [(n_init, ratio, hs_frac) for ratio, hs_frac in ((0.2, 0.1), (0.1, 0.03), (0.4, 0.3))
              for n_init in n_starts]
    for n_init, ratio, hs_frac in starts:
        if best is not None and math.sqrt(2.0 * best.cost / prob.sel.shape[0]) < 1e-6:
            break  # already fits to 1 ppm of the output range
        hs0 = max(hs_frac * yscale, 0.01 * yscale)
        p0, lb, ub = prob.start([math.log(d0 * (1 + ratio)), math.log(ratio / (1 + ratio)), math.log(hs0), 0.3],
                                n_init, float(icpt))
        try:
            r = least_squares(prob.resid, p0, jac=jac, bounds=(lb, ub), x_scale="jac", max_nfev=300)
        except (ValueError, FloatingPointError, OverflowError):
            continue
        if best is None or r.cost < best.cost:
            best = r
    if best is None:
        raise ModelError("data: Bouc–Wen least squares failed for every start; check that u_V and y_nm form hysteresis loops")
    d, A, beta, gamma, nn, off = prob.unpack(best.x)
    try:
        model = cls(d_nm_per_V=d, A_nm_per_V=A, beta=beta, gamma=gamma, n=nn, offset_nm=off, u0_V=u0)
    except ValueError as err:
        raise ModelError(f"data: the fitted Bouc–Wen parameters are not admissible ({err})") from None
    _note_bw_problems(model, best, nfix is None)
    res = (model.forward().block(u) - y)[k0:]
    model.fit_residual_nm = float(np.sqrt(np.mean(res * res)))
    log.info("identify bouc-wen: %s", model.summary().replace("\n", "; "))
    return model


def _problem(t_s: Any, u_V: Any, y_nm: Any, n: float | None, max_rows: int, u0_V: float | None,
             fit_from_index: int, jacobian: str) -> tuple["_BWProblem", float]:
    """The checked record as a :class:`_BWProblem` (rows ``max_rows`` evenly from the burn-in
    ``fit_from_index`` on), and the intercept of its straight-line fit [nm]."""
    u = check_finite("u_V", u_V).reshape(-1)
    y = check_finite("y_nm", y_nm).reshape(-1)
    if u.shape != y.shape:
        raise ModelError(f"y_nm: length {y.shape[0]} differs from u_V length {u.shape[0]}; they must be equal")
    if t_s is not None and np.asarray(t_s).reshape(-1).shape != u.shape:
        raise ModelError("t_s: length differs from u_V; they must be equal")
    if u.shape[0] < 20:
        raise ModelError(f"u_V: {u.shape[0]} samples; at least 20 are needed to identify a Bouc–Wen model")
    if not np.ptp(u) > 0:
        raise ModelError("u_V: the input never changes; identification needs an input that sweeps the range")
    if n is not None and (isinstance(n, bool) or not isinstance(n, (int, float)) or not 1.0 <= float(n) <= 10.0):
        raise ModelError(f"n: must be a number in 1..10, got {plain_repr(n)}")
    if isinstance(max_rows, bool) or not isinstance(max_rows, (int, np.integer)) or max_rows < 20:
        raise ModelError(f"max_rows: must be an integer >= 20, got {plain_repr(max_rows)}")
    if jacobian not in ("sensitivities", "2-point"):
        raise ModelError(f"jacobian: must be 'sensitivities' or '2-point', got {plain_repr(jacobian)}")
    u0 = float(u[0]) if u0_V is None else number_option("u0_V", u0_V)
    u = np.ascontiguousarray(u)
    k0 = number_option("fit_from_index", fit_from_index, lo=0, hi=u.shape[0] - 20, integer=True)
    sel = np.unique(np.linspace(k0, u.shape[0] - 1, min(max_rows, u.shape[0] - k0)).round().astype(np.int64))
    travel = float(np.sum(np.abs(np.diff(np.r_[u0, u]))))
    slope, icpt = np.polyfit(u, y, 1)
    yscale = max(float(np.ptp(y)), 1e-12)
    prob = _BWProblem(u, y, sel, u0, travel, yscale, None if n is None else float(n), jacobian == "sensitivities")
    prob.k0, prob.slope = int(k0), float(slope)
    return prob, float(icpt)


class _BWProblem:
    """The least-squares problem of :func:`_identify`: residuals over the rows ``sel`` (the model
    simulated on every sample) and, if ``sensitivities``, their Jacobian from the forward
    sensitivities of the simulation (:mod:`afmctl.compensators._bouc_wen_kernels`), computed in
    the same pass as the residuals and kept for the Jacobian call at the same point (else the
    residuals alone, from the forward operator's kernel, for a finite-difference Jacobian).

    Search vector ``p = [log d, log(A/d), log h_sat, c, (n), offset/ŷ]`` with
    ``β + γ = A/h_sat^n`` and ``γ = c·β``; residuals in units of the output range ŷ."""

    def __init__(self, u: np.ndarray, y: np.ndarray, sel: np.ndarray, u0: float, travel: float,
                 yscale: float, nfix: float | None, sensitivities: bool = True) -> None:
        self.u, self.y, self.sel, self.u0, self.travel, self.yscale, self.nfix = u, y, sel, u0, travel, yscale, nfix
        self.sensitivities = sensitivities
        self.u_sel, self.y_sel = u[sel], y[sel]
        self.k0, self.slope = 0, 0.0
        #: rate-dependent fits (:mod:`.rate_bouc_wen`): every sample's capped input rate [V/s] and
        #: the highest one; the search vector then holds the growth c·top before the offset
        self.q, self.top = _NO_RATE, 0.0
        #: a growth given, not fitted: c [s/V] (the search vector then has no growth)
        self.fixed_gain: float | None = None
        self._h = np.empty(sel.shape[0])
        self._s = np.empty((sel.shape[0], 5))
        self._x: np.ndarray | None = None
        self._jac: np.ndarray | None = None

    def unpack(self, p: np.ndarray) -> tuple[float, float, float, float, float, float]:
        """(d, A, β, γ, n, offset [nm]) of the search vector ``p``."""
        d = math.exp(p[0])
        A = d * math.exp(p[1])
        hs = math.exp(p[2])
        c = p[3]
        nn = self.nfix if self.nfix is not None else p[4]
        bg = A / hs ** nn
        beta = bg / (1.0 + c)
        return d, A, beta, beta * c, nn, p[-1] * self.yscale

    def start(self, shape: list[float], n: float, offset_nm: float, growth: float | None = None,
              growth_max: float = math.inf) -> tuple[np.ndarray, list[float], list[float]]:
        """A start of the search and its bounds: ``shape`` = [log d, log(A/d), log h_sat, γ/β],
        then ``n`` (when it is fitted), the ``growth`` c·top (when given: a rate-dependent fit,
        0 … ``growth_max``) and the offset [nm]. The start is clipped into the bounds, which
        keep the fit admissible and not stiff (:func:`_identify`)."""
        p0 = list(shape)
        lb = [-np.inf, math.log(1e-4), math.log(0.005 * self.yscale), -0.8]
        ub = [np.inf, math.log(2.0), math.log(10.0 * self.yscale), 1.0]
        if self.nfix is None:
            p0.append(n)
            lb.append(1.0)
            ub.append(4.0)
        if growth is not None:
            p0.append(growth)
            lb.append(0.0)
            ub.append(growth_max)
        p0.append(offset_nm / self.yscale)
        lb.append(-np.inf)
        ub.append(np.inf)
        return np.clip(np.array(p0), np.array(lb) + 1e-9, np.array(ub) - 1e-9), lb, ub

    def rate_gain(self, p: np.ndarray) -> float:
        """c [s/V] of the search vector ``p`` (0 without rates)."""
        if not self.q.shape[0]:
            return 0.0
        return self.fixed_gain if self.fixed_gain is not None else float(p[-2]) / self.top

    def resid(self, p: np.ndarray) -> np.ndarray:
        """Model minus data on the rows ``sel`` [output ranges]; also computes the Jacobian
        (if ``sensitivities``)."""
        d, A, beta, gamma, nn, off = self.unpack(p)
        self._x = np.array(p, dtype=float)
        c = self.rate_gain(p)
        hm = (A * (1.0 + c * self.top) / (beta + gamma)) ** (1.0 / nn)   # the largest amplitude's saturation
        k = nn * (beta + abs(gamma)) * hm ** (nn - 1.0)
        du_sub = _SUB / max(k, 1e-300)
        if not math.isfinite(du_sub) or self.travel / du_sub > 2e7:
            self._jac = np.zeros((self.sel.shape[0], len(p)))
            return np.full(self.sel.shape[0], 10.0)  # far too stiff to be a piezo loop: reject
        if not self.sensitivities:
            if self.q.shape[0]:
                raise ModelError("jacobian: a rate-dependent Bouc–Wen fit uses the sensitivities")
            y_full = bw_forward_block(self.u, np.array([0.0, self.u0]),
                                      np.array([d, A, beta, gamma, nn, off, du_sub]))
            return (y_full[self.sel] - self.y_sel) / self.yscale
        h, s = self._h, self._s
        bw_sens_nb(self.u, self.q, c, 0.0, self.u0, A, beta, gamma, nn, du_sub, _MAX_SUB, self.sel,
                   self.nfix is None, h, s)
        y_m = d * self.u_sel - h + off  # the forward operator's output, bit for bit
        # chain rule from dh/d(A, β, γ, n) to p (the output y = d·u − h + offset)
        bg_part = beta * s[:, 1] + gamma * s[:, 2]
        common = A * s[:, 0] + bg_part
        cols = [d * self.u_sel - common, -common, nn * bg_part, beta / (1.0 + p[3]) * (s[:, 1] - s[:, 2])]
        if self.nfix is None:
            cols.append(p[2] * bg_part - s[:, 3])  # p[2] = log h_sat
        if self.q.shape[0] and self.fixed_gain is None:
            cols.append(-s[:, 4] / self.top)      # p[-2] = c·top, the growth at the highest rate
        cols.append(np.full(h.shape[0], self.yscale))
        self._jac = np.stack(cols, axis=1) / self.yscale
        return (y_m - self.y_sel) / self.yscale

    def jac(self, p: np.ndarray) -> np.ndarray:
        """d resid / d p at ``p`` (from the residual pass at the same point)."""
        if self._x is None or not np.array_equal(self._x, p):
            self.resid(p)
        assert self._jac is not None
        return self._jac


#: names of the Bouc–Wen search parameters (:func:`_identify`); n on its bounds 1 or 4 is an
#: admissible member of the family (n = 1 is the classical model) and is not a failure
_BW_PARAMS = ("d", "A/d", "h_sat", "gamma/beta", "n", "offset")


def _note_bw_problems(model: BoucWenModel, sol: Any, free_n: bool) -> None:
    """Record a least-squares run that spent its budget, or a parameter stopped on a bound
    that only limits the search (:mod:`afmctl.compensators.fit_health`)."""
    from .fit_health import note_problem

    if sol.status == 0:
        note_problem(model, f"bouc-wen: least squares did not converge ({sol.nfev} evaluations)")
    names = _BW_PARAMS if free_n else _BW_PARAMS[:4] + _BW_PARAMS[5:]
    on_bound = [nm for nm, a in zip(names, sol.active_mask) if a != 0 and nm != "n"]
    if on_bound:
        note_problem(model, f"bouc-wen: {', '.join(on_bound)} on the bound of the search")
