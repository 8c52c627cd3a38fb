"""Heat generated in a piezotube by its drive voltage (drift paper, eqs. 4–9).

Korayem & Sadeghzadeh (Scientia Iranica F 17(2), 2010) derive the heat generated in a
piezotube from the charge induced on its electrodes (eqs. 5–6), the dissipated power
(eq. 7) and the mechanical strain energy (eq. 4):

    HG = S_DE · V · dV/dt − S_EE · V²                                      (eq. 8)

    S_DE = e31² · π · D_t · L / (2 · t · E)        [J/V² = W·s/V²]         (eqs. 5–7, 9)
    S_EE = (π/32) · E · D_t · L · (d31 / t)²       [printed as N·m/V²]     (eq. 9)

with ``D_t = d_out² − d_in²`` (m²), tube length ``L`` (m), wall thickness ``t`` (m),
modulus of elasticity ``E`` (Pa), piezoelectric charge constant ``e31`` (C/m²) and strain
constant ``d31`` (m/V).

Reading of the damaged/loose parts of the text (also listed in docs/DRIFT.md):

* Eqs. 5–7 print ``e31²·π·D_t·L·E/(2t)``; only ``E`` in the *denominator* gives a
  capacitance-like ``S_DE`` (about 1e-12 J/V² for a 40 mm PZT-5H tube, against the
  paper's "3.77e-11 J for 1 V"); eq. 9 writes ``g31`` where eq. 7 has ``e31``. We use
  ``e31`` and ``E`` in the denominator.
* ``S_EE·V²`` is an energy (J) while ``S_DE·V·V̇`` is a power (W); the paper subtracts
  them anyway. We keep eq. 8 as published and treat ``S_EE`` as a power coefficient in
  W/V² (numerically the eq. 9 value, i.e. "per second"). Because of that, eq. 8 is
  negative for a held voltage; it is kept so (no clipping) — the drift transfer
  functions are linear in HG.
* ``V·V̇`` is evaluated as the backward difference of ``V²/2``:
  ``V·V̇ ≈ (V_k² − V_{k−1}²) / (2·dt)``, so a voltage step deposits ``S_DE·Δ(V²)/2`` of
  energy whatever the sample period (the first sample after reset has ``V̇ = 0``).

Units: volts in, watts out, seconds for ``dt_s``.
"""
from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from .base import ModelError, check_finite


class TubeGeometry(BaseModel):
    """Piezotube geometry and material constants (SI units; defaults: a 40 mm PZT-5H tube,
    1/4" outer diameter, 0.51 mm wall — the length the nonlinearities paper and Table 2 of
    the drift paper use)."""

    model_config = ConfigDict(extra="forbid")

    length_m: float = Field(0.040, gt=0, le=1.0, description="tube length L [m]")
    outer_diameter_m: float = Field(6.35e-3, gt=0, le=0.2, description="outer diameter d_out [m]")
    wall_m: float = Field(0.51e-3, gt=0, le=0.05, description="wall thickness t [m]")
    e31_C_per_m2: float = Field(-6.55, description="piezoelectric charge constant e31 [C/m²] (PZT-5H ≈ −6.55)")
    d31_m_per_V: float = Field(-274e-12, description="piezoelectric strain constant d31 [m/V] (PZT-5H ≈ −274e-12)")
    E_Pa: float = Field(60.6e9, gt=0, description="modulus of elasticity E [Pa] (PZT-5H 1/s11 ≈ 60.6e9)")

    @model_validator(mode="after")
    def _wall_fits(self) -> "TubeGeometry":
        if 2 * self.wall_m >= self.outer_diameter_m:
            raise ValueError(f"wall_m: {self.wall_m} m must be less than half the outer diameter "
                             f"({self.outer_diameter_m / 2} m)")
        return self

    @property
    def inner_diameter_m(self) -> float:
        return self.outer_diameter_m - 2 * self.wall_m

    @property
    def D_t_m2(self) -> float:
        """Diameter parameter ``D_t = d_out² − d_in²`` [m²] (eq. 5)."""
        return self.outer_diameter_m ** 2 - self.inner_diameter_m ** 2


def heat_coefficients(tube: TubeGeometry) -> tuple[float, float]:
    """``(S_DE [J/V²], S_EE [W/V²])`` of eq. 9 for a tube (see the module docstring for
    how the damaged equations are read)."""
    Dt, L, t, E = tube.D_t_m2, tube.length_m, tube.wall_m, tube.E_Pa
    s_de = tube.e31_C_per_m2 ** 2 * math.pi * Dt * L / (2.0 * t * E)
    s_ee = math.pi / 32.0 * E * Dt * L * (tube.d31_m_per_V / t) ** 2
    return s_de, s_ee


class HeatParams(BaseModel):
    """Coefficients of eq. 8 for one axis: given directly, or computed from ``tube``.

    ``S_DE_J_per_V2`` multiplies ``V·dV/dt`` (V²/s) and gives W; ``S_EE_W_per_V2``
    multiplies ``V²`` and gives W. If a coefficient is left out and ``tube`` is given, it
    comes from :func:`heat_coefficients`; if both are left out and no tube is given, it
    is 0 (no heat).
    """

    model_config = ConfigDict(extra="forbid")

    S_DE_J_per_V2: float | None = Field(None, ge=0, le=1.0)
    S_EE_W_per_V2: float | None = Field(None, ge=0, le=1.0)
    tube: TubeGeometry | None = None

    @model_validator(mode="after")
    def _fill(self) -> "HeatParams":
        if self.tube is not None and (self.S_DE_J_per_V2 is None or self.S_EE_W_per_V2 is None):
            s_de, s_ee = heat_coefficients(self.tube)
            if self.S_DE_J_per_V2 is None:
                self.S_DE_J_per_V2 = s_de
            if self.S_EE_W_per_V2 is None:
                self.S_EE_W_per_V2 = s_ee
        if self.S_DE_J_per_V2 is None:
            self.S_DE_J_per_V2 = 0.0
        if self.S_EE_W_per_V2 is None:
            self.S_EE_W_per_V2 = 0.0
        return self

    @property
    def s_de(self) -> float:
        return float(self.S_DE_J_per_V2 or 0.0)

    @property
    def s_ee(self) -> float:
        return float(self.S_EE_W_per_V2 or 0.0)


class AxisHeat(BaseModel):
    """Eq. 8 coefficients per axis (x, y quadrants of the XY tube, z tube)."""

    model_config = ConfigDict(extra="forbid")

    x: HeatParams = Field(default_factory=HeatParams)
    y: HeatParams = Field(default_factory=HeatParams)
    z: HeatParams = Field(default_factory=HeatParams)

    def coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """``(S_DE (3,), S_EE (3,))`` arrays in axis order x, y, z."""
        s_de = np.array([self.x.s_de, self.y.s_de, self.z.s_de], dtype=np.float64)
        s_ee = np.array([self.x.s_ee, self.y.s_ee, self.z.s_ee], dtype=np.float64)
        return s_de, s_ee


def heat_generation(u_V: np.ndarray, dt_s: float, s_de: np.ndarray | float, s_ee: np.ndarray | float,
                    u_prev_V: np.ndarray | float | None = None) -> np.ndarray:
    """Eq. 8 for a block of voltages.

    ``u_V`` has shape (N,) or (N, axes); ``s_de``/``s_ee`` broadcast over the axes.
    ``u_prev_V`` is the voltage before the block (default: the first sample, i.e.
    ``V̇ = 0`` at the first sample). Returns HG in W with the shape of ``u_V``.
    This is the plain-numpy reference of the heat term inside the drift predictor.
    """
    if not (dt_s > 0 and math.isfinite(dt_s)):
        raise ModelError(f"dt_s: {dt_s!r} s; must be a positive finite number")
    u = check_finite("u_V", u_V)
    if u.shape[0] == 0:
        return u.copy()
    prev = u[0] if u_prev_V is None else np.asarray(u_prev_V, dtype=np.float64)
    u_before = np.concatenate([np.asarray(prev, dtype=np.float64)[None, ...] * np.ones_like(u[:1]), u[:-1]], axis=0)
    v2 = u * u
    vvdot = (v2 - u_before * u_before) / (2.0 * dt_s)
    return np.asarray(s_de) * vvdot - np.asarray(s_ee) * v2
