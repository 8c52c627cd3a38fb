"""The amplifier stage: the voltage amplifier between the command and the piezo.

A voltage amplifier driving a capacitive stack low-pass-filters the command and limits its
slew (its output current ``I = C·dV/dt`` is bounded); the piezo's hysteresis acts on the
voltage that reaches it. So on a real axis the amplifier comes *before* the hysteresis::

    command u [V] → amplifier → piezo voltage v [V] → hysteresis → creep → dynamics → y [nm]

(``kind = "amplifier"``, the first stage of a chain, :mod:`afmctl.compensators.chain`). Its
discrete form at the sample period ``dt_s``, with ``a = exp(−2π·f_c·dt_s)`` (a first-order
lag of bandwidth ``f_c``, exact for a held command read at the end of each hold interval)
and the slew limit ``S`` [V/s]::

    v_k = v_{k−1} + clip((1 − a)·(u_k − v_{k−1}), ±S·dt_s)                       (1)

The first sample settles the stage (``v_0 = u_0``: an amplifier at rest). The inverse
(the command that brings the stage to the piezo voltage asked for) is exact within the slew
limit::

    u_k = v_{k−1} + (v_k − v_{k−1})/(1 − a),   |v_k − v_{k−1}| ≤ S·dt_s            (2)

and never asks for more: a step beyond ``S·dt_s`` is cut to it (counted in ``n_limited``).
Its gain grows with frequency as a first-order lead's (``1/(1 − a)`` at Nyquist), so the
chain keeps the commands it sends within range and slew (:mod:`.dynamics_limits`).

Identification (:meth:`AmplifierModel.identify`) fits ``f_c`` and ``S`` to a recorded piezo
voltage (an amplifier's monitor output or a controller's recorder channel: the optional
column ``v`` of a data CSV) by the simulation error of (1). Without that column the chain
finds the stage from the record itself (:mod:`.amplifier_identify`).
"""
from __future__ import annotations

import logging
import math
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, FiniteFloat

from . import _amp_kernels as K
from .base import ModelError, StreamingOperator, check_finite
from .input_checks import block_samples, finite_sample, sample_period
from .models import HysteresisModel

log = logging.getLogger(__name__)


def lag_coefficient(bandwidth_Hz: float, dt_s: float) -> float:
    """``a = exp(−2π·f_c·dt)`` of eq. (1) for a bandwidth ``f_c`` [Hz] at ``dt_s`` [s]."""
    return math.exp(-2.0 * math.pi * float(bandwidth_Hz) * sample_period(dt_s, "amplifier stage"))


class AmplifierOperator(StreamingOperator):
    """Eq. (1): command u [V] → piezo voltage v [V]. ``use_numba=False`` runs the reference."""

    def __init__(self, a: float, max_step_V: float, use_numba: bool = True) -> None:
        self.a, self.max_step_V, self.use_numba = float(a), float(max_step_V), use_numba
        self.state = np.zeros(2)
        self._one = np.empty(1)

    def reset(self) -> None:
        self.state[:] = 0.0

    def block(self, x: np.ndarray) -> np.ndarray:
        u = block_samples("u_V", x)
        out = np.empty_like(u)
        (K.amp_forward_nb if self.use_numba else K.amp_forward_py)(u, out, self.a, self.max_step_V, self.state)
        return out

    def step(self, x: float) -> float:
        self._one[0] = finite_sample("u_V", x)
        return float(self.block(self._one)[0])


class AmplifierInverse(StreamingOperator):
    """Eq. (2): piezo voltage asked for v [V] → command u [V], each step of v kept within
    the slew limit; ``n_limited`` counts the steps that were cut since :meth:`reset`."""

    def __init__(self, a: float, max_step_V: float, use_numba: bool = True) -> None:
        self.a, self.max_step_V, self.use_numba = float(a), float(max_step_V), use_numba
        self.state = np.zeros(2)
        self.limited = np.zeros(1, dtype=np.int64)
        self._one = np.empty(1)

    @property
    def n_limited(self) -> int:
        return int(self.limited[0])

    def reset(self) -> None:
        self.state[:] = 0.0
        self.limited[0] = 0

    def block(self, x: np.ndarray) -> np.ndarray:
        v = block_samples("v_V", x)
        out = np.empty_like(v)
        kern = K.amp_inverse_nb if self.use_numba else K.amp_inverse_py
        kern(v, out, self.a, self.max_step_V, self.state, self.limited)
        return out

    def step(self, x: float) -> float:
        self._one[0] = finite_sample("v_V", x)
        return float(self.block(self._one)[0])


class AmplifierModel(HysteresisModel):
    """First-order voltage amplifier with a slew limit (module docstring), u [V] → v [V]."""

    kind: Literal["amplifier"] = "amplifier"
    time_dependent: ClassVar[bool] = True
    bandwidth_Hz: FiniteFloat = Field(gt=0.0, le=1e7, description="small-signal bandwidth f_c [Hz] (first order)")
    slew_V_per_s: FiniteFloat | None = Field(None, gt=0.0, description=(
        "slew (current) limit of the piezo voltage [V/s]; null: the record never reached it"))
    fit_info: dict[str, float | str] | None = Field(None, description="identification summary")

    @classmethod
    def from_lag(cls, bandwidth_Hz: float, slew_V_per_s: float | None = None, **fields: Any) -> "AmplifierModel":
        return cls(bandwidth_Hz=bandwidth_Hz, slew_V_per_s=slew_V_per_s, **fields)

    def max_step_V(self, dt_s: float) -> float:
        """The largest change of the piezo voltage per sample [V] (``S·dt``; inf without a limit)."""
        return math.inf if self.slew_V_per_s is None else float(self.slew_V_per_s) * float(dt_s)

    def forward(self, dt_s: float | None = None, use_numba: bool = True) -> AmplifierOperator:
        """Eq. (1) at ``dt_s`` [s]: command [V] → piezo voltage [V]."""
        a = lag_coefficient(self.bandwidth_Hz, dt_s)  # type: ignore[arg-type]
        return AmplifierOperator(a, self.max_step_V(float(dt_s)), use_numba)  # type: ignore[arg-type]

    def inverse(self, dt_s: float | None = None, use_numba: bool = True) -> AmplifierInverse:
        """Eq. (2) at ``dt_s`` [s]: piezo voltage asked for [V] → command [V]."""
        a = lag_coefficient(self.bandwidth_Hz, dt_s)  # type: ignore[arg-type]
        return AmplifierInverse(a, self.max_step_V(float(dt_s)), use_numba)  # type: ignore[arg-type]

    @classmethod
    def identify(cls, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, **options: Any) -> "AmplifierModel":
        """Fit to a recorded piezo voltage: ``u_V`` the command [V], ``y_nm`` here the piezo
        voltage ``v`` [V] (:func:`fit_amplifier`)."""
        return fit_amplifier(t_s, u_V, y_nm, **options)

    def summary(self) -> str:
        slew = (f"{self.slew_V_per_s:.4g} V/s" if self.slew_V_per_s is not None
                else "not reached by the record (none applied)")
        lines = ["model            : amplifier stage, first order with a slew limit (kind amplifier)",
                 f"bandwidth        : {self.bandwidth_Hz:.5g} Hz", f"slew limit       : {slew}"]
        lines += [f"  fit {k}: {v}" for k, v in (self.fit_info or {}).items()]
        return "\n".join(lines)


#: a slew limit is kept only when it lowers the simulation error of eq. (1) by this fraction
#: where it changes the simulated voltage (:func:`_slew_explains`)
SLEW_MIN_GAIN = 0.5
#: the piezo voltage's gain over the command must lie within this factor of 1 (a monitor
#: scaled otherwise is not the voltage at the piezo)
GAIN_TOLERANCE = 1.25


def _simulate(u: np.ndarray, dt: float, f_c: float, slew: float) -> np.ndarray:
    out = np.empty_like(u)
    K.amp_forward_nb(u, out, lag_coefficient(f_c, dt), slew * dt, np.zeros(2))
    return out


def _slew_explains(u: np.ndarray, v: np.ndarray, dt: float, fit: tuple[float, float, float]) -> bool:
    """Whether the slew-limited fit ``(f_lin, f_c, S)`` explains the record better than the
    linear one ``f_lin`` where the limit binds: the stretches where the linear stage would
    change faster than ``S`` and the two simulations differ by more than the limited fit's
    RMS error and 0.01 % of the voltage span. There its error must be at most
    ``1 − SLEW_MIN_GAIN`` of the linear one's. Over the whole record those stretches are
    few, and the sensor's noise would hide them."""
    f_lin, f_c, slew = fit
    lin, lim = _simulate(u, dt, f_lin, math.inf), _simulate(u, dt, f_c, slew)
    if not float(np.max(np.abs(np.diff(lin)))) > slew * dt * (1.0 + 1e-6):
        return False                              # the limit never binds
    rms = float(np.sqrt(np.mean((lim - v) ** 2)))
    where = np.abs(lin - lim) > max(rms, 1e-4 * float(np.ptp(v)))
    if np.count_nonzero(where) < 3:
        return False
    e_lin, e_lim = lin[where] - v[where], lim[where] - v[where]
    return float(np.dot(e_lim, e_lim)) <= (1.0 - SLEW_MIN_GAIN) * float(np.dot(e_lin, e_lin))


def fit_amplifier(t_s: np.ndarray, u_V: np.ndarray, v_V: np.ndarray, fit_from_index: int = 0) -> AmplifierModel:
    """``f_c`` [Hz] and ``S`` [V/s] of eq. (1) from the command ``u_V`` and the recorded piezo
    voltage ``v_V`` (uniform times ``t_s`` [s]), by least squares on the simulation error
    (the record's noise does not bias it). The bandwidth first without a slew limit (a 1-D
    search on log f_c), then both together (Nelder–Mead on log f_c, log S) from the record's
    fastest change; the slew limit is kept only where it explains the record
    (:func:`_slew_explains`) — a record that never drove the amplifier into it says nothing
    about it (``fit_info["slew_seen_V_per_s"]`` says how fast it went)."""
    from scipy.optimize import minimize, minimize_scalar

    t = check_finite("t_s", t_s).ravel()
    u = np.ascontiguousarray(check_finite("u_V", u_V).ravel())
    v = np.ascontiguousarray(check_finite("v_V", v_V).ravel())
    if not (t.size == u.size == v.size) or t.size < 16:
        raise ModelError("data: need equal-length columns t, u, v with at least 16 samples")
    dt = float(np.median(np.diff(t)))
    k0 = int(fit_from_index)
    gain = float(np.polyfit(u[k0:], v[k0:], 1)[0]) if np.ptp(u[k0:]) > 0 else 1.0
    if not 1.0 / GAIN_TOLERANCE <= gain <= GAIN_TOLERANCE:
        raise ModelError(f"v: the piezo voltage moves {gain:.3g} V per V of the command; column v must be the voltage "
                         f"at the piezo in V (allowed {1 / GAIN_TOLERANCE:.2f} … {GAIN_TOLERANCE:.2f} V/V)")
    f_top = 0.5 / dt

    def sse(f_c: float, slew: float) -> float:
        e = _simulate(u, dt, f_c, slew)[k0:] - v[k0:]
        return float(np.dot(e, e))

    lin = minimize_scalar(lambda x: sse(math.exp(x), math.inf), bounds=(math.log(0.1), math.log(f_top)),
                          method="bounded", options={"xatol": 1e-4})
    f_lin, e_lin = math.exp(float(lin.x)), float(lin.fun)
    seen = float(np.max(np.abs(np.diff(v[k0:])))) / dt
    joint = minimize(lambda x: sse(min(math.exp(x[0]), f_top), math.exp(x[1])), [math.log(f_lin), math.log(seen)],
                     method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-9 * max(e_lin, 1e-30)})
    f_j, s_j = min(math.exp(float(joint.x[0])), f_top), math.exp(float(joint.x[1]))
    keep_slew = s_j < 2.0 * seen and _slew_explains(u[k0:], v[k0:], dt, (f_lin, f_j, s_j))
    f_c, slew = (f_j, s_j) if keep_slew else (f_lin, None)
    rms = math.sqrt((float(joint.fun) if keep_slew else e_lin) / max(1, u.size - k0))
    info: dict[str, float | str] = {"fit_rms_V": rms, "gain_V_per_V": gain, "slew_seen_V_per_s": seen,
                                    "sample_rate_Hz": 1.0 / dt, "fitted_from": "recorded piezo voltage"}
    if f_c >= 0.99 * f_top:
        info["note"] = "bandwidth at the Nyquist frequency: the record cannot tell the amplifier from instantaneous"
    log.info("amplifier stage: %.5g Hz, slew %s (fit RMS %.3g V)", f_c, "none" if slew is None else f"{slew:.4g} V/s",
             rms)
    return AmplifierModel(bandwidth_Hz=f_c, slew_V_per_s=slew, fit_info=info,
                          u_range_V=(float(np.min(u)), float(np.max(u))))
