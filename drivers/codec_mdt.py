"""Sans-I/O codec for the Thorlabs MDT693B (3 channels) / MDT694B (1 channel).

Host → device: ASCII command + ``\\r``. Device → host: an optional echo of the command,
the reply lines separated by ``\\r``, then the prompt ``>`` (older firmware ``*``).
A set command is answered by the prompt alone; an unknown command by
``CMD_NOT_DEFINED>``. Query replies are bracketed, e.g. ``[ 24.80]`` or
``[  0.24,  0.21,  0.22]``; brackets are optional when parsing. See docs/PROTOCOLS.md.

Every function here is pure: bytes in, typed values out (or the reverse).
"""
from __future__ import annotations

from collections.abc import Sequence

from .codec_common import format_inside, parse_number
from .errors import ProtocolError

TERMINATOR = b"\r"
PROMPTS = b">*"
CMD_NOT_DEFINED = b"CMD_NOT_DEFINED"
DECIMALS = 2
#: a reply longer than this without a prompt is garbage, not a slow device
MAX_REPLY = 4096


def encode(command: str) -> bytes:
    """One command line, e.g. ``encode("XVOLTAGE?") == b"XVOLTAGE?\\r"``."""
    return command.encode("ascii") + TERMINATOR


def encode_set(axis: str, value_V: float, lo_V: float, hi_V: float) -> bytes:
    """``XVOLTAGE=75.00\\r`` — the value as sent lies inside [lo_V, hi_V] [V]."""
    return encode(f"{axis.upper()}VOLTAGE={format_inside(value_V, lo_V, hi_V, DECIMALS)}")


def encode_set_xyz(values_V: Sequence[float], lows_V: Sequence[float], highs_V: Sequence[float]) -> bytes:
    """``XYZVOLTAGE=x,y,z\\r`` (30 bytes for 75 V on each axis)."""
    parts = [format_inside(v, lo, hi, DECIMALS) for v, lo, hi in zip(values_V, lows_V, highs_V)]
    return encode("XYZVOLTAGE=" + ",".join(parts))


def split_reply(buffer: bytes | bytearray, prompts: bytes = PROMPTS) -> int:
    """Length of the first complete reply in ``buffer`` (through its prompt), or -1.
    Raises ProtocolError when ``MAX_REPLY`` bytes hold no prompt (garbage)."""
    best = -1
    for p in prompts:
        i = buffer.find(bytes((p,)))
        if i >= 0 and (best < 0 or i < best):
            best = i
    if best >= 0:
        return best + 1
    if len(buffer) > MAX_REPLY:
        raise ProtocolError(f"no prompt in {len(buffer)} bytes", data=bytes(buffer[:200]))
    return -1


def reply_body(command: bytes, reply: bytes, prompts: bytes = PROMPTS) -> bytes:
    """The reply text without echo, prompt and line ends. Raises ProtocolError for
    ``CMD_NOT_DEFINED`` (code ``"CMD_NOT_DEFINED"``) or a missing prompt."""
    if not reply or reply[-1] not in prompts:
        raise ProtocolError("reply does not end with the prompt '>'", data=bytes(reply))
    body = reply[:-1]
    cmd = command.rstrip(b"\r\n")
    stripped = body.lstrip(b"\r\n")
    if cmd and stripped[:len(cmd)].upper() == cmd.upper():  # echo on
        body = stripped[len(cmd):]
    body = body.strip(b"\r\n")
    if CMD_NOT_DEFINED in body.upper():
        raise ProtocolError(f"device did not accept {cmd!r}", code="CMD_NOT_DEFINED",
                            text="CMD_NOT_DEFINED", data=bytes(reply))
    return body


def parse_ack(command: bytes, reply: bytes) -> None:
    """A set command's reply must be the prompt alone (after echo removal)."""
    body = reply_body(command, reply)
    if body.strip():
        raise ProtocolError(f"unexpected text in reply to {command!r}", data=bytes(reply))


def parse_values(command: bytes, reply: bytes, n: int) -> list[float]:
    """Parse ``[ v1, v2, ...]`` (brackets optional) holding exactly ``n`` numbers [V]."""
    body = reply_body(command, reply).strip()
    if body.startswith(b"[") != body.endswith(b"]"):
        raise ProtocolError(f"unbalanced brackets in reply to {command!r}", data=bytes(reply))
    if body.startswith(b"["):
        body = body[1:-1]
    if b"\r" in body or b"\n" in body:
        raise ProtocolError(f"multi-line reply to {command!r}", data=bytes(reply))
    tokens = body.split(b",")
    if len(tokens) != n:
        raise ProtocolError(f"expected {n} value(s) in reply to {command!r}, got {len(tokens)}",
                            data=bytes(reply))
    return [parse_number(t, f"reply to {command!r}", reply) for t in tokens]


def parse_value(command: bytes, reply: bytes) -> float:
    return parse_values(command, reply, 1)[0]


def parse_lines(command: bytes, reply: bytes) -> list[str]:
    """A multi-line text reply (``ID?``) as lines, blank lines dropped."""
    body = reply_body(command, reply)
    return [ln.decode("ascii", "replace").strip() for ln in body.replace(b"\n", b"\r").split(b"\r")
            if ln.strip()]


def is_id_reply(reply: bytes) -> bool:
    """True for the reply to ``ID?`` (it names the model, ``MDT69...``), the known reply the
    driver resynchronises on at connect."""
    return b"MDT69" in reply.upper() and CMD_NOT_DEFINED not in reply.upper()


# --- device side, used by tests and documentation (the simulator has its own parser) ---

def decode_set(line: bytes) -> dict[str, float]:
    """Inverse of :func:`encode_set` / :func:`encode_set_xyz`: ``{"x": 75.0, ...}``."""
    text = line.strip(b"\r\n").upper()
    if text.startswith(b"XYZVOLTAGE="):
        vals = text[len(b"XYZVOLTAGE="):].strip(b"[]").split(b",")
        if len(vals) != 3:
            raise ProtocolError("XYZVOLTAGE needs three values", data=bytes(line))
        return {a: parse_number(v, "XYZVOLTAGE", line) for a, v in zip("xyz", vals)}
    if len(text) > 9 and text[1:9] == b"VOLTAGE=" and text[:1] in b"XYZ":
        return {text[:1].decode().lower(): parse_number(text[9:], "VOLTAGE", line)}
    raise ProtocolError("not a set command", data=bytes(line))


def encode_values_reply(values_V: Sequence[float], prompt: bytes = b">") -> bytes:
    """``[ 24.80]\\r>`` or ``[  0.24,  0.21,  0.22]\\r>``."""
    return b"[" + b",".join(f"{v:6.2f}".encode() for v in values_V) + b"]\r" + prompt
