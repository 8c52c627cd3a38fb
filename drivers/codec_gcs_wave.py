"""Sans-I/O codec for the GCS 2 wave generator (wave tables played on the controller's
servo clock), as PIPython issues the commands and PI's GCS manuals describe them.

* ``WAV <table> X PNT 1 <n> <v1> ... <vn>`` starts a table with n points [V in open loop],
  ``WAV <table> & PNT <first> <n> ...`` appends a segment whose first point gets index
  ``first`` (1-based) — the bunches PIPython's ``pitools.writewavepoints`` sends.
* ``WSL <gen> <table>`` connects generator and table, ``WGC <gen> <cycles>`` (0 = endless),
  ``WTR <gen> <divider> <interpolation>``: a table point lasts ``divider`` servo cycles.
* ``WGO <gen> 1`` starts now, ``WGO <gen> 0`` stops; the single byte 0x09 (``#9``) is
  answered with the running generators as a hex bit mask (bit 0 = generator 1).
* ``SPA? 1 0x0E000200`` reads the servo update time [s]; ``WMS? <table>`` the most points
  a table takes; ``WAV? <table> 1`` the points it holds; ``WOS? <gen>`` the output offset
  the generator adds to every wave value (E-727 manual: output = WOS offset + wave value;
  it can be stored in the controller's non-volatile memory).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

from .codec_common import format_all_inside
from .codec_gcs import DECIMALS, encode, parse_items, reply_lines
from .errors import ProtocolError

#: the single-byte "are wave generators running?" command (no terminator)
RUNNING = b"\x09"
SERVO_UPDATE_TIME_PARAM = "0x0E000200"
#: longest command line the driver sends [bytes, LF included] (the simulator takes 1024)
MAX_LINE = 1000


def encode_wav_pnt(table: int, values_V: Sequence[float] | np.ndarray, lo_V: float, hi_V: float,
                   max_line: int = MAX_LINE) -> list[bytes]:
    """The ``WAV ... PNT`` lines that write ``values_V`` as table ``table``: the first line
    starts the table (``X``), the rest append (``&``) at their index. Every number as sent
    lies in ``[lo_V, hi_V]``; no line is longer than ``max_line`` bytes."""
    texts = format_all_inside(values_V, lo_V, hi_V, DECIMALS, strip=True)
    lines: list[bytes] = []
    k = 0
    while k < len(texts):
        head_len = len(f"WAV {table} & PNT {k + 1} {len(texts) - k} ") + 1
        n, size = 0, head_len
        while k + n < len(texts) and size + len(texts[k + n]) + 1 <= max_line:
            size += len(texts[k + n]) + 1
            n += 1
        if n == 0:
            raise ValueError(f"max_line {max_line} holds no wave point")
        mode = "X" if k == 0 else "&"
        lines.append(encode(f"WAV {table} {mode} PNT {k + 1} {n} " + " ".join(texts[k:k + n])))
        k += n
    return lines


def encode_start(gens: Sequence[int], divider: int, cycles: int) -> bytes:
    """Connect each generator to its own table, set cycles and table rate, then start them
    all with one ``WGO`` (they start on the same servo tick): one write."""
    setup = b"".join(encode(f"WSL {g} {g}") + encode(f"WGC {g} {cycles}") + encode(f"WTR {g} {divider} 0")
                     for g in gens)
    return setup + encode("WGO " + " ".join(f"{g} 1" for g in gens))


def parse_offsets(reply: bytes, gens: Sequence[int]) -> dict[int, float]:
    """``1=0.0000`` lines → ``{gen: offset V}`` for every one of ``gens``."""
    items = parse_items(reply)
    missing = [g for g in gens if str(g) not in items]
    if missing:
        raise ProtocolError(f"WOS? reply holds no offset for generator {missing[0]}", data=bytes(reply))
    return {g: items[str(g)] for g in gens}


def encode_stop(gens: Sequence[int]) -> bytes:
    return encode("WGO " + " ".join(f"{g} 0" for g in gens))


def parse_running(reply: bytes) -> int:
    """The bit mask of a ``#9`` reply (hex digits)."""
    lines = reply_lines(reply)
    try:
        if len(lines) != 1 or len(lines[0]) > 8:
            raise ValueError
        return int(lines[0], 16)
    except ValueError:
        raise ProtocolError("#9 reply is not a hex bit mask", data=bytes(reply)) from None


def parse_table_capacity(reply: bytes, table: int) -> int:
    """``WMS? <table>`` reply ``<table>=<points>`` → the most points the table takes."""
    items = parse_items(reply)
    value = items.get(str(table))
    if value is None or not (1 <= value <= 2**31 - 1) or value != int(value):
        raise ProtocolError(f"WMS? reply holds no point count for table {table}", data=bytes(reply))
    return int(value)


def parse_servo_cycle_s(reply: bytes) -> float:
    """``1 0x0E000200=2e-05`` → 2e-05 s; refuses values outside 1 µs..1 s."""
    items = parse_items(reply)
    if len(items) != 1:
        raise ProtocolError("SPA? reply holds more than the servo update time", data=bytes(reply))
    (value,) = items.values()
    if not 1e-6 <= value <= 1.0:
        raise ProtocolError(f"servo update time {value:g} s is outside 1e-06..1 s", data=bytes(reply))
    return value


def divider_for(rate_Hz: float, servo_cycle_s: float) -> int:
    """The table rate divider that plays ``rate_Hz`` points per second exactly; a rate
    that is not the servo rate over a whole number raises ValueError naming the nearest
    achievable rates."""
    servo_Hz = 1.0 / servo_cycle_s
    d = servo_Hz / rate_Hz
    n = round(d)
    if n >= 1 and abs(d - n) <= 1e-9 * d:
        return n
    lo = max(1, int(d))
    near = sorted({servo_Hz / lo, servo_Hz / (lo + 1)}, reverse=True)
    raise ValueError(f"{rate_Hz:g} Hz is not the servo rate {servo_Hz:g} Hz over a whole number; "
                     "nearest: " + " or ".join(f"{r:.10g} Hz" for r in near))
