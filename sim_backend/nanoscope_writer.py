"""A **test-fixture generator** for Bruker Nanoscope image files (v9 layout), written from the
documented header layout (Nanoscope User Guide, "General Format for CIAO Parameter Objects").

No library on PyPI writes Nanoscope files, and the real sample file the tests ship
(``tests/data/jmarini-nanoscope/``) holds only a retrace channel; this writer makes files with a
trace *and* a retrace height channel of known heights, so that the reader
(:func:`afmctl.compensators.scan_files.read_scan_image`, which decodes them with Gwyddion's
Nanoscope importer through gwyddionpy) can be tested for exactness. It is not an export
format of afmctl and not used outside tests.

Layout written: a text header (``\\key: value`` lines, CR LF), sections ``\\*File list``,
``\\*Ciao scan list`` (``\\Scan Size``, ``\\Samps/line``, ``\\Lines``, ``\\Scan Rate`` and the
Z sensitivity ``\\@Sens. ZsensSens: V <nm/V> nm/V``), one ``\\*Ciao image list`` per channel
(``\\Data offset``, ``\\Data length``, ``\\Bytes/pixel: 4``, ``\\Line Direction``, ``\\@2:Image
Data``, ``\\@2:Z scale``), ``\\*File list end``; the header is padded to ``\\Data length`` bytes
and followed by each channel as little-endian int32, its lines stored bottom line first (the
reverse of the rows given, which are top line first, as Gwyddion presents a Nanoscope image).
Height [nm] = code × (Z scale [V] / 2³²) × sensitivity [nm/V].
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

#: Z scale [V] and sensitivity [nm/V] of the written files: one LSB = 1e-8 V × 100 nm/V = 1e-6 nm
Z_SCALE_V = 42.94967296
Z_SENS_NM_PER_V = 100.0
LSB_NM = Z_SCALE_V / 2.0**32 * Z_SENS_NM_PER_V


def _scan_list(size_nm: float, lines: int, pixels: int, line_rate_Hz: float) -> list[str]:
    return ["\\*Ciao scan list", f"\\Scan Size: {size_nm!r} nm", f"\\Samps/line: {pixels}", f"\\Lines: {lines}",
            f"\\Scan Rate: {line_rate_Hz!r}", f"\\@Sens. ZsensSens: V {Z_SENS_NM_PER_V!r} nm/V"]


def _image_list(offset: int, lines: int, pixels: int, size_nm: float, height_nm: float, direction: str,
                title: str) -> list[str]:
    return ["\\*Ciao image list", f"\\Data offset: {offset}", f"\\Data length: {lines * pixels * 4}",
            "\\Bytes/pixel: 4", f"\\Samps/line: {pixels}", f"\\Number of lines: {lines}",
            f"\\Scan Size: {size_nm!r} {height_nm!r} nm", f"\\Line Direction: {direction}",
            f"\\@2:Image Data: S [ZSensor] \"{title}\"",
            f"\\@2:Z scale: V [Sens. ZsensSens] ({Z_SCALE_V / 2.0**32:.10g} V/LSB) {Z_SCALE_V!r} V"]


def encode_heights(heights_nm: np.ndarray) -> np.ndarray:
    """Heights [nm] → the int32 codes written (rounded to :data:`LSB_NM`); ``ValueError`` if out of range."""
    codes = np.rint(np.asarray(heights_nm, dtype=np.float64) / LSB_NM)
    if np.any(np.abs(codes) > 2**31 - 1):
        raise ValueError(f"heights beyond ±{(2**31 - 1) * LSB_NM:.4g} nm do not fit the int32 codes")
    return codes.astype("<i4")


def write_nanoscope(path: str | Path, channels: dict[str, np.ndarray], *, scan_size_nm: float,
                    line_rate_Hz: float, title: str = "Height Sensor", version: str = "0x09400202") -> Path:
    """Write ``channels`` {``"Trace"``/``"Retrace"``: heights [nm] of shape (lines, pixels)} as a
    Nanoscope file; the slow-axis extent is ``scan_size_nm × lines / pixels`` (square pixels)."""
    shapes = {np.shape(a) for a in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"channels must be 2-D of one shape; got {sorted(shapes)}")
    lines, pixels = next(iter(shapes))
    height_nm = scan_size_nm * lines / pixels
    head_len = 8192 * (1 + (len(channels) * 600 + 400) // 8192)
    text = ["\\*File list", f"\\Version: {version}", f"\\Data length: {head_len}"]
    text += _scan_list(scan_size_nm, lines, pixels, line_rate_Hz)
    blobs = []
    for k, (direction, heights) in enumerate(channels.items()):
        text += _image_list(head_len + k * lines * pixels * 4, lines, pixels, scan_size_nm, height_nm, direction,
                            title)
        blobs.append(encode_heights(np.asarray(heights)[::-1]).tobytes())
    header = ("\r\n".join(text + ["\\*File list end"]) + "\r\n").encode("latin-1")
    if len(header) > head_len:
        raise ValueError("header longer than its reserved space")
    p = Path(path)
    p.write_bytes(header + b"\x1a" * (head_len - len(header)) + b"".join(blobs))
    return p
