"""Sans-I/O codec for afmctl's CAN amplifier frames, defined in ``afm_amplifier.dbc``
(package data of :mod:`afmctl.drivers`, found through :mod:`importlib.resources`) and
encoded/decoded through cantools. Frame ids and scales are read from the DBC by message
and signal name (:func:`frame_id`, :func:`volts_per_bit`); nothing here repeats them.

Frames (all little-endian, see docs/DRIVERS.md):

==============  =======  ==========================================================
frame           sender   signals
==============  =======  ==========================================================
SETPOINT_XYZ    host     X_V, Y_V, Z_V (16 bit voltages), SEQ, FLAGS
HEARTBEAT       host     COUNTER, REQ_STATE (0 keep/1 enable/2 disable), REQ_STATUS, REQ_INFO
STATUS          amp      applied X_V, Y_V, Z_V, LAST_SEQ, STATE, ERROR_CODE
ERROR           amp      CODE, DETAIL, SEQ
LIMITS          amp      MIN_V, X_MAX_V, Y_MAX_V, Z_MAX_V
STREAM_CTRL     host     CMD (0 status/1 start/2 flush/3 drain), RATE_HZ, PREFILL
STREAM_XYZ      host     X_V, Y_V, Z_V, SEQ (16 bit) — one sample for the stream FIFO
STREAM_XYZ_FD   host     SEQ, COUNT, X0_V .. Z9_V — CAN FD (64 bytes): up to 10 samples
STREAM_STATUS   amp      LEVEL, UNDERRUNS, PLAYED_SEQ, STREAM_STATE, CAPACITY_LOG2, OVERFLOWS
REC_CTRL        host     CMD (0 status/1 arm/2 stop), AXES, SIGNALS (bit masks), DIVIDER, POINTS
REC_READ        host     FIRST, COUNT — send those recorded points back
REC_STATUS      amp      REC_STATE, AXES, SIGNALS, COUNT (recorded), CAPACITY, DIVIDER
REC_DATA        amp      INDEX, AXIS, Y_NM (24 bit signed, 0.01 nm), U_V — one recorded point
REC_DATA_V      amp      INDEX, AXIS, V_V — that point's piezo voltage (output stage monitor)
REC_READ_FD     host     FIRST, COUNT — the same points back as REC_DATA_FD (a CAN FD bus)
REC_DATA_FD     amp      INDEX, AXIS, COUNT, Y0_NM, U0_V, V0_V .. Y7_NM, U7_V, V7_V — CAN FD
                         (64 bytes): up to 8 consecutive recorded points of one axis
==============  =======  ==========================================================

Buffered stream (device-timed output): the host sends STREAM_CTRL start with the rate,
then STREAM_XYZ samples; the amplifier plays sample k at t0 + k / RATE_HZ on its own
clock (t0 = arrival of the sample that makes the FIFO hold PREFILL samples) and counts an underrun for every tick with an empty FIFO
(the output then holds). STREAM_CTRL flush empties the FIFO at once (estop).
"""
from __future__ import annotations

import functools
import math
import struct
from collections.abc import Mapping, Sequence
from importlib import resources

from .errors import LimitError, ProtocolError, RecordingOverwritten

DBC_RESOURCE = "afm_amplifier.dbc"
SETPOINT, HEARTBEAT, STATUS, ERROR, LIMITS = "SETPOINT_XYZ", "HEARTBEAT", "STATUS", "ERROR", "LIMITS"
STREAM_CTRL, STREAM_SAMPLE, STREAM_STATUS = "STREAM_CTRL", "STREAM_XYZ", "STREAM_STATUS"
STREAM_SAMPLE_FD = "STREAM_XYZ_FD"
REC_CTRL, REC_READ, REC_STATUS, REC_DATA = "REC_CTRL", "REC_READ", "REC_STATUS", "REC_DATA"
REC_DATA_V = "REC_DATA_V"
REC_READ_FD, REC_DATA_FD = "REC_READ_FD", "REC_DATA_FD"
#: recorded points one REC_DATA_FD frame carries (CAN FD, 64 data bytes)
FD_REC_POINTS = 8
REC_CMD_STATUS, REC_CMD_ARM, REC_CMD_STOP = 0, 1, 2
REC_STATES = {0: "idle", 1: "armed", 2: "recording", 3: "done", 4: "fault"}
#: SIGNALS bits of REC_CTRL / REC_STATUS
REC_SIGNAL_BITS = {"y_nm": 1, "u_V": 2, "v_V": 4}
CMD_STATUS, CMD_START, CMD_FLUSH, CMD_DRAIN = 0, 1, 2, 3
STREAM_STATES = {0: "idle", 1: "armed", 2: "playing", 3: "draining", 4: "fault"}
FLAG_REQ_STATUS = 0x01
ERRORS = {1: "value outside the amplifier range", 2: "sequence gap (setpoints lost or reordered)",
          3: "outputs disabled", 4: "hardware fault", 5: "stream FIFO overflow",
          6: "recorder request refused (detail 1 points, 2 divider, 3 axes/signals, 4 read past the recording, "
             "5 points overwritten: read back too late)"}
STATES = {0: "disabled", 1: "enabled", 2: "fault"}


@functools.lru_cache(maxsize=1)
def database():
    """The cantools database of ``afm_amplifier.dbc`` (loaded on first use)."""
    import cantools
    text = resources.files(__package__).joinpath(DBC_RESOURCE).read_text(encoding="utf-8")
    return cantools.database.load_string(text, database_format="dbc")


@functools.lru_cache(maxsize=16)
def message(name_or_id: str | int):
    """The DBC message named ``name_or_id`` (or with that frame id); KeyError if none."""
    db = database()
    if isinstance(name_or_id, str):
        return db.get_message_by_name(name_or_id)
    return db.get_message_by_frame_id(name_or_id)


@functools.lru_cache(maxsize=16)
def frame_id(name: str) -> int:
    """Frame id of the DBC message ``name`` (e.g. ``frame_id("STATUS")``)."""
    return int(message(name).frame_id)


@functools.lru_cache(maxsize=1)
def volts_per_bit() -> float:
    """Scale of the setpoint voltage signals [V per bit], from the DBC."""
    return float(message(SETPOINT).get_signal_by_name("X_V").scale)


def quantize_inside(value_V: float, lo_V: float, hi_V: float) -> float:
    """The nearest multiple of the DBC's voltage step (0.0025 V) inside [lo_V, hi_V]
    (never rounds across a limit)."""
    step_V = volts_per_bit()
    if lo_V <= value_V <= hi_V:          # the usual case (NaN is not): a step inside
        v = round(value_V / step_V) * step_V
        if lo_V <= v <= hi_V:
            return v
    if not math.isfinite(value_V):
        raise LimitError(f"{value_V!r} V is not a finite voltage")
    value_V = min(max(value_V, lo_V), hi_V)  # also keeps huge values from overflowing
    raw = round(value_V / step_V)
    if raw * step_V > hi_V:
        raw = math.floor(hi_V / step_V)
        while raw * step_V > hi_V:
            raw -= 1
    if raw * step_V < lo_V:
        raw = math.ceil(lo_V / step_V)
        while raw * step_V < lo_V:
            raw += 1
    v = raw * step_V
    if not lo_V <= v <= hi_V:
        raise LimitError(f"no {step_V:g} V step lies in [{lo_V:g}, {hi_V:g}] V")
    return v


@functools.lru_cache(maxsize=1)
def setpoint_range_V() -> tuple[float, float]:
    """The voltage range the DBC declares for the SETPOINT_XYZ signals [V]."""
    sig = message(SETPOINT).get_signal_by_name("X_V")
    return float(sig.minimum), float(sig.maximum)


def encode_setpoint(values_V: Sequence[float], seq: int, lows_V: Sequence[float], highs_V: Sequence[float],
                    flags: int = 0) -> bytes:
    """8 data bytes of SETPOINT_XYZ; each value as sent lies in its [low, high] [V] and in
    the range the DBC declares (checked here once, then cantools encodes without its
    slower per-call range check)."""
    x, y, z = (quantize_inside(v, lo, hi) for v, lo, hi in zip(values_V, lows_V, highs_V))
    lo, hi = setpoint_range_V()
    if not (lo <= x <= hi and lo <= y <= hi and lo <= z <= hi):
        raise LimitError(f"setpoint ({x}, {y}, {z}) V does not fit the CAN frame's range [{lo:g}, {hi:g}] V")
    return message(SETPOINT).encode({"X_V": x, "Y_V": y, "Z_V": z, "SEQ": seq & 0xFF, "FLAGS": flags & 0xFF},
                                       strict=False)


def encode_stream_sample(values_V: Sequence[float], seq: int, lows_V: Sequence[float],
                         highs_V: Sequence[float]) -> bytes:
    """8 data bytes of STREAM_XYZ (one FIFO sample, SEQ mod 65536); each value [V] as sent
    lies in its [low, high] and in the DBC's range, as for :func:`encode_setpoint`."""
    x, y, z = (quantize_inside(v, lo, hi) for v, lo, hi in zip(values_V, lows_V, highs_V))
    lo, hi = setpoint_range_V()
    if not (lo <= x <= hi and lo <= y <= hi and lo <= z <= hi):
        raise LimitError(f"sample ({x}, {y}, {z}) V does not fit the CAN frame's range [{lo:g}, {hi:g}] V")
    return message(STREAM_SAMPLE).encode({"X_V": x, "Y_V": y, "Z_V": z, "SEQ": seq & 0xFFFF}, strict=False)


#: samples one STREAM_XYZ_FD frame carries (CAN FD, 64 data bytes)
FD_SAMPLES = 10


def encode_stream_block(rows_V: Sequence[Sequence[float]], seq: int, lows_V: Sequence[float],
                        highs_V: Sequence[float]) -> bytes:
    """64 data bytes of STREAM_XYZ_FD (CAN FD): 1..:data:`FD_SAMPLES` consecutive samples
    (rows x, y, z [V]), the first with ``seq`` (mod 65536); each value as sent lies in its
    [low, high] and in the DBC's range, as for :func:`encode_stream_sample`; unused slots 0.
    Packed by :func:`stream_block_struct` (the DBC's layout; the same bytes as cantools,
    tests/test_can_stream.py), or by cantools where the DBC lays the frame out otherwise."""
    n = len(rows_V)
    if not 1 <= n <= FD_SAMPLES:
        raise ProtocolError(f"STREAM_XYZ_FD: {n} samples; one frame carries 1..{FD_SAMPLES}")
    lo, hi = setpoint_range_V()
    values: list[float] = []
    for k in range(n):
        x, y, z = (quantize_inside(v, a, b) for v, a, b in zip(rows_V[k], lows_V, highs_V))
        if not (lo <= x <= hi and lo <= y <= hi and lo <= z <= hi):
            raise LimitError(f"sample ({x}, {y}, {z}) V does not fit the CAN frame's range [{lo:g}, {hi:g}] V")
        values += (x, y, z)
    packer = stream_block_struct()
    if packer is not None:
        step_V = volts_per_bit()
        return packer.pack(seq & 0xFFFF, n, *(round(v / step_V) for v in values), *((0,) * (3 * (FD_SAMPLES - n))))
    sig: dict[str, float] = {"SEQ": seq & 0xFFFF, "COUNT": n}
    for k in range(FD_SAMPLES):
        x, y, z = values[3 * k:3 * k + 3] if k < n else (0.0, 0.0, 0.0)
        sig[f"X{k}_V"], sig[f"Y{k}_V"], sig[f"Z{k}_V"] = x, y, z
    return message(STREAM_SAMPLE_FD).encode(sig, strict=False)


@functools.lru_cache(maxsize=1)
def stream_block_struct() -> struct.Struct | None:
    """STREAM_XYZ_FD as a :class:`struct.Struct` of SEQ, COUNT, X0_V, Y0_V, Z0_V .. Z9_V (raw
    counts), read from the DBC: when it lays them out one after another from bit 0, each
    little-endian, unsigned, 8 or 16 bits, without offset, the frame padded with zeros
    (0.6 µs a frame against cantools' 16.5 µs, 2026-11-29: a 10 kHz stream sends 1,000 such
    frames a second); None otherwise (cantools encodes)."""
    msg = message(STREAM_SAMPLE_FD)
    names = ["SEQ", "COUNT"] + [f"{a}{k}_V" for k in range(FD_SAMPLES) for a in "XYZ"]
    codes, fmt, bit = {8: "B", 16: "H"}, "<", 0
    for name in names:
        sig = msg.get_signal_by_name(name)
        if (sig.start != bit or sig.byte_order != "little_endian" or sig.is_signed or sig.length not in codes
                or sig.offset != 0):
            return None
        fmt += codes[sig.length]
        bit += sig.length
    pad = int(msg.length) - bit // 8
    return struct.Struct(fmt + f"{pad}x") if bit % 8 == 0 and pad >= 0 else None


def decode_stream_block(data: bytes) -> tuple[int, list[tuple[float, float, float]]]:
    """STREAM_XYZ_FD data → (SEQ of the first sample, its COUNT samples x, y, z [V]);
    a wrong length or a COUNT outside 1..:data:`FD_SAMPLES` → ProtocolError."""
    sig = decode(STREAM_SAMPLE_FD, data)
    n = int(sig["COUNT"])
    if not 1 <= n <= FD_SAMPLES:
        raise ProtocolError(f"STREAM_XYZ_FD: COUNT {n}, expected 1..{FD_SAMPLES}", data=bytes(data))
    return int(sig["SEQ"]), [(float(sig[f"X{k}_V"]), float(sig[f"Y{k}_V"]), float(sig[f"Z{k}_V"]))
                             for k in range(n)]


def encode_stream_ctrl(cmd: int, rate_Hz: float = 0.0, prefill: int = 1) -> bytes:
    """6 data bytes of STREAM_CTRL: ``cmd`` one of CMD_STATUS/START/FLUSH/DRAIN; ``rate_Hz``
    the play rate for CMD_START (a whole number of Hz, 1..1 000 000); ``prefill`` the samples
    to queue before the amplifier's clock starts (1..65535)."""
    if not (isinstance(prefill, int) and 1 <= prefill <= 0xFFFF):
        raise LimitError(f"stream prefill {prefill!r}: a whole number of samples in 1..65535")
    if cmd not in (CMD_STATUS, CMD_START, CMD_FLUSH, CMD_DRAIN):
        raise ProtocolError(f"STREAM_CTRL: unknown command {cmd!r} (0..3)")
    rate = round(float(rate_Hz)) if math.isfinite(rate_Hz) else -1
    if cmd == CMD_START and not (1 <= rate <= 1_000_000 and rate == float(rate_Hz)):
        raise LimitError(f"stream rate {rate_Hz!r} Hz: a whole number of Hz in 1..1000000")
    return message(STREAM_CTRL).encode({"CMD": cmd, "RATE_HZ": rate if cmd == CMD_START else 0,
                                        "PREFILL": prefill if cmd == CMD_START else 0})


def encode_heartbeat(counter: int, req_state: int = 0, req_status: bool = False, req_info: bool = False) -> bytes:
    return message(HEARTBEAT).encode({"COUNTER": counter & 0xFF, "REQ_STATE": req_state,
                                         "REQ_STATUS": int(req_status), "REQ_INFO": int(req_info)})


def decode(name_or_id: str | int, data: bytes) -> dict[str, float]:
    """Any frame of the DBC (by message name or frame id) → its signals; wrong length or
    unknown id → ProtocolError."""
    try:
        msg = message(name_or_id)
    except KeyError:
        what = f"0x{name_or_id:X}" if isinstance(name_or_id, int) else repr(name_or_id)
        raise ProtocolError(f"unknown CAN frame {what}", data=bytes(data)) from None
    if len(data) != msg.length:
        raise ProtocolError(f"{msg.name}: {len(data)} data bytes, expected {msg.length}", data=bytes(data))
    try:
        return dict(msg.decode(bytes(data), decode_choices=False, scaling=True))
    except Exception as err:
        raise ProtocolError(f"{msg.name}: cannot decode ({err})", data=bytes(data)) from None


def error_from(signals: Mapping[str, float], data: bytes = b"") -> ProtocolError:
    code, detail = int(signals["CODE"]), int(signals["DETAIL"])
    kind = RecordingOverwritten if (code, detail) == (6, 5) else ProtocolError
    return kind(f"CAN amplifier error (setpoint SEQ {int(signals['SEQ'])}, detail {detail})",
                code=code, text=ERRORS.get(code, "unknown error"), data=bytes(data) or None)


def encode_rec_ctrl(cmd: int, axes_mask: int = 0, signals: int = 0, points: int = 0, divider: int = 0) -> bytes:
    """8 data bytes of REC_CTRL (``cmd`` one of REC_CMD_STATUS/ARM/STOP); points and divider
    1..65535 for an arm."""
    if cmd == REC_CMD_ARM and not (1 <= points <= 0xFFFF and 1 <= divider <= 0xFFFF):
        raise LimitError(f"recorder: points {points!r} and divider {divider!r} must be whole numbers 1..65535")
    return message(REC_CTRL).encode({"CMD": cmd, "AXES": axes_mask, "SIGNALS": signals,
                                     "POINTS": points if cmd == REC_CMD_ARM else 0,
                                     "DIVIDER": divider if cmd == REC_CMD_ARM else 0})


def encode_rec_read(first: int, count: int) -> bytes:
    return message(REC_READ).encode({"FIRST": int(first), "COUNT": int(count)})


def encode_rec_read_fd(first: int, count: int) -> bytes:
    """4 data bytes of REC_READ_FD: points ``first`` .. ``first + count - 1`` back as
    REC_DATA_FD frames."""
    return message(REC_READ_FD).encode({"FIRST": int(first), "COUNT": int(count)})


def encode_rec_block(index: int, axis: int, points: Sequence[tuple[float, float, float]]) -> bytes:
    """64 data bytes of REC_DATA_FD: 1..:data:`FD_REC_POINTS` consecutive recorded points of
    axis index ``axis`` (0 x, 1 y, 2 z), the first ``index``; each point (position [nm],
    output voltage [V], piezo voltage [V]) clamped into its signal's DBC range; unused slots 0."""
    n = len(points)
    if not 1 <= n <= FD_REC_POINTS:
        raise ProtocolError(f"REC_DATA_FD: {n} points; one frame carries 1..{FD_REC_POINTS}")
    y_lo, y_hi, v_hi = _rec_ranges()
    sig: dict[str, float] = {"INDEX": int(index) & 0xFFFF, "AXIS": int(axis), "COUNT": n}
    for k in range(FD_REC_POINTS):
        y, u, v = points[k] if k < n else (0.0, 0.0, 0.0)
        sig[f"Y{k}_NM"] = min(max(float(y), y_lo), y_hi)
        sig[f"U{k}_V"] = min(max(float(u), 0.0), v_hi)
        sig[f"V{k}_V"] = min(max(float(v), 0.0), v_hi)
    return message(REC_DATA_FD).encode(sig, strict=False)


def decode_rec_block(data: bytes) -> tuple[int, int, list[tuple[float, float, float]]]:
    """REC_DATA_FD data → (INDEX of the first point, AXIS, its COUNT points (position [nm],
    output voltage [V], piezo voltage [V])); a wrong length or a COUNT outside
    1..:data:`FD_REC_POINTS` → ProtocolError."""
    sig = decode(REC_DATA_FD, data)
    n = int(sig["COUNT"])
    if not 1 <= n <= FD_REC_POINTS:
        raise ProtocolError(f"REC_DATA_FD: COUNT {n}, expected 1..{FD_REC_POINTS}", data=bytes(data))
    return int(sig["INDEX"]), int(sig["AXIS"]), [(float(sig[f"Y{k}_NM"]), float(sig[f"U{k}_V"]),
                                                  float(sig[f"V{k}_V"])) for k in range(n)]


@functools.lru_cache(maxsize=1)
def _rec_ranges() -> tuple[float, float, float]:
    """(lowest, highest position [nm], highest voltage [V]) a recorded point's signals carry (DBC)."""
    msg = message(REC_DATA_FD)
    y = msg.get_signal_by_name("Y0_NM")
    return float(y.minimum), float(y.maximum), float(msg.get_signal_by_name("U0_V").maximum)
