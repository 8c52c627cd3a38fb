"""Sans-I/O codec for the PI GCS open-loop subset (E-727 and similar).

Host → device: ``CMD arg val arg val...`` + LF. Set commands send no reply; errors latch
and are read (and cleared) with ``ERR?``. A reply ends with an LF *not* preceded by a
space; in multi-line replies every line but the last ends in ``" \\n"``. Query replies are
``item=value`` lines, e.g. ``1=49.98``. See docs/PROTOCOLS.md.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

from .codec_common import format_inside, parse_number
from .errors import ProtocolError

TERMINATOR = b"\n"
DECIMALS = 4
MAX_REPLY = 4096

#: GCS error codes emulated by the simulator and named in driver errors (a table per codec: the
#: shape matches the other codecs' tables, the codes and texts are the device's)
ERRORS: dict[int, str] = {
    0: "no error",
    1: "parameter syntax error",
    2: "unknown command",
    15: "invalid axis identifier",
    17: "parameter out of range",
    301: "send buffer overflow",
    302: "voltage out of limits",
    303: "open-loop value cannot be set when servo is on",
    304: "received command is too long",
}


def encode(command: str) -> bytes:
    return command.encode("ascii") + TERMINATOR


def encode_sva(values_V: Mapping[str, float], lows_V: Mapping[str, float], highs_V: Mapping[str, float]) -> bytes:
    """``SVA 1 75 2 75 3 75\\n`` for GCS axis ids ``1..3``; numbers as sent lie in the limits."""
    parts = []
    for axis_id, v in values_V.items():
        parts.append(f"{axis_id} {format_inside(v, lows_V[axis_id], highs_V[axis_id], DECIMALS, strip=True)}")
    return encode("SVA " + " ".join(parts))


def split_reply(buffer: bytes | bytearray) -> int:
    """Length of the first complete reply (through the LF not preceded by a space) or -1."""
    start = 0
    while True:
        i = buffer.find(b"\n", start)
        if i < 0:
            if len(buffer) > MAX_REPLY:
                raise ProtocolError(f"no reply end in {len(buffer)} bytes", data=bytes(buffer[:200]))
            return -1
        if i == 0 or buffer[i - 1] != 0x20:
            return i + 1
        start = i + 1


def reply_lines(reply: bytes) -> list[bytes]:
    if not reply.endswith(b"\n") or reply.endswith(b" \n"):
        raise ProtocolError("GCS reply does not end with an LF not preceded by a space (truncated?)",
                            data=bytes(reply))
    lines = reply[:-1].split(b"\n")
    for ln in lines[:-1]:
        if not ln.endswith(b" "):
            raise ProtocolError("GCS multi-line reply: inner line without trailing space", data=bytes(reply))
    return [ln.strip() for ln in lines]


def parse_items(reply: bytes, expect: Sequence[str] | None = None) -> dict[str, float]:
    """``1=49.98 \\n2=50.1\\n`` → ``{"1": 49.98, "2": 50.1}``; ``expect`` lists the ids
    that must be present (exactly)."""
    out: dict[str, float] = {}
    for ln in reply_lines(reply):
        key, sep, val = ln.partition(b"=")
        if not sep or not key.strip():
            raise ProtocolError("GCS reply line is not item=value", data=bytes(reply))
        out[key.strip().decode("ascii", "replace")] = parse_number(val, "GCS reply", reply)
    if expect is not None and sorted(out) != sorted(expect):
        raise ProtocolError(f"GCS reply has items {sorted(out)}, expected {list(expect)}", data=bytes(reply))
    return out


def parse_error_code(reply: bytes) -> int:
    """The integer of an ``ERR?`` reply."""
    lines = reply_lines(reply)
    if len(lines) != 1 or not lines[0].isdigit() or len(lines[0]) > 6:
        raise ProtocolError("ERR? reply is not an integer", data=bytes(reply))
    return int(lines[0])


def error_for(code: int, data: bytes = b"") -> ProtocolError:
    text = ERRORS.get(code, "unknown error")
    return ProtocolError("GCS device error", code=code, text=text, data=data or None)


def check_error_reply(reply: bytes) -> None:
    code = parse_error_code(reply)
    if code != 0:
        raise error_for(code, reply)


def parse_axes(reply: bytes) -> list[str]:
    """``SAI?`` → ``["1", "2", "3"]``."""
    axes = [ln.decode("ascii", "replace") for ln in reply_lines(reply) if ln]
    if not axes or any(not a.replace("_", "").isalnum() for a in axes):
        raise ProtocolError("SAI? reply holds no axis names", data=bytes(reply))
    return axes


# --- device side, for tests ---

def decode_sva(line: bytes) -> dict[str, float]:
    tokens = line.strip().split()
    if not tokens or tokens[0].upper() != b"SVA" or len(tokens) % 2 != 1 or len(tokens) < 3:
        raise ProtocolError("not an SVA command", data=bytes(line))
    return {tokens[i].decode(): parse_number(tokens[i + 1], "SVA", line) for i in range(1, len(tokens), 2)}


def encode_items_reply(items: Mapping[str, float]) -> bytes:
    lines = [f"{k}={v:.4f}".encode() for k, v in items.items()]
    return b" \n".join(lines) + b"\n"
