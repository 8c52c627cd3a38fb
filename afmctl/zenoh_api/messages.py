"""Payload schemas of the zenoh API (documented for users in docs/ZENOH.md).

Every message carries ``schema`` (the version of these schemas, :data:`SCHEMA_VERSION`)
and ``seq`` (a per-sender, per-key sequence number starting at 0 and incremented by one
per message), so a receiver can see a gap or a sender that speaks another version.

* control messages (trajectory, temperature, cmd, status, drift) are UTF-8 JSON objects,
  validated by the pydantic models below;
* setpoint batches (high rate) use a compact binary layout: a 32-byte little-endian header
  followed by ``n`` fixed-size little-endian records (:data:`SETPOINT_DTYPE`)::

      offset size  field
      0      4     magic  b"AFMS"
      4      2     schema        uint16   (= SCHEMA_VERSION)
      6      2     header_bytes  uint16   (= 32; records start here)
      8      8     seq           uint64   batch sequence number (per publisher, +1 per batch)
      16     8     first_sample  uint64   sample sequence number of record 0
      24     4     n             uint32   number of records
      28     4     record_bytes  uint32   (= 88)
      32     n*88  records: seq uint64, t_s float64, target_nm 3*float64,
                   corrected_nm 3*float64, u_V 3*float64   (axes x, y, z)

Decoding never trusts the sender: sizes, versions, finiteness and ranges are checked and
a :class:`MessageError` names the field and the allowed range.
"""
from __future__ import annotations

import json
import math
import struct
from typing import Annotated, Any, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from afmctl.compensators.errortext import first_validation_error
from afmctl.compensators.temperature import T_MAX_C, T_MIN_C

from ..errors import AfmctlError

#: version of every payload schema in this module
SCHEMA_VERSION = 1

#: absolute bound on any position in a message [nm] (1 mm; the controller's safety layer
#: applies the real, tighter voltage limits)
POSITION_LIMIT_NM = 1.0e6
#: sample period bounds [s]
DT_MIN_S, DT_MAX_S = 1.0e-6, 1.0
#: accepted ambient temperatures [°C]
#: default cap on samples one trajectory message may carry or generate
MAX_SEGMENT_SAMPLES = 1_000_000

#: one setpoint record (little-endian, packed: 88 bytes)
SETPOINT_DTYPE = np.dtype([
    ("seq", "<u8"),
    ("t_s", "<f8"),
    ("target_nm", "<f8", (3,)),
    ("corrected_nm", "<f8", (3,)),
    ("u_V", "<f8", (3,)),
])
SETPOINT_MAGIC = b"AFMS"
_HEADER = struct.Struct("<4sHHQQII")
SETPOINT_HEADER_BYTES = _HEADER.size  # 32


class MessageError(AfmctlError):
    """A received payload was rejected; the message names the field and the allowed range."""


# --------------------------------------------------------------------------- helpers
_Position = Annotated[float, Field(ge=-POSITION_LIMIT_NM, le=POSITION_LIMIT_NM, allow_inf_nan=False)]
_Vec3 = Annotated[list[_Position], Field(min_length=3, max_length=3)]


class _Message(BaseModel):
    schema_: Literal[1] = Field(SCHEMA_VERSION, alias="schema",
                                description="payload schema version (this service speaks 1)")
    seq: int = Field(..., ge=0, lt=2**63, description="sender's message sequence number")

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    def to_json_bytes(self) -> bytes:
        return json.dumps(self.model_dump(mode="json", by_alias=True), separators=(",", ":"),
                          allow_nan=False).encode()


# --------------------------------------------------------------------------- trajectory
class SegmentMsg(_Message):
    """Explicit target positions sampled every ``dt_s`` seconds, rows ``[x, y, z]`` in nm."""

    type: Literal["segment"] = "segment"
    dt_s: float = Field(..., ge=DT_MIN_S, le=DT_MAX_S, allow_inf_nan=False)
    positions_nm: list[_Vec3] = Field(..., min_length=1)

    def positions(self, max_samples: int = MAX_SEGMENT_SAMPLES) -> np.ndarray:
        if len(self.positions_nm) > max_samples:
            raise MessageError(f"positions_nm: {len(self.positions_nm)} samples; allowed 1..{max_samples}")
        return np.asarray(self.positions_nm, dtype=np.float64).reshape(-1, 3)


class LineMsg(_Message):
    """A straight move from ``from_nm`` to ``to_nm`` at constant speed over ``duration_s``."""

    type: Literal["line"] = "line"
    dt_s: float = Field(..., ge=DT_MIN_S, le=DT_MAX_S, allow_inf_nan=False)
    from_nm: _Vec3
    to_nm: _Vec3
    duration_s: float = Field(..., gt=0.0, le=3600.0, allow_inf_nan=False)

    def positions(self, max_samples: int = MAX_SEGMENT_SAMPLES) -> np.ndarray:
        n = _count(self.duration_s / self.dt_s, max_samples, "duration_s/dt_s")
        s = np.arange(1, n + 1, dtype=np.float64) / n
        a, b = np.asarray(self.from_nm), np.asarray(self.to_nm)
        return a[None, :] + s[:, None] * (b - a)[None, :]


class RasterMsg(_Message):
    """A raster scan: ``lines`` lines of ``points_per_line`` points (trace then retrace).

    Fast axis x, slow axis y, centred on ``center_nm``; each line (trace + retrace) takes
    ``1/line_rate_hz`` seconds, sampled every ``dt_s``.
    """

    type: Literal["raster"] = "raster"
    dt_s: float = Field(..., ge=DT_MIN_S, le=DT_MAX_S, allow_inf_nan=False)
    center_nm: _Vec3
    size_nm: Annotated[list[Annotated[float, Field(ge=0.0, le=2 * POSITION_LIMIT_NM, allow_inf_nan=False)]],
                       Field(min_length=2, max_length=2)]
    lines: int = Field(..., ge=1, le=65536)
    line_rate_hz: float = Field(..., gt=0.0, le=1.0e4, allow_inf_nan=False)

    def positions(self, max_samples: int = MAX_SEGMENT_SAMPLES) -> np.ndarray:
        per_line = _count(1.0 / (self.line_rate_hz * self.dt_s), max_samples, "1/(line_rate_hz*dt_s)")
        total = _count(per_line * self.lines, max_samples, "lines*samples per line")
        half = max(per_line // 2, 1)
        w, h = self.size_nm
        cx, cy, cz = self.center_nm
        for name, c, size in (("x", cx, w), ("y", cy, h)):
            if abs(c) + size / 2 > POSITION_LIMIT_NM:
                raise MessageError(f"center_nm/size_nm: {name} reaches beyond ±{POSITION_LIMIT_NM:g} nm")
        ramp = np.concatenate([np.linspace(-0.5, 0.5, half), np.linspace(0.5, -0.5, per_line - half)])
        x = np.tile(ramp, self.lines) * w + cx
        line_idx = np.repeat(np.arange(self.lines), per_line)
        y = (line_idx / max(self.lines - 1, 1) - 0.5) * h + cy if self.lines > 1 else np.full(total, cy)
        return np.column_stack([x, y, np.full(total, cz)])


TrajectoryMsg = Annotated[Union[SegmentMsg, LineMsg, RasterMsg], Field(discriminator="type")]
_TRAJECTORY = TypeAdapter(TrajectoryMsg)


def _count(value: float, max_samples: int, what: str) -> int:
    if not math.isfinite(value) or value < 1 or value > max_samples:
        raise MessageError(f"{what}: gives {value:.6g} samples; allowed 1..{max_samples}")
    return int(round(value))


# --------------------------------------------------------------------------- temperature
class TemperatureMsg(_Message):
    """One ambient temperature reading [°C] at time ``t_s`` (the sender's clock, s)."""

    t_s: float = Field(..., ge=0.0, le=1.0e10, allow_inf_nan=False)
    T_C: float = Field(..., ge=T_MIN_C, le=T_MAX_C, allow_inf_nan=False)


# --------------------------------------------------------------------------- cmd
CMD_NAMES = ("start", "stop", "estop", "status", "config", "drift-measurement")


class CmdRequest(_Message):
    """The payload of a query on ``cmd`` (or ``?cmd=NAME`` in the selector)."""

    cmd: Literal["start", "stop", "estop", "status", "config", "drift-measurement"]
    args: dict[str, Any] = Field(default_factory=dict)
    seq: int = Field(0, ge=0, lt=2**63)


class DriftMeasurementArgs(BaseModel):
    """``args`` of the ``drift-measurement`` command: a measured drift [nm] per axis x, y, z
    (``null`` = axis not measured), its 1-sigma [nm] and optionally the controller time
    [s] it refers to (default: when it arrives)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    measured_drift_nm: list[Annotated[float, Field(ge=-1e6, le=1e6, allow_inf_nan=False)] | None] = Field(
        ..., min_length=3, max_length=3)
    std_nm: float = Field(..., ge=1e-6, le=1e6, allow_inf_nan=False)
    t_s: float | None = Field(None, ge=0.0, le=1e7, allow_inf_nan=False)

    def measured_nm(self) -> list[float]:
        """The measurement with NaN for axes not measured."""
        return [math.nan if v is None else float(v) for v in self.measured_drift_nm]


def drift_measurement_args(args: Any) -> DriftMeasurementArgs:
    """Validate the ``args`` of a ``drift-measurement`` command (MessageError naming the field)."""
    try:
        return DriftMeasurementArgs.model_validate(args)
    except ValidationError as err:
        raise MessageError("field args." + _validation_message(err)[len("field "):]) from None


class CmdReply(_Message):
    cmd: str
    ok: bool
    result: dict[str, Any] = Field(default_factory=dict)
    error: str | None = None


# --------------------------------------------------------------------------- published
class ErrorInfo(BaseModel):
    model_config = ConfigDict(extra="forbid")

    t_s: float = Field(..., description="wall-clock time of the error (Unix s)")
    source: str = Field(..., description="key or component the error came from")
    message: str


class StatusMsg(_Message):
    """Service state, loop statistics (lateness in s, counts) and recent errors."""

    scanner: str
    t_s: float = Field(..., description="wall-clock time (Unix s)")
    state: str
    stats: dict[str, Any] = Field(default_factory=dict)
    errors: list[ErrorInfo] = Field(default_factory=list)
    rejected: int = Field(0, ge=0, description="messages rejected since start")


class DriftMsg(_Message):
    """Drift estimate [nm] per axis x, y, z, its 1-sigma uncertainty and its inputs."""

    t_s: float
    drift_nm: list[float] = Field(..., min_length=3, max_length=3)
    std_nm: list[float] | None = Field(None, min_length=3, max_length=3)
    T_C: float | None = None
    inputs: dict[str, Any] = Field(default_factory=dict)


class LearnMsg(_Message):
    """One iteration of ``afmctl learn`` (``<prefix>/<scanner>/learn``): the tracking error of
    the table just played, measured by the device's recorder, in % of the scan range —
    over the whole table and over the central part of each line an AFM images — and what
    the learning did next."""

    t_s: float = Field(..., allow_inf_nan=False, description="wall-clock time (Unix s)")
    iteration: int = Field(..., ge=0, le=1_000_000, description="0: the model's table, before any learning")
    max_pct: float = Field(..., ge=0, allow_inf_nan=False, description="max |error| over the table [% of range]")
    rms_pct: float = Field(..., ge=0, allow_inf_nan=False, description="RMS error over the table [% of range]")
    central_max_pct: float | None = Field(None, ge=0, allow_inf_nan=False,
                                          description="max |error| over the central part of each line [% of range]")
    central_rms_pct: float | None = Field(None, ge=0, allow_inf_nan=False,
                                          description="RMS error over the central part of each line [% of range]")
    step: float | None = Field(None, ge=0, allow_inf_nan=False, description="learning gain used for the next table")
    state: Literal["learning", "converged", "stopped", "diverged", "fault"] = "learning"
    detail: str = Field("", max_length=500, description="why learning ended, or what changed")


class SimTipMsg(_Message):
    """True tip position from the simulator (``<prefix>/<scanner>/sim/tip``)."""

    t_s: float
    position_nm: list[float] = Field(..., min_length=3, max_length=3)


class SimImageMsg(_Message):
    """One pixel of the simulator's image (``<prefix>/<scanner>/sim/image``): the sample
    height [nm] under the true tip position [nm] at plant time ``t_s`` [s] (an ideal z
    feedback keeps the tip on the surface), and the sample's name."""

    t_s: float = Field(..., allow_inf_nan=False)
    position_nm: _Vec3
    height_nm: float = Field(..., ge=-POSITION_LIMIT_NM, le=POSITION_LIMIT_NM, allow_inf_nan=False)
    sample: str = Field("", max_length=100)


# --------------------------------------------------------------------------- decoding
def _loads(payload: bytes, max_bytes: int) -> Any:
    if len(payload) > max_bytes:
        raise MessageError(f"payload: {len(payload)} bytes; allowed at most {max_bytes}")
    try:
        return json.loads(payload.decode("utf-8"))
    except UnicodeDecodeError:
        raise MessageError("payload: not UTF-8 text (expected a JSON object)") from None
    except (json.JSONDecodeError, RecursionError) as err:
        raise MessageError(f"payload: not valid JSON ({getattr(err, 'msg', 'too deeply nested')})") from None
    except ValueError:  # e.g. an integer of more than 4300 digits
        raise MessageError("payload: a number in it is too long (at most 4300 digits)") from None


def _validation_message(err: ValidationError) -> str:
    first, loc = first_validation_error(err, skip=("segment", "line", "raster"))
    msg = first["msg"]
    if loc == "schema":
        msg = f"{msg} (this service speaks schema {SCHEMA_VERSION})"
    return f"field {loc}: {msg}"


def _check_header(data: Any) -> None:
    if not isinstance(data, dict):
        raise MessageError("payload: expected a JSON object with 'schema' and 'seq'")
    if "schema" not in data:
        raise MessageError(f"field schema: missing (this service speaks schema {SCHEMA_VERSION})")
    if data["schema"] != SCHEMA_VERSION or isinstance(data["schema"], bool):
        raise MessageError(f"field schema: version {data['schema']!r} not supported; allowed: {SCHEMA_VERSION}")


def decode_trajectory(payload: bytes, max_bytes: int = 64 * 1024 * 1024) -> SegmentMsg | LineMsg | RasterMsg:
    """Validate a ``trajectory`` payload (JSON) into one of the trajectory messages."""
    data = _loads(payload, max_bytes)
    _check_header(data)
    if data.get("type") not in ("segment", "line", "raster"):
        raise MessageError(f"field type: {data.get('type')!r}; allowed: segment, line, raster")
    try:
        return _TRAJECTORY.validate_python(data)
    except ValidationError as err:
        raise MessageError(_validation_message(err)) from None


def decode_json(payload: bytes, cls: type[_Message], max_bytes: int = 1024 * 1024) -> Any:
    """Validate a JSON payload into ``cls`` (temperature, cmd, status, drift ...)."""
    data = _loads(payload, max_bytes)
    _check_header(data)
    try:
        return cls.model_validate(data)
    except ValidationError as err:
        raise MessageError(_validation_message(err)) from None


# --------------------------------------------------------------------------- setpoints
def as_setpoint_records(batch: np.ndarray) -> np.ndarray:
    """Copy any structured array with the setpoint fields into :data:`SETPOINT_DTYPE`."""
    if batch.dtype == SETPOINT_DTYPE:
        return np.ascontiguousarray(batch)
    out = np.empty(len(batch), dtype=SETPOINT_DTYPE)
    for name in SETPOINT_DTYPE.names:
        out[name] = batch[name]
    return out


def encode_setpoints(seq: int, batch: np.ndarray) -> bytes:
    """The binary setpoint-batch payload (layout in the module docstring)."""
    rec = as_setpoint_records(batch)
    first = int(rec["seq"][0]) if len(rec) else 0
    header = _HEADER.pack(SETPOINT_MAGIC, SCHEMA_VERSION, SETPOINT_HEADER_BYTES, seq, first,
                          len(rec), SETPOINT_DTYPE.itemsize)
    return header + rec.tobytes()


def decode_setpoints(payload: bytes) -> tuple[int, np.ndarray]:
    """``(batch seq, records)`` from a setpoint-batch payload; :class:`MessageError` if bad."""
    if len(payload) < SETPOINT_HEADER_BYTES:
        raise MessageError(f"setpoint payload: {len(payload)} bytes; the header alone is {SETPOINT_HEADER_BYTES}")
    magic, schema, hbytes, seq, first, n, rbytes = _HEADER.unpack_from(payload)
    if magic != SETPOINT_MAGIC:
        raise MessageError(f"setpoint payload: magic {magic!r}; expected {SETPOINT_MAGIC!r}")
    if schema != SCHEMA_VERSION:
        raise MessageError(f"field schema: version {schema} not supported; allowed: {SCHEMA_VERSION}")
    if hbytes < SETPOINT_HEADER_BYTES or rbytes != SETPOINT_DTYPE.itemsize:
        raise MessageError(f"setpoint payload: header_bytes {hbytes}/record_bytes {rbytes}; "
                           f"expected >= {SETPOINT_HEADER_BYTES}/{SETPOINT_DTYPE.itemsize}")
    if len(payload) != hbytes + n * rbytes:
        raise MessageError(f"setpoint payload: {len(payload)} bytes; header says {hbytes + n * rbytes}")
    rec = np.frombuffer(payload, dtype=SETPOINT_DTYPE, count=n, offset=hbytes).copy()
    if n and int(rec["seq"][0]) != first:
        raise MessageError("setpoint payload: first_sample does not match record 0")
    return seq, rec
