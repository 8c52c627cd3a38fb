"""Ambient-temperature inputs for the drift predictor (no file I/O here).

* :class:`TemperatureProfile` — a configured profile (constant, ramp, step, sine) in °C
  as a function of time in s; JSON/TOML-friendly pydantic model.
* :func:`check_temperature_series` — validation of measured ``t,T`` samples (NaN,
  out-of-order or repeated timestamps, gaps longer than a limit) with one-line errors;
* :func:`resample_uniform` — linear interpolation of a validated series onto a uniform
  grid (this is how gaps up to the limit are bridged: the temperature is taken as
  linear across the gap, so the predicted drift has no jump).
"""
from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from .base import ModelError
from .errortext import plain_repr

#: The one allowed range of ambient temperatures [°C] (config files, zenoh temperature
#: messages, the controller, the simulator and the drift predictor all check against it);
#: anything outside is a sensor or file error.
T_MIN_C, T_MAX_C = -50.0, 150.0


class TemperatureProfile(BaseModel):
    """Ambient temperature ``T(t)`` [°C].

    * ``constant``: ``T0_C``;
    * ``ramp``: ``T0_C`` until ``t_start_s``, then linear by ``delta_K`` over
      ``duration_s``, then held (the nonlinearities paper's scenario: 2 K over 600 s);
    * ``step``: ``T0_C``, then ``T0_C + delta_K`` from ``t_start_s`` on;
    * ``sine``: ``T0_C + delta_K·sin(2π(t − t_start_s)/period_s)`` from ``t_start_s`` on.
    """

    model_config = ConfigDict(extra="forbid")

    shape: Literal["constant", "ramp", "step", "sine"] = "constant"
    T0_C: float = Field(20.0, ge=T_MIN_C, le=T_MAX_C, description="initial temperature [°C]")
    delta_K: float = Field(0.0, ge=-100.0, le=100.0, description="change (ramp/step) or amplitude (sine) [K]")
    t_start_s: float = Field(0.0, ge=0.0, description="start of the change [s]")
    duration_s: float = Field(600.0, gt=0.0, description="ramp duration [s]")
    period_s: float = Field(3600.0, gt=0.0, description="sine period [s]")

    @model_validator(mode="after")
    def _finite(self) -> "TemperatureProfile":
        for name in ("T0_C", "delta_K", "t_start_s", "duration_s", "period_s"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name}: must be finite")
        T0, d = self.T0_C, self.delta_K
        lo, hi = (T0 - abs(d), T0 + abs(d)) if self.shape == "sine" else (min(T0, T0 + d), max(T0, T0 + d))
        if self.shape != "constant" and not (T_MIN_C <= lo and hi <= T_MAX_C):
            raise ValueError(f"delta_K: the profile reaches {lo:g}..{hi:g} °C; allowed {T_MIN_C:g}..{T_MAX_C:g} °C")
        return self

    def at(self, t_s: np.ndarray | float) -> np.ndarray:
        """Temperature [°C] at times ``t_s`` [s] (array in, array out)."""
        t = np.asarray(t_s, dtype=np.float64)
        rel = t - self.t_start_s
        if self.shape == "constant":
            return np.full_like(t, self.T0_C)
        if self.shape == "ramp":
            return self.T0_C + self.delta_K * np.clip(rel / self.duration_s, 0.0, 1.0)
        if self.shape == "step":
            return self.T0_C + self.delta_K * (rel >= 0.0)
        return self.T0_C + np.where(rel >= 0.0, self.delta_K * np.sin(2.0 * np.pi * rel / self.period_s), 0.0)


def check_temperature_series(t_s: np.ndarray, T_C: np.ndarray, where: str = "temperature",
                             max_gap_s: float | None = None) -> None:
    """Raise :class:`ModelError` (one line naming the row, 1-based data rows) unless
    ``t_s`` is finite and strictly increasing, ``T_C`` finite and within ``T_MIN_C``…``T_MAX_C`` (−50…150 °C),
    and no step is longer than ``max_gap_s``."""
    t = np.asarray(t_s, dtype=np.float64)
    T = np.asarray(T_C, dtype=np.float64)
    if t.ndim != 1 or t.shape != T.shape:
        raise ModelError(f"{where}: t and T must be 1-D of equal length (got {t.shape}, {T.shape})")
    if t.size == 0:
        raise ModelError(f"{where}: no samples; at least 1 row is required")
    for name, arr in (("t", t), ("T", T)):
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise ModelError(f"{where}: column {name}: row {int(bad[0]) + 1} is {float(arr[bad[0]])!r}; values must be finite")
    out = np.flatnonzero((T < T_MIN_C) | (T > T_MAX_C))
    if out.size:
        raise ModelError(f"{where}: column T: row {int(out[0]) + 1} is {float(T[out[0]])!r} °C; "
                         f"allowed {T_MIN_C:g}..{T_MAX_C:g} °C")
    d = np.diff(t)
    bad = np.flatnonzero(d <= 0)
    if bad.size:
        i = int(bad[0])
        raise ModelError(f"{where}: column t: time must be strictly increasing; row {i + 2} ({float(t[i + 1])!r} s) "
                         f"follows {float(t[i])!r} s")
    if max_gap_s is not None and d.size:
        big = np.flatnonzero(d > max_gap_s)
        if big.size:
            i = int(big[0])
            raise ModelError(f"{where}: column t: gap of {d[i]:g} s between rows {i + 1} and {i + 2} exceeds "
                             f"the allowed {max_gap_s:g} s (max gap); fill the gap or raise the limit")


def resample_uniform(t_s: np.ndarray, values: np.ndarray, dt_s: float, max_samples: int = 20_000_000
                     ) -> tuple[np.ndarray, np.ndarray]:
    """``(t_grid, values_on_grid)``: linear interpolation of ``values`` (N,) or (N, k) at
    times ``t_s`` onto ``t_grid = t_s[0] + k·dt_s`` covering ``t_s[-1]``."""
    t = np.asarray(t_s, dtype=np.float64)
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise ModelError(f"dt_s: {plain_repr(dt_s)} s; must be > 0")
    n = int(math.ceil((t[-1] - t[0]) / dt_s - 1e-9)) + 1
    if n > max_samples:
        raise ModelError(f"dt_s: {dt_s:g} s over {t[-1] - t[0]:g} s needs {n} samples; at most {max_samples} "
                         "(choose a larger step)")
    grid = t[0] + dt_s * np.arange(n)
    v = np.asarray(values, dtype=np.float64)
    if v.ndim == 1:
        return grid, np.interp(grid, t, v)
    return grid, np.column_stack([np.interp(grid, t, v[:, j]) for j in range(v.shape[1])])
