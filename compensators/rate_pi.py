"""Rate-dependent Prandtl–Ishlinskii hysteresis (kind ``rate-pi``): loops that widen with
the scan rate.

Many stacks' loops grow wider the faster they are driven. Al Janaideh and Krejčí make the
PI model's thresholds functions of the input's rate (rate-dependent PI, "Inverse
rate-dependent Prandtl–Ishlinskii model for feedforward compensation of hysteresis in a
piezomicropositioning actuator", IEEE/ASME Trans. Mechatronics 18 (2013)); here every
threshold grows in proportion to a smoothed input rate, so the zero threshold (the linear
play) stays zero::

    ρ(t)   = |ds/dt| [V/s] through a first-order low-pass of time constant ``rate_tau_s``,
             s the input through the same low-pass (so ρ does not grow with the sample rate)
    r_i(t) = r_i·(1 + c·min(ρ(t), ρ_max))               c = ``rate_gain_s_per_V`` [s/V]
    x_i(t) = max(u(t) − r_i(t), min(u(t) + r_i(t), x_i(t − T)))   (PI eq. 3)
    y(t)   = offset_nm + Σ_i w_i·x_i(t)                  (PI eq. 4)

``ρ_max`` (``rate_max_V_per_s``) is the highest rate of the identification record: how
the loop grows past it is not known, and a growth extrapolated from slow sweeps to a fast
multisine widened the thresholds past the whole range. With ``c = 0`` it is the PI model (:mod:`afmctl.compensators.pi`). The thresholds of a
sample depend on the inputs before it (ρ of the previous sample), so the inverse is exact:
per sample it solves the piecewise-linear, increasing equation ``y(u) = target`` for ``u``
(:mod:`._rate_pi_kernels`), with the same play states as the forward operator.

**Identification** (:meth:`RatePIModel.identify`): for a given ``(c, τ)`` the play outputs
are fixed by the input alone, and the weights are PI's constrained least squares (eq. 5,
partial sums ≥ ε); ``τ`` and ``c`` are searched (``c`` as the threshold growth at the
record's fast end). A record at one rate cannot tell ``c``: ``identify --model auto`` tries
this kind only on a record that sweeps at several rates (:mod:`.coverage`).
"""
from __future__ import annotations

import logging
import math
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, FiniteFloat, ValidationInfo, field_validator

from . import _rate_pi_kernels as K
from .base import ModelError, StreamingOperator
from .input_checks import block_samples, finite_sample, number_option, sample_period
from .models import HysteresisModel
from .pi import MAX_OPERATORS, _fit_options, check_pi_parameters, fit_pi_weights, prepare_pi_identification

log = logging.getLogger(__name__)

#: smoothing time constants of the input rate tried by identification [s]
RATE_TAUS_S: tuple[float, ...] = (0.003, 0.01, 0.03, 0.1)
#: threshold growths ``1 + c·ρ_max`` tried at the record's highest rate ρ_max (where the
#: growth stops); 1 is the PI model
GROWTHS: tuple[float, ...] = (1.0, 1.1, 1.25, 1.5, 2.0, 3.0)
#: the refinement does not search past this growth at ρ_max
MAX_GROWTH = 4.0


class RatePIOperator(StreamingOperator):
    """Forward (u [V] → y [nm]) or inverse (y [nm] → u [V]) rate-dependent PI operator at
    sample period ``dt_s`` [s] (module docstring). ``use_numba=False`` runs the plain-numpy
    reference (bit-identical, slower)."""

    def __init__(self, model: "RatePIModel", dt_s: float, inverse: bool = False, use_numba: bool = True) -> None:
        r, w, x0 = check_pi_parameters(model.thresholds, model.weights, model.initial_state)
        self.r, self.w, self.x0 = r, w, x0
        self.c = float(model.rate_gain_s_per_V)
        self.rmax = math.inf if model.rate_max_V_per_s is None else float(model.rate_max_V_per_s)
        self.dt = float(number_option("dt_s", dt_s, lo=1e-9, hi=10.0))
        self.a = K.smoothing_factor(self.dt, float(model.rate_tau_s))
        self.offset = float(model.offset_nm)
        self.inverse, self.use_numba = inverse, use_numba
        self.state = x0.copy()
        self.aux = np.array([0.0, float(x0[0])])

    def reset(self) -> None:
        self.state[:] = self.x0
        self.aux[:] = (0.0, float(self.x0[0]))

    def step(self, x: float) -> float:
        return float(self.block(np.array([finite_sample("input", x)]))[0])

    def block(self, x: np.ndarray) -> np.ndarray:
        x = block_samples("input", x)
        args = (self.r, self.w, self.c, self.rmax, self.a, self.dt, self.state, self.aux, self.offset)
        if not self.use_numba:
            return (K.inverse_block_ref if self.inverse else K.forward_block_ref)(x, *args)
        out = np.empty_like(x)
        (K.inverse_block if self.inverse else K.forward_block)(x, *args, out)
        return out


class RatePIModel(HysteresisModel):
    """Rate-dependent PI model file (``kind = "rate-pi"``; module docstring): u [V] → y [nm]."""

    kind: Literal["rate-pi"] = "rate-pi"
    time_dependent: ClassVar[bool] = True
    fits_with_burn_in: ClassVar[bool] = True
    thresholds: list[FiniteFloat] = Field(max_length=MAX_OPERATORS,
                                          description="play thresholds r_i at rest [V], first 0, increasing")
    weights: list[FiniteFloat] = Field(max_length=MAX_OPERATORS, description="weights w_i [nm/V]")
    initial_state: list[FiniteFloat] | None = Field(
        default=None, max_length=MAX_OPERATORS, description="initial play states [V]; default all 0")
    offset_nm: FiniteFloat = Field(default=0.0, description="output offset [nm]")
    rate_gain_s_per_V: float = Field(default=0.0, ge=0.0, le=1.0, allow_inf_nan=False,
                                     description="c: thresholds grow by c·ρ, ρ the smoothed input rate [V/s]; 0 … 1 s/V")
    rate_max_V_per_s: float | None = Field(
        default=None, gt=0.0, allow_inf_nan=False,
        description="the rate [V/s] the growth stops at (the identification record's highest); None: none")
    rate_tau_s: float = Field(default=0.01, ge=1e-4, le=100.0, allow_inf_nan=False,
                              description="time constant of the rate's low-pass [s], 1e-4 … 100 s")

    @field_validator("weights")
    @classmethod
    def _check_weights(cls, v: list[float], info: ValidationInfo) -> list[float]:
        r = info.data.get("thresholds")
        if r is not None:
            try:
                check_pi_parameters(r, v)
            except ModelError as err:
                raise ValueError(str(err).split(": ", 1)[-1]) from None
        return v

    @field_validator("initial_state")
    @classmethod
    def _check_state(cls, v: list[float] | None, info: ValidationInfo) -> list[float] | None:
        r, w = info.data.get("thresholds"), info.data.get("weights")
        if v is not None and r is not None and w is not None:
            try:
                check_pi_parameters(r, w, v)
            except ModelError as err:
                raise ValueError(str(err).split(": ", 1)[-1]) from None
        return v

    def forward(self, dt_s: float | None = None) -> RatePIOperator:
        """Operator u [V] → y [nm] at sample period ``dt_s`` [s]."""
        return RatePIOperator(self, sample_period(dt_s, "rate-dependent PI model"))

    def inverse(self, dt_s: float | None = None) -> RatePIOperator:
        """Compensator y [nm] → u [V] at sample period ``dt_s`` [s] (exact, per sample)."""
        return RatePIOperator(self, sample_period(dt_s, "rate-dependent PI model"), inverse=True)

    def summary(self) -> str:
        r, w = np.asarray(self.thresholds), np.asarray(self.weights)
        return "\n".join([
            "model            : rate-dependent Prandtl–Ishlinskii (kind rate-pi)",
            f"play operators   : {r.size}, thresholds at rest 0 … {r[-1]:.6g} V",
            f"weights          : w0 = {w[0]:.6g} nm/V, sum = {float(np.sum(w)):.6g} nm/V",
            f"offset           : {self.offset_nm:.6g} nm",
            f"rate dependence  : thresholds × (1 + {self.rate_gain_s_per_V:.4g} s/V · ρ), ρ = |du/dt| "
            f"of the input low-passed over {self.rate_tau_s * 1e3:.4g} ms (× {1 + self.rate_gain_s_per_V * 1e4:.4g} at 10 kV/s)"])

    @classmethod
    def identify(cls, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, n_operators: int | None = None,
                 **options: Any) -> "RatePIModel":
        """Fit a rate-dependent PI model to uniformly sampled ``(t [s], u [V], y [nm])``.

        Thresholds, initial state and the weights' constraints as :meth:`PIModel.identify`
        (its options too: ``thresholds``, ``min_slope_fraction``, ``max_rows``,
        ``fit_from_index``). ``rate_tau_s`` and ``rate_gain_s_per_V`` fix those parameters;
        otherwise ``τ`` is tried from :data:`RATE_TAUS_S` and ``c`` from the threshold growths
        :data:`GROWTHS` at the record's highest rate, the best pair refined on ``c``; the fit
        with the lowest RMS residual is kept (``c = 0`` is among them: PI itself)."""
        opts = dict(options)
        tau = opts.pop("rate_tau_s", None)
        gain = opts.pop("rate_gain_s_per_V", None)
        u, y, r, x0 = prepare_pi_identification(t_s, u_V, y_nm, n_operators, opts)
        fit_opts = _fit_options(opts)
        t = np.asarray(t_s, dtype=np.float64).ravel()
        dt = float(np.median(np.diff(t)))
        taus = RATE_TAUS_S if tau is None else (number_option("rate_tau_s", tau, lo=1e-4, hi=100.0),)
        tops = {tau_s: float(np.max(rate_series(u, dt, tau_s))) for tau_s in taus}    # ρ_max per τ [V/s]
        best: tuple[float, float, float, np.ndarray, float] | None = None
        for tau_s in taus:
            for c in _gains(tops[tau_s], gain):
                fit = _fit_at(u, y, r, x0, dt, c, tau_s, fit_opts)
                if best is None or fit[0] < best[0]:
                    best = (fit[0], c, tau_s, fit[1], fit[2])
        assert best is not None
        if gain is None and best[1] > 0:
            best = _refine_gain(u, y, r, x0, dt, best, tops[best[2]], fit_opts)
        rms, c, tau_s, w, off = best
        top = tops[tau_s]
        log.info("rate-pi fit: tau %.4g s, c %.4g s/V up to %.4g V/s, rms residual %.4g nm", tau_s, c, top, rms)
        return cls(thresholds=r.tolist(), weights=w.tolist(), initial_state=x0.tolist(), offset_nm=off,
                   rate_gain_s_per_V=c, rate_tau_s=tau_s, rate_max_V_per_s=top if top > 0 else None)


def rate_series(u: np.ndarray, dt_s: float, tau_s: float) -> np.ndarray:
    """ρ [V/s] the operator sees at every sample of ``u`` [V] (the smoothed rate of the
    samples before it), from rest."""
    u = np.ascontiguousarray(u, dtype=np.float64)
    out = np.empty(u.size)
    K.rates(u, K.smoothing_factor(dt_s, tau_s), dt_s, np.array([0.0, float(u[0])]), out)
    return out


def _gains(fast: float, gain: Any) -> list[float]:
    """The values of ``c`` [s/V] to try: the fixed one, or :data:`GROWTHS` at the record's
    highest rate ``fast`` [V/s] (PI alone when the record never moves)."""
    if gain is not None:
        return [number_option("rate_gain_s_per_V", gain, lo=0.0, hi=1.0)]
    if not fast > 0:
        return [0.0]
    return sorted({min(1.0, (g - 1.0) / fast) for g in GROWTHS})      # c ≤ 1 s/V, the file's bound


def _fit_at(u: np.ndarray, y: np.ndarray, r: np.ndarray, x0: np.ndarray, dt: float, c: float, tau_s: float,
            fit_opts: dict[str, Any]) -> tuple[float, np.ndarray, float]:
    """Weights and offset at ``(c, τ)`` and their RMS residual [nm] over the fitted rows."""
    kept: dict[str, Any] = {}                  # the play matrix the fit used, and its row stride

    def matrix(uu: np.ndarray, rr: np.ndarray, xx: np.ndarray, stride: int) -> np.ndarray:
        kept.update(X=play_matrix(uu, rr, xx, dt, c, tau_s, stride), stride=stride)
        return kept["X"]

    w, off = fit_pi_weights(u, y, r, x0, matrix=matrix, **fit_opts)
    stride = kept["stride"]
    k0 = int(fit_opts.get("fit_from_index", 0) or 0)
    rows = np.arange(0, u.size, stride) >= k0
    resid = kept["X"][rows] @ w + off - y[::stride][rows]
    return float(np.sqrt(np.mean(resid ** 2))), w, off


def _refine_gain(u: np.ndarray, y: np.ndarray, r: np.ndarray, x0: np.ndarray, dt: float,
                 best: tuple[float, float, float, np.ndarray, float], fast: float, fit_opts: dict[str, Any]
                 ) -> tuple[float, float, float, np.ndarray, float]:
    """``best`` = (rms, c, τ, w, offset) refined on ``c`` between half and twice its value,
    below a growth of :data:`MAX_GROWTH` at the record's highest rate ``fast`` [V/s]."""
    from scipy.optimize import minimize_scalar

    _, c0, tau_s, _, _ = best
    hi = min(2.0 * c0, (MAX_GROWTH - 1.0) / fast, 1.0)
    res = minimize_scalar(lambda c: _fit_at(u, y, r, x0, dt, float(c), tau_s, fit_opts)[0],
                          bounds=(0.5 * c0, max(hi, 0.5 * c0)), method="bounded",
                          options={"xatol": 0.02 * c0, "maxiter": 12})
    c = float(res.x)
    rms, w, off = _fit_at(u, y, r, x0, dt, c, tau_s, fit_opts)
    return (rms, c, tau_s, w, off) if rms < best[0] else best


def play_matrix(u: np.ndarray, r: np.ndarray, x0: np.ndarray, dt: float, c: float, tau_s: float,
                stride: int = 1, rate_max_V_per_s: float = math.inf) -> np.ndarray:
    """Outputs of every rate-dependent play, rows ``u[::stride]``, shape ``(rows, n)``."""
    state = x0.astype(np.float64).copy()
    aux = np.array([0.0, float(u[0])])
    a = K.smoothing_factor(dt, tau_s)
    rows = []
    chunk = max(stride, (65536 // stride) * stride)
    for start in range(0, u.size, chunk):
        seg = np.ascontiguousarray(u[start:start + chunk])
        out = np.empty((seg.size, r.size))
        K.play_outputs(seg, r, c, rate_max_V_per_s, a, dt, state, aux, out)
        rows.append(out[::stride])
    return np.concatenate(rows, axis=0)
