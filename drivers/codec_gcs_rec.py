"""Sans-I/O codec for the GCS 2 data recorder, as PIPython's ``datarectools`` drives it and
PI's GCS manuals describe it.

* ``DRC <table> <source> <option>``: record option 2 = actual position of axis <source>
  [µm], 14 = open-loop control value of axis <source> [V] (the voltage commanded: ``SVA``
  or the wave generator; PIPython's ``OPENLOOP_INPUT_14``), 7 = piezo voltage of output
  channel <source> [V] (what the amplifier stage puts on the piezo; ``PIEZO_VOLTAGE_7``)
  (1 commanded position, 3 position error).
* ``DRT 0 0 0``: every table triggers with the default source 0 — the wave generator's
  start (``WGO``) or ``WGR``; ``RTR <n>``: a point every n servo cycles.
* ``TNR?`` the number of record tables; ``SPA? 1 0x16000200`` / ``0x16000300`` the points
  of all tables and the number of tables (points per table = their quotient, as PIPython
  computes it for the E-7xx); ``DRL? <tables>`` points recorded since the trigger.
* ``DRR? <offset> <n> <tables>``: the GCS array — ``# key = value`` header lines up to
  ``# END_HEADER``, then n lines of one column per table (separator ``SEPARATOR``, a byte
  value; 32 = space); every line but the last ends with a space before the LF. Read line by
  line (:func:`split_line`), so the reply may be of any length.
"""
from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np

from .codec_gcs import encode, parse_items, reply_lines
from .errors import ProtocolError

OPTION_ACTUAL_POSITION = 2
OPTION_PIEZO_VOLTAGE = 7
OPTION_OPENLOOP_CONTROL = 14
TRIGGER_WAVE_START = 0
MAX_POINTS_PARAM = "0x16000200"
CHAN_NUMBER_PARAM = "0x16000300"


def encode_configure(tables: Sequence[tuple[int, str, int]], rate: int) -> list[bytes]:
    """One ``DRC`` per table, ``DRT 0 0 0`` (start with the wave generator), ``RTR rate``."""
    lines = [encode(f"DRC {t} {src} {opt}") for t, src, opt in tables]
    return lines + [encode(f"DRT 0 {TRIGGER_WAVE_START} 0"), encode(f"RTR {int(rate)}")]


def encode_read(tables: Sequence[int], points: int, offset: int = 1) -> bytes:
    return encode(f"DRR? {int(offset)} {int(points)} " + " ".join(str(t) for t in tables))


def parse_int(reply: bytes, what: str) -> int:
    """A single integer reply (``TNR?``, ``RTR?``)."""
    lines = reply_lines(reply)
    if len(lines) != 1 or not lines[0].isdigit():
        raise ProtocolError(f"{what} reply is not an integer", data=bytes(reply))
    return int(lines[0])


def parse_counts(reply: bytes, tables: Sequence[int]) -> dict[int, int]:
    """``DRL?`` reply ``1=400 \\n2=400`` → ``{1: 400, 2: 400}`` for every one of ``tables``."""
    items = parse_items(reply, [str(t) for t in tables])
    if any(v < 0 or v != int(v) for v in items.values()):
        raise ProtocolError("DRL? reply holds a count that is not a whole number", data=bytes(reply))
    return {int(k): int(v) for k, v in items.items()}


def parse_param(reply: bytes, param: str) -> float:
    """``1 0x16000200=262144`` → 262144."""
    items = parse_items(reply)
    if len(items) != 1:
        raise ProtocolError(f"SPA? reply does not hold parameter {param} alone", data=bytes(reply))
    return next(iter(items.values()))


def split_line(buffer: bytes | bytearray) -> int:
    """Length of the first line (through its LF) or -1."""
    i = buffer.find(b"\n")
    return i + 1 if i >= 0 else -1


#: the end of a GCS answer: an LF not preceded by a space
_ANSWER_END = re.compile(rb"(?<! )\n")
#: the longest run of ``DRR?`` data lines taken as one frame [bytes]
MAX_DATA_BLOCK = 16 * 1024 * 1024


def split_answer(buffer: bytes | bytearray) -> int:
    """Length of the rest of a GCS answer (through its last line) or -1: the data lines
    of a ``DRR?`` chunk in one frame (one scan, however many lines)."""
    m = _ANSWER_END.search(buffer)
    if m is None:
        if len(buffer) > MAX_DATA_BLOCK:
            raise ProtocolError(f"DRR? answer: no last line in {len(buffer)} bytes", data=bytes(buffer[:200]))
        return -1
    return m.end()


def is_last_line(line: bytes) -> bool:
    """The last line of a GCS answer ends with an LF not preceded by a space."""
    return line.endswith(b"\n") and not line.endswith(b" \n")


def parse_header(lines: Sequence[bytes]) -> dict[str, str]:
    """``# key = value`` lines (through ``# END_HEADER``) → ``{key: value}``."""
    out: dict[str, str] = {}
    for raw in lines:
        text = raw.decode("ascii", "replace").strip()
        if not text.startswith("#"):
            raise ProtocolError("DRR? header line does not start with #", data=bytes(raw))
        key, sep, value = text.lstrip("#").partition("=")
        if sep:
            out[key.strip().upper()] = value.strip()
    return out


def parse_data(header: dict[str, str], lines: Sequence[bytes], columns: int) -> np.ndarray:
    """The data lines of a GCS array → (n, columns) float array; the header's ``NDATA``,
    ``DIM`` and ``SEPARATOR`` are checked against what was asked."""
    try:
        ndata, dim, sep = int(header["NDATA"]), int(header["DIM"]), int(header.get("SEPARATOR", "32"))
    except (KeyError, ValueError):
        raise ProtocolError(f"DRR? header lacks NDATA/DIM or holds a non-integer: {header}") from None
    if dim != columns or ndata != len(lines):
        raise ProtocolError(f"DRR? answer: {len(lines)} lines of DIM={dim}, header NDATA={ndata}; "
                            f"{columns} columns were asked")
    split = None if sep == 32 else chr(sep)
    ok = False
    if split is None:                   # all lines in one split (fast): as many numbers as asked, all finite
        cells_all = b" ".join(lines).split()
        if len(cells_all) == ndata * columns:
            try:
                out = np.array(cells_all, dtype=np.float64).reshape(ndata, columns)
                ok = bool(np.all(np.isfinite(out)))
            except ValueError:
                ok = False
        if ok:                          # each line holds `columns` numbers (not only the total)
            ok = all(len(raw.split()) == columns for raw in lines)
    if ok:
        return out
    cells = [raw.decode("ascii", "replace").strip().split(split) for raw in lines]
    try:
        out = np.array(cells, dtype=np.float64).reshape(ndata, columns)   # all lines at once
        ok = bool(np.all(np.isfinite(out)))
    except ValueError:                  # a line of other length or not numbers: find it
        ok = False
    if not ok:
        for k, (raw, row) in enumerate(zip(lines, cells)):
            try:
                values = [float(c) for c in row]
            except ValueError:
                raise ProtocolError(f"DRR? data line {k + 1} is not numbers", data=bytes(raw)) from None
            if len(values) != columns or not all(np.isfinite(values)):
                raise ProtocolError(f"DRR? data line {k + 1}: {len(values)} finite values expected {columns}",
                                    data=bytes(raw))
    return out
