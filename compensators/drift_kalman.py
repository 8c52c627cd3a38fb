"""Online drift correction: a Kalman filter that fuses the drift model's prediction with
drift measurements when they arrive.

The drift model (:mod:`afmctl.compensators.drift`) is right in shape but not in size: its
coefficients are uncertain (Table A1 of the drift paper has unstated units, and any real
scanner differs from its nominal set). We write the true drift per axis as

    d_true(t) = d_model(t) + b(t)

and track the bias ``b`` [nm] (and, by default, its rate ``ḃ`` [nm/s]) as a random walk
(integrated random walk with ``with_rate=True``). A measurement — the displacement of a
reference feature found by phase correlation between images
(:mod:`afmctl.compensators.phase_correlation`), or a position sensor — is
``z = d_true + v``, ``v ~ N(0, σ²)``, so the innovation is ``z − (d_model + b)``.

The three axes are independent two-state (or one-state) filters.

* :meth:`DriftKalman.predict` — once per loop sample (or per call with its own
  ``dt_s``): advances the bias, stores the model drift, returns the estimate
  ``d_model + b`` [nm] (3,);
* :meth:`DriftKalman.update` — when a measurement arrives: ``measured_drift_nm`` (3,)
  (NaN for an axis that was not measured), ``meas_std_nm`` (scalar or (3,)). Pass
  ``model_drift_nm`` when the measurement refers to a different instant or window than
  the last prediction (e.g. the mean model drift over an image frame) and ``age_s`` for
  how long ago that instant was;
* :attr:`estimate_nm`, :attr:`std_nm` (1-σ of the bias, i.e. of the estimate when the
  model's shape is right), :attr:`bias_nm`, :attr:`rate_nm_per_s`.

Process noise (continuous white noise densities): the bias rate is driven by
``q_rate_nm2_per_s3`` (nm²/s³), the bias itself by ``q_bias_nm2_per_s`` (nm²/s), i.e.
per step ``Q = q_rate·[[dt³/3, dt²/2], [dt²/2, dt]] + q_bias·[[dt, 0], [0, 0]]``.
"""
from __future__ import annotations

import math

import numba
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .base import ModelError
from .errortext import plain_repr


class KalmanParams(BaseModel):
    """Tuning of :class:`DriftKalman` (units in the field names)."""

    model_config = ConfigDict(extra="forbid")

    with_rate: bool = True
    bias_std0_nm: float = Field(10.0, gt=0, le=1e6, description="prior 1-σ of the bias [nm]")
    rate_std0_nm_per_s: float = Field(0.05, gt=0, le=1e4, description="prior 1-σ of the bias rate [nm/s]")
    q_bias_nm2_per_s: float = Field(1e-4, ge=0, le=1e6, description="bias random-walk density [nm²/s]")
    q_rate_nm2_per_s3: float = Field(1e-7, ge=0, le=1e6, description="bias-rate random-walk density [nm²/s³]")


def _predict_loop(x, P, m, dt, q_rate, q_bias, est):
    """Time update of the three per-axis filters (x: (3, n), P: (3, n, n), n = 1 or 2):
    ``x ← F·x``, ``P ← F·P·Fᵀ + Q``, ``est = m + bias``. Plain loops: the numba kernel
    and this python reference do the same arithmetic (tested equal)."""
    n = x.shape[1]
    for a in range(3):
        if n == 2:
            x[a, 0] = x[a, 0] + dt * x[a, 1]
            p00 = P[a, 0, 0]
            p01 = P[a, 0, 1]
            p11 = P[a, 1, 1]
            n01 = p01 + dt * p11
            P[a, 0, 0] = p00 + dt * (p01 + n01) + q_rate * dt * dt * dt / 3.0 + q_bias * dt
            n01 = n01 + q_rate * dt * dt / 2.0
            P[a, 0, 1] = n01
            P[a, 1, 0] = n01
            P[a, 1, 1] = p11 + q_rate * dt
        else:
            P[a, 0, 0] = P[a, 0, 0] + q_bias * dt
        est[a] = m[a] + x[a, 0]


_predict_kernel = numba.njit(cache=True)(_predict_loop)


def _number(value: object) -> float:
    """``value`` as a float; NaN for anything that is not a number (callers reject NaN)."""
    if isinstance(value, (str, bytes, bool)):
        return math.nan
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        return math.nan


def _vector(name: str, value: object) -> np.ndarray:
    """``value`` as a float array (-1,), or ModelError naming ``name`` (checks of length
    and finiteness follow at the caller)."""
    try:
        return np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ModelError(f"{name}: {value!r:.60}; need 3 numbers [nm]") from None


class DriftKalman:
    """Per-axis bias (+ bias rate) Kalman filter around a drift model; see the module
    docstring. ``dt_s`` [s] is the default step of :meth:`predict`."""

    def __init__(self, dt_s: float, params: KalmanParams | None = None, **overrides: float | bool) -> None:
        if not (isinstance(dt_s, (int, float)) and not isinstance(dt_s, bool) and math.isfinite(dt_s) and dt_s > 0):
            raise ModelError(f"dt_s: {plain_repr(dt_s)} s; must be a positive finite number")
        base = params if params is not None else KalmanParams()
        self.params = base.model_copy(update=overrides) if overrides else base
        KalmanParams.model_validate(self.params.model_dump())
        self.dt_s = float(dt_s)
        self.n = 2 if self.params.with_rate else 1
        self.reset()

    def reset(self) -> None:
        """Zero bias and rate, prior covariance, zero model drift."""
        p = self.params
        self.x = np.zeros((3, self.n))
        self.P = np.zeros((3, self.n, self.n))
        self.P[:, 0, 0] = p.bias_std0_nm ** 2
        if self.n == 2:
            self.P[:, 1, 1] = p.rate_std0_nm_per_s ** 2
        self.model_nm = np.zeros(3)
        self._est = np.zeros(3)
        self.n_updates = 0
        self.last_innovation_nm = np.full(3, np.nan)

    # ------------------------------------------------------------------ filter
    def predict(self, model_drift_nm: np.ndarray, dt_s: float | None = None) -> np.ndarray:
        """Advance by ``dt_s`` (default: the constructor's) and return ``model + bias``
        [nm] (3,)."""
        dt = self.dt_s if dt_s is None else _number(dt_s)
        if not (math.isfinite(dt) and dt >= 0):
            raise ModelError(f"dt_s: {plain_repr(dt_s)} s; must be a non-negative finite number")
        m = _vector("model_drift_nm", model_drift_nm).copy()
        if m.shape[0] != 3 or not math.isfinite(m[0] + m[1] + m[2]):
            raise ModelError(f"model_drift_nm: {model_drift_nm!r}; need 3 finite values [nm]")
        p = self.params
        _predict_kernel(self.x, self.P, m, dt, p.q_rate_nm2_per_s3 if self.n == 2 else 0.0,
                        p.q_bias_nm2_per_s, self._est)
        self.model_nm = m
        return self._est.copy()

    def update(self, measured_drift_nm: np.ndarray, meas_std_nm: float | np.ndarray,
               model_drift_nm: np.ndarray | None = None, age_s: float = 0.0) -> np.ndarray:
        """Fuse a drift measurement [nm] (3,; NaN = axis not measured) with 1-σ
        ``meas_std_nm`` [nm]. ``model_drift_nm`` is the model's drift for the same instant
        or window as the measurement (default: the last value given to :meth:`predict`).
        ``age_s`` [s] says how long ago the measured instant was (e.g. half an image
        frame for a frame-mean measurement): the bias then was ``b − age·ḃ``, so the
        measurement row is ``H = [1, −age]`` (process noise over the age is neglected).
        Returns the new estimate [nm] (3,)."""
        z = _vector("measured_drift_nm", measured_drift_nm)
        if z.shape[0] != 3 or np.any(np.isinf(z)):
            raise ModelError(f"measured_drift_nm: {measured_drift_nm!r}; need 3 values [nm] (NaN = not measured)")
        try:
            r = np.broadcast_to(np.asarray(meas_std_nm, dtype=np.float64), (3,))
        except (TypeError, ValueError):
            r = np.full(3, np.nan)
        if not np.all(np.isfinite(r)) or np.any(r <= 0):
            raise ModelError(f"meas_std_nm: {plain_repr(meas_std_nm)}; must be > 0 and finite [nm]")
        m = self.model_nm if model_drift_nm is None else _vector("model_drift_nm", model_drift_nm)
        if m.shape[0] != 3 or not np.all(np.isfinite(m)):
            raise ModelError(f"model_drift_nm: {model_drift_nm!r}; need 3 finite values [nm]")
        age = _number(age_s)
        if not (math.isfinite(age) and age >= 0):
            raise ModelError(f"age_s: {plain_repr(age_s)} s; must be a non-negative finite number")
        H = np.array([1.0, -age]) if self.n == 2 else np.array([1.0])
        for a in range(3):
            if not math.isfinite(z[a]):
                continue
            innov = z[a] - (m[a] + float(H @ self.x[a]))
            P = self.P[a]
            PH = P @ H
            s = float(H @ PH) + r[a] ** 2
            k = PH / s
            self.x[a] += k * innov
            P_new = P - np.outer(k, PH)
            self.P[a] = 0.5 * (P_new + P_new.T)
            self.last_innovation_nm[a] = innov
        self.n_updates += 1
        return self.estimate_nm

    # ------------------------------------------------------------------ read-out
    @property
    def estimate_nm(self) -> np.ndarray:
        """Current drift estimate ``model + bias`` [nm] (3,)."""
        return self.model_nm + self.x[:, 0]

    @property
    def std_nm(self) -> np.ndarray:
        """1-σ uncertainty of the estimate (of the bias) [nm] (3,)."""
        return np.sqrt(np.maximum(self.P[:, 0, 0], 0.0))

    @property
    def bias_nm(self) -> np.ndarray:
        return self.x[:, 0].copy()

    @property
    def rate_nm_per_s(self) -> np.ndarray:
        return self.x[:, 1].copy() if self.n == 2 else np.zeros(3)
