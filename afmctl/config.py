"""Configuration of the afmctl service: pydantic models read from TOML.

A configuration is one TOML file (see ``examples/``) validated by :class:`Config`.
Every table and key is checked: unknown keys are rejected, numbers are range-checked, and
an error names the field (``loop.rate_Hz``) and the allowed range.

Environment variables override the file: ``AFMCTL_<SECTION>__<KEY>=value`` (nested keys
separated by a double underscore), e.g. ``AFMCTL_LOOP__RATE_HZ=500`` or
``AFMCTL_AMPLIFIER__PORT=/dev/ttyUSB1``. Values are parsed as JSON when they look like it.

Units are in the field names: ``_V`` volts, ``_V_per_s`` volts per second, ``_nm``
nanometres, ``_s`` seconds, ``_Hz`` hertz, ``_C`` degrees Celsius.

:func:`load_config` reads a file (or a TOML string), applies the environment and returns a
:class:`Config`; any problem raises :class:`afmctl.errors.AfmctlError` with one line.
"""
from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from afmctl.compensators.errortext import first_validation_error, plain_repr
from afmctl.compensators.textfiles import decode_text, read_text_file
from afmctl.compensators.temperature import T_MAX_C, T_MIN_C
from afmctl.drivers.registry import driver_names

from .errors import AfmctlError
from .zenoh_api.settings import ZenohSettings

Axis = Literal["x", "y", "z"]
AXES: tuple[Axis, ...] = ("x", "y", "z")

class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


# --------------------------------------------------------------------------- scanner
class AxisSpec(_Strict):
    """Linear calibration of one axis, used where no hysteresis model is configured:
    ``u_V = offset_V + position_nm / nm_per_V``."""

    nm_per_V: float = Field(66.7, gt=0, le=1e6, description="sensitivity [nm/V] (> 0)")
    offset_V: float = Field(0.0, ge=-1000, le=1000, description="voltage at position 0 nm [V]")


class ScannerSection(_Strict):
    """The scanner being driven."""

    name: str = Field("scanner", pattern=r"^[A-Za-z0-9_\-.]+$", max_length=64,
                      description="scanner name (zenoh key chunk, run-log name)")
    axes: list[Axis] = Field(default_factory=lambda: list(AXES), min_length=1, max_length=3,
                             description="axes driven by the amplifier (subset of x, y, z)")
    calibration: dict[Axis, AxisSpec] = Field(default_factory=dict,
                                              description="linear calibration per axis (defaults apply)")

    @field_validator("axes")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError(f"axes {v}: each of x, y, z at most once")
        return v

    def axis_spec(self, axis: str) -> AxisSpec:
        return self.calibration.get(axis, AxisSpec())  # type: ignore[call-overload]


# --------------------------------------------------------------------------- amplifier
class Limits(_Strict):
    """A closed voltage interval [min_V, max_V]."""

    min_V: float = Field(0.0, ge=-1000, le=1000, description="lowest voltage [V]")
    max_V: float = Field(150.0, ge=-1000, le=1000, description="highest voltage [V]")

    @model_validator(mode="after")
    def _order(self) -> "Limits":
        if not self.min_V < self.max_V:
            raise ValueError(f"min_V ({self.min_V:g}) must be below max_V ({self.max_V:g})")
        return self


#: ``amplifier.settle_s`` unset: the hold before a planned wave table [s]
DEFAULT_SETTLE_S = 0.2
#: ``amplifier.settle_s`` unset: the hold before each play of ``afmctl learn`` [s] — after
#: the approach ramp the creep still moves the scanner for seconds; with 0.2 s two plays
#: from rest differ by 1-3 nm on the simulated scanner, with 2 s by under 0.7 nm
#: (docs/LEARNING.md), and a learned table is only as repeatable as its plays
LEARN_SETTLE_S = 2.0


class AmplifierSection(_Strict):
    """The amplifier link (drivers.registry.open_amplifier)."""

    driver: str = Field("mdt693b", description="driver name: " + ", ".join(driver_names()),
                        json_schema_extra={"enum": list(driver_names())})
    port: str = Field("", description="pyserial URL/path (e.g. /dev/ttyUSB0) or 'virtual:afm0' for CAN; "
                                      "empty with [simulation] enabled")
    options: dict[str, Any] = Field(default_factory=dict, description="extra driver options (e.g. baudrate)")
    limits_V: dict[Axis, Limits] = Field(default_factory=dict,
                                         description="host voltage limits per axis [V] (default 0..150 V)")
    slew_V_per_s: float = Field(1000.0, gt=0, le=1e7, description="largest output slew rate [V/s]")
    output: Literal["setpoints", "stream", "wave"] = Field(
        "setpoints", description="how the loop reaches the amplifier: 'setpoints' (one setpoint per tick, the "
                                 "host's timing), 'stream' (device-timed: samples queued ahead into the "
                                 "amplifier's FIFO, driver 'can'), 'wave' (a finite trajectory computed whole "
                                 "before the run, as `afmctl compensate` does, and played on the "
                                 "amplifier's clock: wave generator of drivers 'gcs'/'nv200', stream "
                                 "FIFO of 'can')")
    settle_s: float | None = Field(None, ge=0.0, le=60.0, description=(
        "output = 'wave': hold at the table's first row this long after the approach ramp, before the table starts "
        "[s] (the ramp's ringing and creep die out, the same way in every play); unset: "
        f"{DEFAULT_SETTLE_S:g} s for a planned table, {LEARN_SETTLE_S:g} s while afmctl learn plays, and for "
        "trajectory.kind = 'learned' the hold the table was learned with"))
    low_water_s: float = Field(0.1, gt=0.0, le=10.0, description="output = 'stream'/'wave' on CAN: top the device FIFO up "
                                                                 "when it holds less than this [s of samples]")
    high_water_s: float = Field(0.2, gt=0.0, le=10.0, description="output = 'stream'/'wave' on CAN: fill the device FIFO to "
                                                                  "this [s of samples]; > low_water_s")

    def hold_s(self, unset: float = DEFAULT_SETTLE_S) -> float:
        """The settle hold [s]: ``settle_s``, or ``unset`` when the configuration leaves it out."""
        return float(self.settle_s) if self.settle_s is not None else float(unset)

    @model_validator(mode="after")
    def _stream_marks(self) -> "AmplifierSection":
        if self.output == "wave" and self.driver not in ("can", "gcs", "nv200"):
            raise ValueError(f"output = 'wave' needs a device clock: driver 'gcs', 'nv200' (wave generator) or "
                             f"'can' (stream FIFO) (got {self.driver!r})")
        if self.output == "stream" and self.driver != "can":
            raise ValueError(f"output = 'stream' needs a link that buffers: driver 'can' (got {self.driver!r})")
        if self.output in ("stream", "wave") and self.driver == "can":
            if not self.low_water_s < self.high_water_s:
                raise ValueError(f"low_water_s {self.low_water_s:g} must be below high_water_s "
                                 f"{self.high_water_s:g} [s]")
        return self

    @field_validator("driver")
    @classmethod
    def _known_driver(cls, v: str) -> str:
        """The registry's names are the only source of the allowed drivers."""
        if v not in driver_names():
            raise ValueError(f"unknown driver {v!r}; allowed: {', '.join(driver_names())}")
        return v

    def axis_limits(self, axis: str) -> Limits:
        return self.limits_V.get(axis, Limits())  # type: ignore[call-overload]


# --------------------------------------------------------------------------- loop
class LoopSection(_Strict):
    """The real-time loop."""

    rate_Hz: float = Field(1000.0, ge=1.0, le=20000.0, description="loop (sample) rate [Hz], 1..20000")
    spin_s: float = Field(2e-4, ge=0.0, le=0.005, description="busy-wait before each deadline [s], 0..0.005")
    block_samples: int = Field(256, ge=1, le=65536, description="trajectory samples generated per block")
    prefetch_blocks: int = Field(8, ge=1, le=1024, description="trajectory blocks buffered ahead of the loop")
    switch_interval_s: float | None = Field(2e-4, ge=1e-5, le=0.1,
                                            description="Python GIL switch interval while running [s] (None: leave)")
    realtime_priority: int | None = Field(
        None, ge=1, le=99, description="run the loop thread SCHED_FIFO at this priority (Linux; needs "
                                       "CAP_SYS_NICE or root; None: normal scheduling)")
    cpu: int | Literal["auto", "none"] | None = Field(
        "auto", description="CPU of the loop thread; every other afmctl thread and the zenoh process run on "
                            "the others: 'auto' (with realtime_priority set: the highest CPU when the process "
                            "may use two or more; otherwise no pinning), a CPU number 0..1023, or 'none'; "
                            "Linux only")
    gc_freeze: bool = Field(True, description="collect garbage and freeze the survivors at start (shorter "
                                              "garbage-collector pauses during the run)")
    phase: float | None = Field(
        None, ge=0.0, lt=1.0, description="where in each period the loop's deadlines fall on the machine's "
                                          "monotonic clock, as a share of the period, 0..1 (several loops on "
                                          "one CPU given 0, 1/3 and 2/3 do not spin at once); None: where "
                                          "the run happens to start")
    resync_periods: int = Field(20, ge=2, le=100000,
                                description="when this many periods late, restart the schedule instead of catching up")

    @field_validator("cpu")
    @classmethod
    def _cpu_number(cls, v: int | str | None) -> int | str | None:
        if isinstance(v, int) and not 0 <= v <= 1023:
            raise ValueError(f"{v} is not a CPU number 0..1023 (or 'auto', 'none')")
        return v

    @property
    def dt_s(self) -> float:
        return 1.0 / self.rate_Hz


# --------------------------------------------------------------------------- compensation
class AxisCompensation(_Strict):
    """Feedforward model of one axis: a model JSON file (afmctl identify) or none (linear)."""

    model: Path | None = Field(None, description="model JSON file (kind pi|epi|preisach|bouc-wen|rate-pi|rate-bouc-wen|creep|chain, "
                                                 "e.g. afmctl identify --model auto); overrides scanner_model "
                                                 "for this axis; none: linear calibration")


class DriftSection(_Strict):
    """Thermal-drift prediction (compensators.drift)."""

    enabled: bool = Field(False, description="subtract the predicted drift from the target")
    params: str = Field("physical_tube", description="named parameter set (physical_tube, table_a1) "
                                                "or a JSON file of DriftParams")
    overrides: dict[str, Any] = Field(default_factory=dict, description="DriftParams fields to override")
    kalman: bool = Field(False, description="fuse the prediction with drift measurements "
                                            "(compensators.drift_kalman.DriftKalman; needs enabled = true)")
    kalman_bias_std0_nm: float = Field(10.0, gt=0, le=1e6, description="prior 1-sigma of the bias [nm], (0, 1e6]")
    kalman_rate_std0_nm_per_s: float = Field(0.05, gt=0, le=1e4,
                                             description="prior 1-sigma of the bias rate [nm/s], (0, 1e4]")
    kalman_q_bias_nm2_per_s: float = Field(1e-4, ge=0, le=1e6,
                                           description="bias random-walk density [nm^2/s], 0..1e6")
    kalman_q_rate_nm2_per_s3: float = Field(1e-7, ge=0, le=1e6,
                                            description="bias-rate random-walk density [nm^2/s^3], 0..1e6")
    kalman_with_rate: bool = Field(True, description="track the bias rate [nm/s] as well as the bias")

    @model_validator(mode="after")
    def _kalman_needs_model(self) -> "DriftSection":
        if self.kalman and not self.enabled:
            raise ValueError("compensation.drift.kalman = true needs compensation.drift.enabled = true")
        return self

    def kalman_params(self):
        """The :class:`afmctl.compensators.drift_kalman.KalmanParams` of this section."""
        from afmctl.compensators.drift_kalman import KalmanParams
        return KalmanParams(with_rate=self.kalman_with_rate, bias_std0_nm=self.kalman_bias_std0_nm,
                            rate_std0_nm_per_s=self.kalman_rate_std0_nm_per_s,
                            q_bias_nm2_per_s=self.kalman_q_bias_nm2_per_s,
                            q_rate_nm2_per_s3=self.kalman_q_rate_nm2_per_s3)


class TemperatureSection(_Strict):
    """Where the ambient temperature for the drift predictor comes from."""

    source: Literal["constant", "file", "external"] = Field(
        "constant", description="constant value, a CSV file (t,T in s, °C) or external (zenoh/set_temperature)")
    T_C: float = Field(22.0, ge=T_MIN_C, le=T_MAX_C, description="constant / initial temperature [°C]")
    file: Path | None = Field(None, description="CSV with columns t,T (s, °C) for source = file")

    @model_validator(mode="after")
    def _file(self) -> "TemperatureSection":
        if self.source == "file" and self.file is None:
            raise ValueError("temperature.file is required when temperature.source = 'file'")
        return self


class CompensationSection(_Strict):
    """Feedforward: an optional scanner model file (per-axis chains + x/y/z coupling), per-axis
    model files that override it, drift prediction and its temperature source."""

    scanner_model: Path | None = Field(None, description="scanner model JSON (kind scanner): per-axis models "
                                                         "and the 3x3 coupling matrix with its inverse")
    x: AxisCompensation = Field(default_factory=AxisCompensation)
    y: AxisCompensation = Field(default_factory=AxisCompensation)
    z: AxisCompensation = Field(default_factory=AxisCompensation)
    drift: DriftSection = Field(default_factory=DriftSection)
    temperature: TemperatureSection = Field(default_factory=TemperatureSection)

    def axis(self, axis: str) -> AxisCompensation:
        return getattr(self, axis)


# --------------------------------------------------------------------------- safety
class SafetySection(_Strict):
    """Limits applied last, to every value sent to the amplifier (afmctl.control.safety)."""

    limits_V: dict[Axis, Limits] = Field(default_factory=dict,
                                         description="extra (tighter) voltage limits per axis [V]")
    slew_V_per_s: float = Field(1000.0, gt=0, le=1e7, description="slew-rate limit [V/s]")
    ramp_V_per_s: float = Field(100.0, gt=0, le=1e7,
                                description="rate of start/stop/resume ramps [V/s] (capped by the slew limits)")
    watchdog_s: float = Field(0.1, ge=0.001, le=60, description="trajectory stall before holding [s]")
    on_stall: Literal["hold", "safe"] = Field("hold", description="watchdog action: hold output or ramp to safe_V")
    on_finish: Literal["hold", "safe"] = Field("safe", description="at the end of the trajectory / stop(): "
                                                                    "hold the output or ramp to safe_V")
    safe_V: dict[Axis, float] = Field(default_factory=dict, description="safe output per axis [V] (default 0 V)")
    reconnect_interval_s: float = Field(0.2, ge=0.001, le=60, description="pause between reconnect attempts [s]")
    max_reconnects: int = Field(50, ge=0, le=1_000_000, description="attempts before giving up (state stays fault)")

    def safe_value(self, axis: str) -> float:
        return float(self.safe_V.get(axis, 0.0))  # type: ignore[call-overload]


# --------------------------------------------------------------------------- trajectory
_pos = Field(gt=0, le=1e7)


class RasterSpec(_Strict):
    """Raster scan in the x–y plane at height z."""

    kind: Literal["raster"] = "raster"
    x0_nm: float = Field(0.0, ge=-1e7, le=1e7, description="scan start x [nm]")
    y0_nm: float = Field(0.0, ge=-1e7, le=1e7, description="scan start y [nm]")
    z_nm: float = Field(0.0, ge=-1e7, le=1e7, description="height [nm]")
    width_nm: float = Field(1000.0, gt=0, le=1e7, description="fast-axis range [nm]")
    height_nm: float = Field(1000.0, ge=0, le=1e7, description="slow-axis range [nm]")
    lines: int = Field(64, ge=1, le=100000, description="number of scan lines")
    line_rate_Hz: float = Field(1.0, gt=0, le=10000, description="lines per second (trace + retrace = 1 line)")
    mode: Literal["trace-retrace", "bidirectional"] = Field(
        "trace-retrace", description="trace-retrace (each line forth and back) or bidirectional (serpentine)")
    fast_axis: Literal["x", "y"] = "x"
    repeat: int = Field(1, ge=1, le=100000, description="number of frames")


class Move(_Strict):
    x_nm: float = Field(ge=-1e7, le=1e7)
    y_nm: float = Field(ge=-1e7, le=1e7)
    z_nm: float = Field(0.0, ge=-1e7, le=1e7)
    dwell_s: float = Field(0.0, ge=0, le=3600, description="hold after arriving [s]")


class MovesSpec(_Strict):
    """Point-to-point moves with jerk-limited (S-curve) profiles."""

    kind: Literal["moves"] = "moves"
    points: list[Move] = Field(min_length=1, max_length=100000)
    start_nm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    v_max_nm_per_s: float = Field(5000.0, gt=0, le=1e9)
    a_max_nm_per_s2: float = Field(1e5, gt=0, le=1e12)
    j_max_nm_per_s3: float = Field(1e7, gt=0, le=1e15)


class IndentationSpec(_Strict):
    """Indentation array (extended-PI paper, Fig. 9): a grid of points, at each one the z
    axis presses down ``depth_nm`` and holds ``dwell_s``."""

    kind: Literal["indentation"] = "indentation"
    x0_nm: float = Field(0.0, ge=-1e7, le=1e7)
    y0_nm: float = Field(0.0, ge=-1e7, le=1e7)
    nx: int = Field(5, ge=1, le=1000)
    ny: int = Field(5, ge=1, le=1000)
    pitch_x_nm: float = Field(500.0, gt=0, le=1e7)
    pitch_y_nm: float = Field(500.0, gt=0, le=1e7)
    z_up_nm: float = Field(0.0, ge=-1e7, le=1e7, description="approach height [nm]")
    depth_nm: float = Field(100.0, gt=0, le=1e6, description="indentation depth below z_up_nm [nm]")
    dwell_s: float = Field(0.05, ge=0, le=60)
    v_max_nm_per_s: float = Field(5000.0, gt=0, le=1e9)
    a_max_nm_per_s2: float = Field(1e5, gt=0, le=1e12)
    j_max_nm_per_s3: float = Field(1e7, gt=0, le=1e15)


class TextSpec(_Strict):
    """Imprint a text with a single-stroke font (image-based paper: 'NK')."""

    kind: Literal["text"] = "text"
    text: str = Field("NK", min_length=1, max_length=64, description="letters A–Z, digits, space, '-'")
    x0_nm: float = Field(0.0, ge=-1e7, le=1e7)
    y0_nm: float = Field(0.0, ge=-1e7, le=1e7)
    height_nm: float = Field(2000.0, gt=0, le=1e7, description="letter height [nm]")
    z_up_nm: float = Field(0.0, ge=-1e7, le=1e7, description="height between strokes [nm]")
    z_down_nm: float = Field(-50.0, ge=-1e7, le=1e7, description="height while imprinting [nm]")
    speed_nm_per_s: float = Field(2000.0, gt=0, le=1e9)


class SpiralSpec(_Strict):
    """Archimedean spiral scan at constant linear speed."""

    kind: Literal["spiral"] = "spiral"
    cx_nm: float = Field(500.0, ge=-1e7, le=1e7)
    cy_nm: float = Field(500.0, ge=-1e7, le=1e7)
    z_nm: float = Field(0.0, ge=-1e7, le=1e7)
    radius_nm: float = Field(500.0, gt=0, le=1e7)
    pitch_nm: float = Field(50.0, gt=0, le=1e7, description="radial distance between turns [nm]")
    speed_nm_per_s: float = Field(2000.0, gt=0, le=1e9)


class FileSpec(_Strict):
    """Positions from a file: CSV with header t,x,y,z (s, nm) or NPY array (N,4)."""

    kind: Literal["file"] = "file"
    path: Path


class LearnedSpec(_Strict):
    """A table of voltages learned from the scanner's measured motion (``afmctl learn``),
    played as it is with ``amplifier.output = "wave"``; refused when the trajectory, the
    amplifier, its limits or the model files differ from those it was learned with."""

    kind: Literal["learned"] = "learned"
    file: Path = Field(description="learned table (.afmwave) written by afmctl learn")


class QueueSpec(_Strict):
    """Segments arriving at run time (zenoh, Controller.submit_segment)."""

    kind: Literal["queue"] = "queue"
    idle: Literal["hold", "end"] = Field("hold", description="when the queue is empty: hold (watchdog) or end the run")


TrajectorySpec = Annotated[
    RasterSpec | MovesSpec | IndentationSpec | TextSpec | SpiralSpec | FileSpec | LearnedSpec | QueueSpec,
    Field(discriminator="kind")]


# --------------------------------------------------------------------------- run log, simulation
class RunLogSection(_Strict):
    """Crash-safe log of every setpoint, drift estimate and state change (afmctl.control.runlog)."""

    enabled: bool = True
    dir: Path = Field(Path("runs"), description="directory for run logs (RUN-NAME.afmlog)")
    flush_interval_s: float = Field(0.05, gt=0, le=0.1, description="flush at least this often [s], ≤ 0.1")
    fsync: bool = Field(True, description="fsync after each flush (survives power loss, not only a crash)")


class SimulationSection(_Strict):
    """Run against a simulated scanner in this process: a simulated amplifier of
    ``amplifier.driver`` is served on a pty (serial drivers) or the virtual CAN bus, with a
    sim_backend Scanner as its load."""

    enabled: bool = Field(False, description="serve a simulated amplifier + scanner in-process")
    scanner: Path | None = Field(None, description="ScannerConfig JSON file; none: the default scanner")
    baud: int = Field(115200, ge=1200, le=10_000_000, description="simulated serial baud rate")
    device: dict[str, Any] = Field(default_factory=dict,
                                   description="options of the simulated amplifier, e.g. nv200: sensor = 'strain "
                                               "gauge', posmax_um = 12 (a sensored unit whose recorder reads the "
                                               "scanner's position sensor)")


# --------------------------------------------------------------------------- top level
class Config(BaseSettings):
    """The whole service configuration (one TOML file, ``AFMCTL_`` environment overrides)."""

    model_config = SettingsConfigDict(env_prefix="AFMCTL_", env_nested_delimiter="__", extra="forbid",
                                      case_sensitive=False, env_parse_none_str="none")

    scanner: ScannerSection = Field(default_factory=ScannerSection)
    amplifier: AmplifierSection = Field(default_factory=AmplifierSection)
    loop: LoopSection = Field(default_factory=LoopSection)
    compensation: CompensationSection = Field(default_factory=CompensationSection)
    safety: SafetySection = Field(default_factory=SafetySection)
    trajectory: TrajectorySpec = Field(default_factory=RasterSpec)
    runlog: RunLogSection = Field(default_factory=RunLogSection)
    simulation: SimulationSection = Field(default_factory=SimulationSection)
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)

    @field_validator("trajectory", mode="before")
    @classmethod
    def _default_kind(cls, v: Any) -> Any:
        if isinstance(v, dict) and "kind" not in v:
            return {"kind": "raster", **v}  # the default trajectory kind
        return v

    @classmethod
    def settings_customise_sources(cls, settings_cls: type[BaseSettings],
                                   init_settings: PydanticBaseSettingsSource,
                                   env_settings: PydanticBaseSettingsSource,
                                   dotenv_settings: PydanticBaseSettingsSource,
                                   file_secret_settings: PydanticBaseSettingsSource,
                                   ) -> tuple[PydanticBaseSettingsSource, ...]:
        # environment beats the file
        return (_EnvCaseSource(settings_cls, env_settings), init_settings)

    @model_validator(mode="after")
    def _cross_validator(self) -> "Config":
        return self._cross()

    def _cross(self) -> "Config":
        """The checks that span sections (also rerun after command-line overrides)."""
        if self.amplifier.driver == "mdt694b" and self.scanner.axes != ["x"]:
            raise ValueError("scanner.axes must be ['x'] for the single-channel mdt694b")
        for axis in self.scanner.axes:
            lo, hi = self.limits(axis)
            if not lo < hi:
                raise ValueError(f"safety.limits_V.{axis} and amplifier.limits_V.{axis} leave no voltage range "
                                 f"(intersection [{lo:g}, {hi:g}] V)")
        if not self.simulation.enabled and not self.amplifier.port:
            raise ValueError("amplifier.port is required unless simulation.enabled = true")
        if self.trajectory.kind == "learned" and self.amplifier.output != "wave":
            raise ValueError("trajectory.kind = 'learned' plays a learned table on the amplifier's clock: "
                             "set amplifier.output = 'wave'")
        return self

    # convenience -----------------------------------------------------------
    @property
    def dt_s(self) -> float:
        return self.loop.dt_s

    def limits(self, axis: str) -> tuple[float, float]:
        """Effective configured limits of ``axis`` [V]: amplifier ∩ safety."""
        a = self.amplifier.axis_limits(axis)
        lo, hi = a.min_V, a.max_V
        s = self.safety.limits_V.get(axis)  # type: ignore[call-overload]
        if s is not None:
            lo, hi = max(lo, s.min_V), min(hi, s.max_V)
        return lo, hi

    def slew_V_per_s(self) -> float:
        return min(self.amplifier.slew_V_per_s, self.safety.slew_V_per_s)


_TRAJ_KINDS = {"raster": RasterSpec, "moves": MovesSpec, "indentation": IndentationSpec, "text": TextSpec,
               "spiral": SpiralSpec, "file": FileSpec, "learned": LearnedSpec, "queue": QueueSpec}


def _model_of(annotation: Any) -> Any:
    """The BaseModel class of a field annotation (or of dict values), if any."""
    import typing
    origin = typing.get_origin(annotation)
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    if origin is dict:
        args = typing.get_args(annotation)
        inner = _model_of(args[1]) if len(args) == 2 else None
        return ("dict", inner) if inner is not None else None
    return None


def _fix_case(data: Any, model: Any) -> Any:
    if not isinstance(data, dict):
        return data
    if model is RasterSpec and "kind" in data:  # the trajectory union: pick by kind
        model = _TRAJ_KINDS.get(str(data.get("kind")), RasterSpec)
    fields = getattr(model, "model_fields", {})
    lower = {name.lower(): name for name in fields}
    out = {}
    for key, value in data.items():
        name = key if key in fields else lower.get(str(key).lower(), key)
        sub = fields.get(name)
        if sub is not None:
            if name == "trajectory":
                inner = RasterSpec
            else:
                inner = _model_of(sub.annotation)
            if isinstance(inner, tuple) and isinstance(value, dict):
                value = {k: _fix_case(v, inner[1]) for k, v in value.items()}
            elif inner is not None and not isinstance(inner, tuple):
                value = _fix_case(value, inner)
        out[name] = value
    return out


class _EnvCaseSource(PydanticBaseSettingsSource):
    """The environment source with key case restored: variables arrive lower-cased
    (``AFMCTL_LOOP__RATE_HZ`` → ``rate_hz``); keys are mapped back to the field names
    (``rate_Hz``). File keys are not touched (they must match exactly)."""

    def __init__(self, settings_cls: type[BaseSettings], inner: PydanticBaseSettingsSource) -> None:
        super().__init__(settings_cls)
        self.inner = inner

    def get_field_value(self, field: Any, field_name: str) -> tuple[Any, str, bool]:  # pragma: no cover
        return self.inner.get_field_value(field, field_name)

    def __call__(self) -> dict[str, Any]:
        return _fix_case(self.inner(), self.settings_cls)


def _field_info(model: Any, loc: tuple) -> Any:
    """The pydantic FieldInfo at ``loc`` below ``model`` (dict keys and union tags are
    stepped over), or None."""
    import typing
    info = None
    tp: Any = model
    for part in loc:
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            if not isinstance(part, str) or part not in tp.model_fields:
                continue        # a union tag such as 'raster'
            info = tp.model_fields[part]
            tp = info.annotation
            continue
        args = typing.get_args(tp)
        origin = typing.get_origin(tp)
        if origin is Annotated:
            tp = args[0]
            args = typing.get_args(tp)
            origin = typing.get_origin(tp)
        if origin is dict:
            tp = args[1]
            info = None
        elif origin is list and isinstance(part, int):
            tp = args[0]
            info = None
        elif args:              # a union: the member that has the next field
            members = [a for a in args if isinstance(a, type) and issubclass(a, BaseModel)]
            hit = [m for m in members if isinstance(part, str) and part in m.model_fields]
            tagged = [m for m in members if m.model_fields.get("kind") is not None
                      and m.model_fields["kind"].default == part]
            pick = tagged or hit
            if not pick:
                return None
            tp = pick[0]
            if not tagged:
                info = tp.model_fields[part]
                tp = info.annotation
        else:
            return None
    return info


def _allowed_range(model: Any, loc: tuple) -> str:
    """``allowed: 0 < value <= 1e+07`` from the field's numeric constraints ('' if none)."""
    info = _field_info(model, loc)
    if info is None:
        return ""
    lo = hi = ""
    for m in info.metadata:
        for attr, fmt in (("ge", "{} <= "), ("gt", "{} < ")):
            if getattr(m, attr, None) is not None:
                lo = fmt.format(f"{getattr(m, attr):g}")
        for attr, fmt in (("le", " <= {}"), ("lt", " < {}")):
            if getattr(m, attr, None) is not None:
                hi = fmt.format(f"{getattr(m, attr):g}")
    if not (lo or hi):
        return ""
    return f"allowed: {lo}value{hi}"


def _env_name(loc: tuple) -> str | None:
    """The AFMCTL_* environment variable that set ``loc``, if one did."""
    import os
    want = ("AFMCTL_" + "__".join(str(p) for p in loc)).upper()
    for name in os.environ:
        if name.upper() == want:
            return name
    return None


def format_validation_error(err: ValidationError, where: str = "config", model: Any = None,
                            prefix: str = "") -> str:
    """One line naming the first bad field, its value and the allowed range, e.g.
    ``cfg.toml: field loop.rate_Hz = 1e9: Input should be less than or equal to 20000
    (allowed: 0.1 <= value <= 20000)``. ``model``: the pydantic class validated (default
    :class:`Config`, whose values may come from an ``AFMCTL_*`` variable: then the
    variable is named instead of the file). ``prefix``: prepended to the field name (the
    section of ``model`` in the file, e.g. ``"loop."``)."""
    first, name = first_validation_error(err, prefix)
    loc = tuple(first["loc"])
    msg = first["msg"]
    env = _env_name(loc) if loc and model is None else None
    if env is not None:
        where = f"environment {env}"
    value = ""
    if first["type"] not in ("extra_forbidden", "missing") and not isinstance(first.get("input"), (dict, list)):
        value = f" = {plain_repr(first.get('input'))}"
    rng = _allowed_range(model if model is not None else Config, loc) if loc else ""
    if rng and first["type"] in ("greater_than", "greater_than_equal", "less_than", "less_than_equal",
                                 "float_parsing", "int_parsing", "float_type", "int_type", "finite_number",
                                 "int_from_float"):
        msg = f"{msg} ({rng})"
    extra = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
    return f"{where}: field {name}{value}: {msg}{extra}"


def _resolve_paths(cfg: Config, base: Path) -> Config:
    """Make relative file paths in the configuration relative to the file's directory: every
    path field of the schema (``runlog.dir`` with its default ``runs`` too; the trajectory's
    ``path`` or ``file``; ``compensation.drift.params`` when it names a JSON file), absolute
    paths as they are."""
    def fix(p: Path | None) -> Path | None:
        return p if p is None or p.is_absolute() else base / p
    for ax in AXES:
        c = cfg.compensation.axis(ax)
        c.model = fix(c.model)
    cfg.compensation.scanner_model = fix(cfg.compensation.scanner_model)
    t = cfg.compensation.temperature
    t.file = fix(t.file)
    if isinstance(cfg.trajectory, FileSpec):
        cfg.trajectory.path = fix(cfg.trajectory.path)  # type: ignore[assignment]
    if isinstance(cfg.trajectory, LearnedSpec):
        cfg.trajectory.file = fix(cfg.trajectory.file)  # type: ignore[assignment]
    cfg.runlog.dir = fix(cfg.runlog.dir)  # type: ignore[assignment]
    cfg.simulation.scanner = fix(cfg.simulation.scanner)
    d = cfg.compensation.drift
    if d.params.endswith(".json") and not Path(d.params).is_absolute():
        d.params = str(base / d.params)
    z = cfg.zenoh
    z.tls.root_ca = fix(z.tls.root_ca)
    z.tls.certificate = fix(z.tls.certificate)
    z.tls.private_key = fix(z.tls.private_key)
    z.auth.dictionary_file = fix(z.auth.dictionary_file)
    return cfg


def config_from_dict(data: dict[str, Any], where: str = "config", base: Path | None = None) -> Config:
    """Validate a decoded configuration (environment overrides applied)."""
    try:
        cfg = Config(**data)
    except ValidationError as err:
        raise AfmctlError(format_validation_error(err, where)) from None
    if base is not None:
        cfg = _resolve_paths(cfg, base)
    return cfg


def _deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def parse_toml(text: str, where: str) -> dict[str, Any]:
    """TOML ``text``; one-line :class:`AfmctlError` naming ``where`` when it cannot be decoded
    (:func:`afmctl.compensators.textfiles.decode_text`)."""
    return decode_text(text, "TOML", where, AfmctlError)


def load_config(path: str | Path | None = None, *, text: str | None = None,
                overrides: dict[str, Any] | None = None) -> Config:
    """Read a TOML configuration file (or ``text``), merge ``overrides`` (nested dict, e.g.
    from command-line options; they beat the environment too) and apply ``AFMCTL_*``
    environment overrides."""
    if text is None and path is None:
        return config_from_dict({}, "defaults")
    where = str(path) if path is not None else "config"
    if text is None:
        p = Path(path)  # type: ignore[arg-type]
        text = read_text_file(p, "configuration", AfmctlError)
        base = p.resolve().parent
    else:
        base = Path.cwd()
    data = parse_toml(text, where)
    cfg = config_from_dict(_deep_merge(data, overrides or {}), where, base)
    if overrides:  # command line beats the environment as well: re-validate those sections
        try:
            for key, value in overrides.items():
                section = getattr(cfg, key)
                merged = _deep_merge(section.model_dump(), value) if isinstance(value, dict) else value
                setattr(cfg, key, type(section).model_validate(merged))
            cfg._cross()
        except ValidationError as err:
            raise AfmctlError(format_validation_error(err, where, type(section), f"{key}.")) from None
        except ValueError as err:
            raise AfmctlError(f"{where}: {err}") from None
    return cfg


def json_schema() -> dict[str, Any]:
    """The JSON schema of :class:`Config` (``afmctl schema``)."""
    return Config.model_json_schema()
