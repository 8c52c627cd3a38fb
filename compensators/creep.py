"""Linear creep: a bank of first-order lags with log-spaced time constants, and its exact
inverse (nonlinearities paper, eq. 21: creep as first-order delay operators).

Discrete form at sample period ``dt_s`` with ``a_k = exp(−dt_s/τ_k)``::

    z_k[n] = a_k·z_k[n−1] + (1 − a_k)·x[n]          (lag k, exact for a held input)
    y[n]   = x[n] − Σ_k c_k·(x[n] − z_k[n])

After a step of the input the output jumps by ``(1 − Σ c_k·a_k)`` of the step and then
creeps towards the step in the direction of motion; the static gain is 1. With
``c_k ≥ 0`` and ``Σ c_k < 1`` it is invertible in closed form::

    x[n] = (y[n] − Σ_k c_k·a_k·z_k[n−1]) / (1 − Σ_k c_k·a_k)

:class:`LinearCreep` is unit-free (the output has the unit of the input) so it can sit
after any hysteresis operator in a :class:`~afmctl.compensators.base.Chain`;
:class:`LinearCreepModel` (``kind = "creep"``) is a model file u [V] → y [nm] with a gain
and an offset: ``y = offset_nm + gain_nm_per_V · creep(u)``.
"""
from __future__ import annotations

import logging
import math
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, FiniteFloat, model_validator

from . import _pi_kernels as K
from .base import ModelError, StreamingOperator, check_finite
from .input_checks import block_samples, exclude_mask, finite_sample, number_option, sample_period
from .models import HysteresisModel

log = logging.getLogger(__name__)


def check_creep_parameters(time_constants_s: Any, weights: Any, dt_s: Any = None
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Validate ``τ_k > 0`` and ``c_k ≥ 0`` with ``Σ c_k < 1``; return float64 arrays."""
    tau = np.array(time_constants_s, dtype=np.float64).ravel()
    c = np.array(weights, dtype=np.float64).ravel()
    if tau.size != c.size:
        raise ModelError(f"creep_weights: {c.size} values but {tau.size} time constants")
    if not (np.all(np.isfinite(tau)) and np.all(np.isfinite(c))):
        raise ModelError("time_constants_s, creep_weights: all values must be finite")
    if np.any(tau <= 0):
        raise ModelError("time_constants_s: every time constant must be > 0 s")
    if np.any(c < 0):
        raise ModelError("creep_weights: every weight must be ≥ 0")
    if float(np.sum(c)) >= 1.0:
        raise ModelError(f"creep_weights: sum is {float(np.sum(c)):.6g}; it must be < 1 for an invertible creep operator")
    if dt_s is not None:
        sample_period(dt_s, "creep operator")
    return tau, c


def log_spaced_time_constants(tau_min_s: float, tau_max_s: float, n: int) -> np.ndarray:
    """``n`` time constants log-spaced from ``tau_min_s`` to ``tau_max_s`` [s]."""
    if n == 1:
        return np.array([math.sqrt(tau_min_s * tau_max_s)])
    return np.geomspace(tau_min_s, tau_max_s, n)


class LinearCreep(StreamingOperator):
    """Forward creep operator ``x → y`` (unit-free), state ``z`` starts at ``initial``.

    ``gain``/``in_offset``/``out_offset`` give ``y = out_offset + gain·creep(x − in_offset)``.
    """

    def __init__(self, time_constants_s: Any, weights: Any, dt_s: float, initial: float = 0.0, *,
                 gain: float = 1.0, in_offset: float = 0.0, out_offset: float = 0.0,
                 use_numba: bool = True) -> None:
        tau, c = check_creep_parameters(time_constants_s, weights, dt_s)
        self.a = np.exp(-float(dt_s) / tau)
        self.c = c
        self.initial = float(initial)
        self.z = np.full(tau.size, self.initial)
        self.gain, self.in_offset, self.out_offset = float(gain), float(in_offset), float(out_offset)
        self.use_numba = use_numba
        self._buf = np.empty(1)

    def reset(self) -> None:
        self.z[:] = self.initial

    def _raw(self, x: np.ndarray) -> np.ndarray:
        if self.use_numba:
            out = np.empty_like(x)
            K.creep_block(x, self.a, self.c, self.z, out)
            return out
        return K.creep_block_ref(x, self.a, self.c, self.z)

    def block(self, x: np.ndarray) -> np.ndarray:
        x = block_samples("input", x)
        return self.out_offset + self.gain * self._raw(x - self.in_offset)

    def step(self, x: float) -> float:
        self._buf[0] = finite_sample("input", x)
        return float(self.block(self._buf)[0])


class LinearCreepInverse(LinearCreep):
    """Exact inverse of :class:`LinearCreep` with the same parameters: ``y → x``.

    With ``gain``/offsets it inverts ``y = out_offset + gain·creep(x − in_offset)``.
    """

    def block(self, y: np.ndarray) -> np.ndarray:
        y = block_samples("input", y)
        v = (y - self.out_offset) / self.gain
        if self.use_numba:
            out = np.empty_like(v)
            K.creep_inv_block(v, self.a, self.c, self.z, out)
        else:
            out = K.creep_inv_block_ref(v, self.a, self.c, self.z)
        return out + self.in_offset


class LinearCreepModel(HysteresisModel):
    """Linear creep model file (``kind = "creep"``): ``y = offset_nm + gain_nm_per_V·creep(u)``.

    No hysteresis: use it for scanners whose loop is negligible, or as the creep stage
    after a hysteresis model. Time-dependent (needs ``dt_s``). The lag states start at
    ``initial_V`` (a scanner at rest at that voltage).
    """

    kind: Literal["creep"] = "creep"
    time_dependent: ClassVar[bool] = True
    fits_with_burn_in: ClassVar[bool] = True
    fits_exclude: ClassVar[bool] = True
    gain_nm_per_V: FiniteFloat = Field(gt=0, description="static gain [nm/V]")
    offset_nm: FiniteFloat = Field(default=0.0, description="output offset [nm]")
    initial_V: FiniteFloat = Field(default=0.0, description="input at rest before the first sample [V]")
    time_constants_s: list[FiniteFloat] = Field(min_length=1, max_length=1000,
                                                description="lag time constants τ_k [s]")
    creep_weights: list[FiniteFloat] = Field(min_length=1, max_length=1000,
                                             description="creep fractions c_k ≥ 0, Σ c_k < 1")

    @model_validator(mode="after")
    def _check(self) -> "LinearCreepModel":
        try:
            check_creep_parameters(self.time_constants_s, self.creep_weights)
        except ModelError as err:
            raise ValueError(str(err)) from None
        return self

    def forward(self, dt_s: float | None = None) -> LinearCreep:
        """Operator u [V] → y [nm] at sample period ``dt_s`` [s]."""
        return LinearCreep(self.time_constants_s, self.creep_weights, sample_period(dt_s, "creep model"), self.initial_V,
                           gain=self.gain_nm_per_V, out_offset=self.offset_nm)

    def inverse(self, dt_s: float | None = None) -> LinearCreepInverse:
        """Compensator y [nm] → u [V] at sample period ``dt_s`` [s]."""
        return LinearCreepInverse(self.time_constants_s, self.creep_weights, sample_period(dt_s, "creep model"), self.initial_V,
                                  gain=self.gain_nm_per_V, out_offset=self.offset_nm)

    def summary(self) -> str:
        lines = ["model            : linear creep, bank of first-order lags (kind creep)",
                 f"gain             : {self.gain_nm_per_V:.6g} nm/V, offset {self.offset_nm:.6g} nm",
                 f"creep fraction   : {sum(self.creep_weights):.4g} of a step in total"]
        for tau, c in zip(self.time_constants_s, self.creep_weights):
            lines.append(f"  tau {tau:10.4g} s : c = {c:.4g}")
        return "\n".join(lines)

    @classmethod
    def identify(cls, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, n_operators: int | None = None,
                 **options: Any) -> "LinearCreepModel":
        """Fit gain, offset and creep fractions by linear least squares.

        ``n_operators`` lags (default 4) with time constants log-spaced between
        ``tau_min_s`` (default 5 samples) and ``tau_max_s`` (default a fifth of the record).
        With ``z_k`` the lag outputs of ``u``: ``y = offset + g(1 − Σc)·u + Σ g·c_k·z_k`` is
        linear in ``(offset, g(1−Σc), g·c_k)``; ``c_k ≥ 0`` is enforced with bounded least
        squares. Data must be uniformly sampled. ``fit_from_index`` (option, default 0):
        samples before it only drive the lags (a burn-in); the rows fitted start there.
        ``exclude`` (option): one boolean per sample, True for samples that drive the lags
        but are not fitted (samples whose ``y`` was not measured).
        """
        from scipy.optimize import lsq_linear

        n = 4 if n_operators is None else int(n_operators)
        if not 1 <= n <= 50:
            raise ModelError(f"n_operators: {n} is out of range; allowed 1 … 50")
        t = check_finite("t_s", t_s).ravel()
        u = check_finite("u_V", u_V).ravel()
        y = check_finite("y_nm", y_nm).ravel()
        if not (t.size == u.size == y.size) or u.size < 4 * n + 4:
            raise ModelError(f"data: need equal-length columns with at least {4 * n + 4} samples")
        d = np.diff(t)
        dt = float(np.median(d))
        if dt <= 0 or np.max(np.abs(d - dt)) > 1e-3 * dt:
            raise ModelError("t_s: the creep model needs strictly increasing, uniformly sampled time")
        if np.ptp(u) <= 0:
            raise ModelError("u_V: the input voltage never changes")
        tau_min = number_option("tau_min_s", options.pop("tau_min_s", 5 * dt))
        tau_max = number_option("tau_max_s", options.pop("tau_max_s", max(0.2 * (t[-1] - t[0]), 2 * tau_min)))
        k0 = number_option("fit_from_index", options.pop("fit_from_index", 0), lo=0, hi=u.size - 4 * n - 4,
                           integer=True)
        skip = exclude_mask(options.pop("exclude", None), u.size)
        if options:
            raise ModelError(f"options: unknown option(s) {', '.join(sorted(options))}; "
                             "allowed: tau_min_s, tau_max_s, fit_from_index, exclude")
        if not (0 < tau_min < tau_max):
            raise ModelError(f"tau_min_s, tau_max_s: need 0 < tau_min_s < tau_max_s (got {tau_min}, {tau_max})")
        tau = log_spaced_time_constants(tau_min, tau_max, n)
        from scipy.signal import lfilter

        Z = np.empty((u.size, n))
        for k in range(n):
            a = math.exp(-dt / float(tau[k]))
            Z[:, k] = lfilter([1.0 - a], [1.0, -a], u, zi=[a * float(u[0])])[0]
        rows = np.arange(u.size) >= k0
        if skip is not None:
            rows &= ~skip
        if np.count_nonzero(rows) < 4 * n + 4:
            raise ModelError(f"exclude: {np.count_nonzero(rows)} samples are left to fit; at least {4 * n + 4} "
                             "are needed")
        A = np.column_stack([np.ones_like(u), u, Z])[rows]
        lb = np.full(n + 2, -np.inf)
        lb[2:] = 0.0
        res = lsq_linear(A, y[rows], bounds=(lb, np.full(n + 2, np.inf)), method="bvls", tol=1e-12)
        off, pu, pk = float(res.x[0]), float(res.x[1]), res.x[2:]
        g = pu + float(np.sum(pk))
        if g <= 0:
            raise ModelError("data: the fitted static gain is not positive; is y really increasing with u?")
        c = np.maximum(pk, 0.0) / g     # bvls may return -0.0 or a rounding-level negative
        if float(np.sum(c)) >= 1.0:
            c = c * (0.999 / float(np.sum(c)))
        return cls(gain_nm_per_V=g, offset_nm=off, initial_V=float(u[0]), time_constants_s=tau.tolist(),
                   creep_weights=c.tolist())

