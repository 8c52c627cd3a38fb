"""Sans-I/O codec for afmctl's CAN amplifier frames, defined in ``afm_amplifier.dbc``
(package data next to this module) and encoded/decoded through cantools.

Frames (all little-endian, see docs/DRIVERS.md):

==============  =====  =======  ==========================================================
frame           id     sender   signals
==============  =====  =======  ==========================================================
SETPOINT_XYZ    0x110  host     X_V, Y_V, Z_V (16 bit, 0.0025 V/bit, 0-163.8375 V), SEQ, FLAGS
HEARTBEAT       0x111  host     COUNTER, REQ_STATE (0 keep/1 enable/2 disable), REQ_STATUS, REQ_INFO
STATUS          0x190  amp      applied X_V, Y_V, Z_V, LAST_SEQ, STATE, ERROR_CODE
ERROR           0x191  amp      CODE, DETAIL, SEQ
LIMITS          0x192  amp      MIN_V, X_MAX_V, Y_MAX_V, Z_MAX_V
==============  =====  =======  ==========================================================
"""
from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

from .errors import LimitError, ProtocolError

DBC_PATH = Path(__file__).with_name("afm_amplifier.dbc")
SETPOINT_ID, HEARTBEAT_ID, STATUS_ID, ERROR_ID, LIMITS_ID = 0x110, 0x111, 0x190, 0x191, 0x192
V_PER_BIT = 0.0025
FLAG_REQ_STATUS = 0x01
ERRORS = {1: "value outside the amplifier range", 2: "sequence gap (setpoints lost or reordered)",
          3: "outputs disabled", 4: "hardware fault"}
STATES = {0: "disabled", 1: "enabled", 2: "fault"}


@functools.lru_cache(maxsize=1)
def database():
    import cantools
    return cantools.database.load_file(str(DBC_PATH))


@functools.lru_cache(maxsize=8)
def message(frame_id: int):
    return database().get_message_by_frame_id(frame_id)


def quantize_inside(value_V: float, lo_V: float, hi_V: float) -> float:
    """The nearest multiple of 0.0025 V inside [lo_V, hi_V] (never rounds across a limit)."""
    if not math.isfinite(value_V):
        raise LimitError(f"{value_V!r} V is not a finite voltage")
    value_V = min(max(value_V, lo_V), hi_V)  # also keeps huge values from overflowing
    raw = round(value_V / V_PER_BIT)
    if raw * V_PER_BIT > hi_V:
        raw = math.floor(hi_V / V_PER_BIT)
        while raw * V_PER_BIT > hi_V:
            raw -= 1
    if raw * V_PER_BIT < lo_V:
        raw = math.ceil(lo_V / V_PER_BIT)
        while raw * V_PER_BIT < lo_V:
            raw += 1
    v = raw * V_PER_BIT
    if not lo_V <= v <= hi_V:
        raise LimitError(f"no 0.0025 V step lies in [{lo_V:g}, {hi_V:g}] V")
    return v


@functools.lru_cache(maxsize=1)
def setpoint_range_V() -> tuple[float, float]:
    """The voltage range the DBC declares for the SETPOINT_XYZ signals [V]."""
    sig = message(SETPOINT_ID).get_signal_by_name("X_V")
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
    return message(SETPOINT_ID).encode({"X_V": x, "Y_V": y, "Z_V": z, "SEQ": seq & 0xFF, "FLAGS": flags & 0xFF},
                                       strict=False)


def encode_heartbeat(counter: int, req_state: int = 0, req_status: bool = False, req_info: bool = False) -> bytes:
    return message(HEARTBEAT_ID).encode({"COUNTER": counter & 0xFF, "REQ_STATE": req_state,
                                         "REQ_STATUS": int(req_status), "REQ_INFO": int(req_info)})


def decode(frame_id: int, data: bytes) -> dict[str, float]:
    """Any frame of the DBC → its signals; wrong length or unknown id → ProtocolError."""
    try:
        msg = message(frame_id)
    except KeyError:
        raise ProtocolError(f"unknown CAN frame id 0x{frame_id:X}", data=bytes(data)) from None
    if len(data) != msg.length:
        raise ProtocolError(f"{msg.name}: {len(data)} data bytes, expected {msg.length}", data=bytes(data))
    try:
        return dict(msg.decode(bytes(data), decode_choices=False, scaling=True))
    except Exception as err:
        raise ProtocolError(f"{msg.name}: cannot decode ({err})", data=bytes(data)) from None


def error_from(signals: Mapping[str, float], data: bytes = b"") -> ProtocolError:
    code = int(signals["CODE"])
    return ProtocolError(f"CAN amplifier error (setpoint SEQ {int(signals['SEQ'])}, detail {int(signals['DETAIL'])})",
                         code=code, text=ERRORS.get(code, "unknown error"), data=bytes(data) or None)
