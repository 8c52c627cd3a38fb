"""Sans-I/O codec for the piezosystem jena NV200 (open-loop voltage subset).

Host → device: ``cmd`` (read) or ``cmd,value`` (write) + CR LF. Every device reply ends
with XON (0x11): ``cmd,value`` for a read, ``error,<n>`` for an error. Whether a
successful write is acknowledged is *unconfirmed*: the simulator sends nothing, and the
driver ignores any frame that is neither an error nor the reply it waits for.
See docs/PROTOCOLS.md.
"""
from __future__ import annotations

from .codec_common import format_inside, parse_number
from .errors import ProtocolError

TERMINATOR = b"\r\n"
XON = b"\x11"
DECIMALS = 3
MAX_REPLY = 4096

#: NV200 error codes emulated by the simulator and named in driver errors (each codec keeps its
#: own table: the shape matches the other codecs' tables, the codes and texts are the device's)
ERRORS: dict[int, str] = {
    1: "unspecified error",
    2: "unknown command",
    3: "parameter missing",
    4: "range exceeded",
    5: "too many parameters",
    6: "parameter locked or read-only",
    7: "underload",
    8: "overload",
    9: "parameter too low",
    10: "parameter too high",
}


def encode(command: str) -> bytes:
    return command.encode("ascii") + TERMINATOR


def encode_set(value_V: float, lo_V: float, hi_V: float) -> bytes:
    """``set,75.000\\r\\n`` (12 bytes); the number as sent lies in [lo_V, hi_V] [V]."""
    return encode("set," + format_inside(value_V, lo_V, hi_V, DECIMALS))


def split_reply(buffer: bytes | bytearray) -> int:
    i = buffer.find(XON)
    if i >= 0:
        return i + 1
    if len(buffer) > MAX_REPLY:
        raise ProtocolError(f"no XON in {len(buffer)} bytes", data=bytes(buffer[:200]))
    return -1


def frame_fields(reply: bytes) -> list[bytes]:
    """``b"meas,12.5\\r\\n\\x11"`` → ``[b"meas", b"12.5"]``."""
    if not reply.endswith(XON):
        raise ProtocolError("NV200 reply does not end with XON", data=bytes(reply))
    body = reply[:-1].strip(b"\r\n ")
    if not body or b"\r" in body or b"\n" in body:
        raise ProtocolError("NV200 reply is not one line", data=bytes(reply))
    return body.split(b",")


def last_line(reply: bytes) -> bytes:
    """The last non-empty line of a frame, without XON (a frame may start with text the
    unit sent without XON, e.g. its device type in answer to a bare line end)."""
    lines = [ln.strip() for ln in reply.replace(XON, b"").replace(b"\r", b"\n").split(b"\n")]
    lines = [ln for ln in lines if ln]
    return lines[-1] if lines else b""


def device_type(reply: bytes) -> str:
    """The device type (``NV200/D_NET``) if the frame holds the unit's answer to a bare line end."""
    for ln in reply.replace(XON, b"").replace(b"\r", b"\n").split(b"\n"):
        text = ln.strip(b" \x01\x00<>").decode("ascii", "replace")
        if text.upper().startswith("NV200"):
            return text
    return ""


def is_error(reply: bytes) -> bool:
    return reply.lstrip(b"\r\n ").startswith(b"error")


def error_from(reply: bytes) -> ProtocolError:
    fields = frame_fields(reply)
    if len(fields) != 2 or fields[0] != b"error" or not fields[1].strip().isdigit():
        return ProtocolError("malformed NV200 error reply", data=bytes(reply))
    code = int(fields[1])
    return ProtocolError("NV200 device error", code=code, text=ERRORS.get(code, "unknown error"), data=bytes(reply))


def parse_read(command: str, reply: bytes) -> list[float]:
    """Reply to a read ``cmd`` → its numeric values; ``error,n`` → ProtocolError(code=n)."""
    if is_error(reply):
        raise error_from(reply)
    fields = frame_fields(reply)
    if fields[0] != command.encode():
        raise ProtocolError(f"reply to {command!r} names {fields[0]!r}", data=bytes(reply))
    if len(fields) < 2:
        raise ProtocolError(f"reply to {command!r} holds no value", data=bytes(reply))
    return [parse_number(f, f"reply to {command!r}", reply) for f in fields[1:]]


def parse_value(command: str, reply: bytes) -> float:
    vals = parse_read(command, reply)
    if len(vals) != 1:
        raise ProtocolError(f"reply to {command!r} holds {len(vals)} values, expected 1", data=bytes(reply))
    return vals[0]


# --- device side, for tests ---

def decode_set(line: bytes) -> float:
    fields = line.strip(b"\r\n").split(b",")
    if len(fields) != 2 or fields[0] != b"set":
        raise ProtocolError("not a set command", data=bytes(line))
    return parse_number(fields[1], "set", line)


def encode_read_reply(command: str, value: float) -> bytes:
    return f"{command},{value:.3f}\r\n".encode() + XON
