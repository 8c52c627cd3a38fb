"""Configuration of the simulated 3-axis scanner (pydantic, ``extra="forbid"``).

Every field names its unit (``_V``, ``_nm``, ``_s``, ``_Hz``, ``_C``, ``_per_K``...).
:func:`default_scanner_config` gives the default scanner: 0–150 V amplifiers on every
axis, an asymmetric Preisach hysteresis built from a Gaussian-mixture density (image-based
paper, eq. 3), a logarithmic-like creep bank (nonlinearities paper, eq. 21), a 1 kHz
lateral / 5 kHz vertical structural mode, first-order thermal expansion drift, x/y
cross-coupling and sensor noise.
"""
from __future__ import annotations

import math
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from afmctl.compensators.temperature import T_MAX_C, T_MIN_C

AXES = ("x", "y", "z")


class _Strict(BaseModel):
    # no unknown fields; NaN/±inf rejected in every float field ("Input should be a finite number")
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class _VoltageSpan(_Strict):
    """A model with fields ``u_min_V`` < ``u_max_V`` (checked after validation)."""

    @model_validator(mode="after")
    def _range(self):
        if not self.u_max_V > self.u_min_V:
            raise ValueError(f"u_max_V ({self.u_max_V}) must be greater than u_min_V ({self.u_min_V})")
        return self


class AmplifierConfig(_VoltageSpan):
    """Piezo amplifier model: command → clip → quantise → slew limit → low-pass → piezo.

    ``bandwidth_Hz`` and ``slew_V_per_s`` are the amplifier's figures with its load. To
    derive them from the piezo instead, give ``load_capacitance_F`` with
    ``output_resistance_ohm`` (the output stage and the piezo's capacitance form an RC
    low-pass, f = 1/(2π·R·C)) and/or ``current_limit_A`` (a current-limited output slews
    at most I/C); the effective value is the lower of the two."""

    u_min_V: float = Field(0.0, description="lowest output voltage [V]")
    u_max_V: float = Field(150.0, description="highest output voltage [V]")
    bits: int = Field(16, ge=0, le=32, description="DAC resolution over u_min_V…u_max_V; 0 = no quantisation")
    slew_V_per_s: float | None = Field(1.0e4, gt=0, description="slew-rate limit [V/s]; null = unlimited")
    bandwidth_Hz: float | None = Field(5.0e3, gt=0, description="first-order -3 dB bandwidth [Hz]; null = unlimited")
    load_capacitance_F: float | None = Field(None, gt=0, le=1e-3, description="piezo capacitance [F]")
    output_resistance_ohm: float | None = Field(None, gt=0, description="output resistance [Ω] (with the load)")
    current_limit_A: float | None = Field(None, gt=0, description="output current limit [A] (with the load)")

    def effective_bandwidth_Hz(self) -> float | None:
        """-3 dB bandwidth [Hz] with the capacitive load (None = unlimited)."""
        f = [self.bandwidth_Hz] if self.bandwidth_Hz else []
        if self.load_capacitance_F and self.output_resistance_ohm:
            f.append(1.0 / (2 * math.pi * self.output_resistance_ohm * self.load_capacitance_F))
        return min(f) if f else None

    def effective_slew_V_per_s(self) -> float | None:
        """Slew limit [V/s] with the capacitive load (None = unlimited)."""
        s = [self.slew_V_per_s] if self.slew_V_per_s else []
        if self.load_capacitance_F and self.current_limit_A:
            s.append(self.current_limit_A / self.load_capacitance_F)
        return min(s) if s else None


class PreisachComponent(_Strict):
    """One 2-D Gaussian of the Preisach density μ(α, β) (α = up-switching, β = down-switching
    threshold, both in V). ``mass_nm`` is the displacement the component contributes when all
    its relays are up (its integral over the half-plane α ≥ β)."""

    mass_nm: float = Field(..., ge=0)
    alpha_V: float
    beta_V: float
    sigma_alpha_V: float = Field(..., gt=0)
    sigma_beta_V: float = Field(..., gt=0)
    rho: float = Field(0.0, gt=-1, lt=1, description="correlation of α and β (dimensionless)")


class GaussianPreisachConfig(_VoltageSpan):
    """Classical Preisach hysteresis (image-based paper, eq. 3) whose density is a Gaussian
    mixture on the (α, β) half-plane over u_min_V…u_max_V, discretised on ``n_grid`` nodes,
    plus a reversible linear part ``linear_nm_per_V``: y = linear_nm_per_V·(u − u_min_V) + P[u].
    With no components the axis is linear (no hysteresis)."""

    kind: Literal["gaussian-preisach"] = "gaussian-preisach"
    u_min_V: float = 0.0
    u_max_V: float = 150.0
    n_grid: int = Field(151, ge=3, le=2001, description="grid nodes per axis of the Everett table")
    linear_nm_per_V: float = Field(50.0, description="reversible (anhysteretic) sensitivity [nm/V]")
    components: list[PreisachComponent] = Field(default_factory=list)
    rate_lag_s: float = Field(0.0, ge=0.0, le=1.0, description=(
        "rate-dependent hysteresis: the hysteretic (Preisach) part sees the voltage through a "
        "first-order lag of this time constant [s] while the reversible part follows it at once, "
        "so the loop widens with the input rate (extra phase ≈ 2π·f·rate_lag_s at f); 0 = "
        "rate-independent"))


class ExternalModelConfig(_Strict):
    """Any :class:`afmctl.compensators.models.HysteresisModel` as the plant, given as its model-file
    JSON object (``{"kind": "pi", ...}``); the plant uses ``model.forward(dt_s)``."""

    kind: Literal["model"] = "model"
    model: dict[str, Any]


HysteresisConfig = Annotated[Union[GaussianPreisachConfig, ExternalModelConfig], Field(discriminator="kind")]


class CreepConfig(_Strict):
    """Creep as a bank of first-order lags with log-spaced time constants (nonlinearities
    paper, eq. 21): y = h − Σ_k g_k·(h − x_k), x_k' = (h − x_k)/τ_k, with the g_k equal and
    Σ g_k = ``fraction``. The DC gain is 1: a step rises at once to (1 − fraction) of its
    final value and creeps the rest of the way (≈ logarithmically in time between
    tau_min_s and tau_max_s) — on images this acts like a delay on ascending edges."""

    fraction: float = Field(0.04, ge=0, lt=1, description="creeping part of a step response (dimensionless)")
    tau_min_s: float = Field(0.01, gt=0)
    tau_max_s: float = Field(100.0, gt=0)
    n_lags: int = Field(5, ge=1, le=32)

    @model_validator(mode="after")
    def _order(self) -> "CreepConfig":
        if self.tau_max_s < self.tau_min_s:
            raise ValueError(f"tau_max_s ({self.tau_max_s}) must be ≥ tau_min_s ({self.tau_min_s})")
        return self


class DynamicsConfig(_Strict):
    """One second-order structural mode, unit DC gain: p'' = ω²(r − p) − (ω/Q)·p',
    ω = 2π·resonance_Hz, discretised exactly (zero-order hold, matrix exponential)."""

    resonance_Hz: float = Field(1000.0, gt=0)
    quality_factor: float = Field(20.0, gt=0, description="Q (dimensionless)")


class SensorConfig(_Strict):
    """The axis's position sensor (a capacitive or strain-gauge sensor read by the
    amplifier's data recorder): it sees the true tip position of its axis through a
    first-order low-pass (``bandwidth_Hz``, -3 dB; null = none), a pure delay ``delay_s``
    (whole simulation samples ``dt_s``), Gaussian noise ``noise_nm`` (RMS, seeded by the
    scanner's ``seed``) and a quantiser of step ``resolution_nm`` (0 = none):
    s[n] = Q(lp[n - d] + w[n]). A separate reading: the true tip position is not changed."""

    noise_nm: float = Field(0.2, ge=0, le=1.0e4, description="RMS noise of a reading [nm]")
    resolution_nm: float = Field(0.1, ge=0, le=1.0e4, description="quantisation step [nm]; 0 = none")
    bandwidth_Hz: float | None = Field(1.0e4, gt=0, le=1.0e9, description="first-order -3 dB bandwidth [Hz]; null = unlimited")
    delay_s: float = Field(0.0, ge=0, le=0.1, description="pure delay [s] (rounded to whole dt_s)")


class AxisConfig(_Strict):
    """One axis: amplifier → hysteresis → creep → structural mode(s), and the position
    sensor that reads it.

    ``dynamics`` is the first (dominant) mode; ``extra_modes`` are further modes in series
    after it (each unit DC gain, discretised the same way)."""

    amplifier: AmplifierConfig = Field(default_factory=AmplifierConfig)
    hysteresis: HysteresisConfig = Field(default_factory=GaussianPreisachConfig)
    creep: CreepConfig | None = None
    dynamics: DynamicsConfig | None = None
    extra_modes: list[DynamicsConfig] = Field(default_factory=list, max_length=8)
    sensor: SensorConfig = Field(default_factory=SensorConfig)


class DriftConfig(_Strict):
    """Thermal drift added to the tip position.

    ``kind="params"`` (default): the drift paper's transfer functions from ambient
    temperature and piezo heat, ``compensators.drift.DriftParams`` — the named set
    ``named`` (e.g. "physical_tube", "table_a1") or, when ``params`` is given, that JSON
    object — run as ``params.predictor(dt_s)`` on the piezo voltages and the ambient
    temperature.
    ``kind="expansion"``: first-order thermal model, the scanner temperature follows the
    ambient one with time constant ``thermal_tau_s``, drift_nm = expansion_nm_per_K ·
    (T_scanner − T_at_reset).
    ``kind="none"``: no drift."""

    kind: Literal["params", "expansion", "none"] = "params"
    named: str = "physical_tube"
    params: dict[str, Any] | None = None
    expansion_nm_per_K: tuple[float, float, float] = (2.0, 1.2, 40.0)
    thermal_tau_s: float = Field(120.0, gt=0)


class NoiseConfig(_Strict):
    """Sensor noise (Gaussian, seeded): position sensor readings and image heights."""

    position_std_nm: float = Field(0.1, ge=0)
    height_std_nm: float = Field(0.05, ge=0)


class ScannerConfig(_Strict):
    """The simulated 3-axis piezo scanner. ``dt_s`` is the sample period of the streaming
    simulation (:meth:`Scanner.advance`); :meth:`Scanner.run` may use any period."""

    name: str = "sim0"
    dt_s: float = Field(1.0e-5, gt=0, le=1.0)
    seed: int = Field(0, ge=0, description="seed of the sensor/height noise (non-negative integer)")
    ambient_T_C: float = Field(22.0, ge=T_MIN_C, le=T_MAX_C)
    x: AxisConfig = Field(default_factory=AxisConfig)
    y: AxisConfig = Field(default_factory=AxisConfig)
    z: AxisConfig = Field(default_factory=AxisConfig)
    coupling: list[list[float]] = Field(
        default_factory=lambda: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        description="3×3 matrix applied to the axis displacements [x, y, z] (dimensionless)",
    )
    drift: DriftConfig = Field(default_factory=DriftConfig)
    noise: NoiseConfig = Field(default_factory=NoiseConfig)

    @field_validator("coupling")
    @classmethod
    def _coupling(cls, v: list[list[float]]) -> list[list[float]]:
        if len(v) != 3 or any(len(r) != 3 for r in v):
            raise ValueError("coupling must be a 3×3 matrix")
        if any(not math.isfinite(c) for r in v for c in r):
            raise ValueError("coupling entries must be finite")
        return v

    def axis(self, name: str) -> AxisConfig:
        return getattr(self, name)


def default_preisach(axis: str = "x") -> GaussianPreisachConfig:
    """The default asymmetric Preisach plant of one axis (0–150 V).

    Lateral axes: ≈ 12 µm at 150 V (50 nm/V reversible + 4.5 µm of relays), loop width
    ≈ 12 % of the range, asymmetric (the density is heavier and wider at low β, so the
    ascending and descending branches are not point-symmetric). z: ≈ 2 µm range."""
    scale = 1.0 if axis in ("x", "y") else 1.0 / 6.0
    # y differs a little from x, so x and y are not identical.
    shift = 0.0 if axis == "x" else 4.0
    comps = [
        PreisachComponent(mass_nm=1800 * scale, alpha_V=55 + shift, beta_V=20, sigma_alpha_V=28, sigma_beta_V=18, rho=0.3),
        PreisachComponent(mass_nm=1700 * scale, alpha_V=110, beta_V=70 + shift, sigma_alpha_V=22, sigma_beta_V=25, rho=0.4),
        PreisachComponent(mass_nm=1000 * scale, alpha_V=80, beta_V=72, sigma_alpha_V=40, sigma_beta_V=40, rho=0.9),
    ]
    return GaussianPreisachConfig(linear_nm_per_V=50.0 * scale, components=comps)


def default_scanner_config() -> ScannerConfig:
    """The default 3-axis scanner (see the module docstring)."""
    lateral_amp = AmplifierConfig(u_min_V=0.0, u_max_V=150.0, bits=16, slew_V_per_s=1.0e4, bandwidth_Hz=5.0e3)
    x = AxisConfig(amplifier=lateral_amp, hysteresis=default_preisach("x"), creep=CreepConfig(),
                   dynamics=DynamicsConfig(resonance_Hz=1000.0, quality_factor=20.0))
    y = AxisConfig(amplifier=lateral_amp.model_copy(), hysteresis=default_preisach("y"), creep=CreepConfig(),
                   dynamics=DynamicsConfig(resonance_Hz=1000.0, quality_factor=20.0))
    z = AxisConfig(amplifier=lateral_amp.model_copy(), hysteresis=default_preisach("z"), creep=CreepConfig(),
                   dynamics=DynamicsConfig(resonance_Hz=5000.0, quality_factor=10.0))
    coupling = [[1.0, 0.004, 0.0], [0.006, 1.0, 0.0], [0.0, 0.0, 1.0]]
    return ScannerConfig(x=x, y=y, z=z, coupling=coupling)


def linear_scanner_config(**overrides: Any) -> ScannerConfig:
    """A scanner with no hysteresis, creep, dynamics, drift, coupling or noise (the
    "linear model" reference of the nonlinearities paper): y = 80 nm/V · u laterally,
    13.33 nm/V in z. Fields can be overridden by keyword."""
    ideal_amp = AmplifierConfig(bits=0, slew_V_per_s=None, bandwidth_Hz=None)
    lat = AxisConfig(amplifier=ideal_amp, hysteresis=GaussianPreisachConfig(linear_nm_per_V=80.0))
    z = AxisConfig(amplifier=ideal_amp.model_copy(), hysteresis=GaussianPreisachConfig(linear_nm_per_V=80.0 / 6.0))
    cfg = ScannerConfig(x=lat, y=lat.model_copy(deep=True), z=z, drift=DriftConfig(kind="none"),
                        noise=NoiseConfig(position_std_nm=0.0, height_std_nm=0.0))
    return cfg.model_copy(update=overrides) if overrides else cfg
