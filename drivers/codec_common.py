"""Helpers shared by the pure protocol codecs: number formatting that never leaves the
limits, and strict number parsing. No I/O here."""
from __future__ import annotations

import math
import re
from collections.abc import Sequence

import numpy as np

from .errors import LimitError, ProtocolError

_NUMBER = re.compile(rb"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")


def format_inside(value_V: float, lo_V: float, hi_V: float, decimals: int, *, strip: bool = False) -> str:
    """Format ``value_V`` with ``decimals`` digits so that the number *as sent* lies in
    [lo_V, hi_V] [V]. Rounding never crosses a limit: a value that would round outside
    is moved inward by one quantum. Raises :class:`LimitError` for non-finite values or
    when the interval holds no representable number."""
    if not math.isfinite(value_V):
        raise LimitError(f"{value_V!r} V is not a finite voltage")
    q = 10.0 ** -decimals
    text = f"{value_V:.{decimals}f}"
    for _ in range(4):
        sent = float(text) + 0.0
        if sent > hi_V:
            text = f"{math.floor(hi_V / q) * q:.{decimals}f}"
            if float(text) > hi_V:
                text = f"{(math.floor(hi_V / q) - 1) * q:.{decimals}f}"
        elif sent < lo_V:
            text = f"{math.ceil(lo_V / q) * q:.{decimals}f}"
            if float(text) < lo_V:
                text = f"{(math.ceil(lo_V / q) + 1) * q:.{decimals}f}"
        else:
            break
    sent = float(text)
    if not (lo_V <= sent <= hi_V):
        raise LimitError(f"no {decimals}-decimal voltage lies in [{lo_V:g}, {hi_V:g}] V")
    if sent == 0.0:
        text = f"{0.0:.{decimals}f}"  # never "-0.00"
    if strip and "." in text:
        text = text.rstrip("0").rstrip(".")
        if text in ("", "-", "-0"):
            text = "0"
    return text


def format_all_inside(values_V: Sequence[float] | np.ndarray, lo_V: float, hi_V: float, decimals: int, *,
                      strip: bool = False) -> list[str]:
    """:func:`format_inside` of every value (the same texts), formatted in one pass: only the
    values whose plain rounding lands outside ``[lo_V, hi_V]`` or on zero (or that are not
    finite) go through :func:`format_inside` one by one."""
    vals = np.asarray(values_V, dtype=np.float64).ravel()
    texts = ["%.*f" % (decimals, v) for v in vals.tolist()]
    if not texts:
        return texts
    sent = np.array(texts, dtype=np.float64)
    slow = ~np.isfinite(vals) | ~(sent >= lo_V) | ~(sent <= hi_V) | (sent == 0.0)
    for k in np.flatnonzero(slow).tolist():
        texts[k] = format_inside(float(vals[k]), lo_V, hi_V, decimals, strip=strip)
    if strip and decimals > 0:
        fast = np.flatnonzero(~slow).tolist()
        for k in fast:
            texts[k] = texts[k].rstrip("0").rstrip(".")
    return texts


def parse_number(token: bytes, where: str, data: bytes) -> float:
    """Parse one finite decimal number (the whole of ``token``) or raise ProtocolError
    carrying the full reply ``data``."""
    token = token.strip()
    if not _NUMBER.fullmatch(token):
        raise ProtocolError(f"{where}: expected a number, got {token!r}", data=bytes(data))
    value = float(token)
    if not math.isfinite(value):
        raise ProtocolError(f"{where}: number out of range {token!r}", data=bytes(data))
    return value
