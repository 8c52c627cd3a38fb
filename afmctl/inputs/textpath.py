"""A single-stroke font for imprinting text with the tip (image-based paper, Sec. 4.3: 'NK').

Glyphs are drawn on a cell 0 ≤ x ≤ 4, 0 ≤ y ≤ 6 (units; y up); each glyph is a list of
strokes, each stroke a polyline the tip follows with the pen down. Letters A–Z, digits
0–9, space and '-' are defined. :func:`strokes` lays out a string: it returns strokes in nm
(x, y) for a given letter height, in drawing order (left to right, each glyph's strokes
ordered so the pen-up travel is short).
"""
from __future__ import annotations

import numpy as np

from ..errors import AfmctlError

#: glyph cell height and the advance from one glyph to the next, in cell units (cells are 4 wide)
CELL_H, ADVANCE = 6.0, 5.5

_O = [(0, 1), (1, 0), (3, 0), (4, 1), (4, 5), (3, 6), (1, 6), (0, 5), (0, 1)]

#: glyph → strokes (polylines on the 4 × 6 cell)
GLYPHS: dict[str, list[list[tuple[float, float]]]] = {
    "A": [[(0, 0), (2, 6), (4, 0)], [(1, 3), (3, 3)]],
    "B": [[(0, 0), (0, 6), (3, 6), (4, 5), (4, 4), (3, 3), (0, 3)], [(3, 3), (4, 2), (4, 1), (3, 0), (0, 0)]],
    "C": [[(4, 5), (3, 6), (1, 6), (0, 5), (0, 1), (1, 0), (3, 0), (4, 1)]],
    "D": [[(0, 0), (0, 6), (3, 6), (4, 5), (4, 1), (3, 0), (0, 0)]],
    "E": [[(4, 6), (0, 6), (0, 0), (4, 0)], [(0, 3), (3, 3)]],
    "F": [[(4, 6), (0, 6), (0, 0)], [(0, 3), (3, 3)]],
    "G": [[(4, 5), (3, 6), (1, 6), (0, 5), (0, 1), (1, 0), (3, 0), (4, 1), (4, 3), (2, 3)]],
    "H": [[(0, 6), (0, 0)], [(0, 3), (4, 3)], [(4, 6), (4, 0)]],
    "I": [[(1, 6), (3, 6)], [(2, 6), (2, 0)], [(1, 0), (3, 0)]],
    "J": [[(4, 6), (4, 1), (3, 0), (1, 0), (0, 1)]],
    "K": [[(0, 6), (0, 0)], [(4, 6), (0, 2)], [(1, 3), (4, 0)]],
    "L": [[(0, 6), (0, 0), (4, 0)]],
    "M": [[(0, 0), (0, 6), (2, 3), (4, 6), (4, 0)]],
    "N": [[(0, 0), (0, 6), (4, 0), (4, 6)]],
    "O": [_O],
    "P": [[(0, 0), (0, 6), (3, 6), (4, 5), (4, 4), (3, 3), (0, 3)]],
    "Q": [_O, [(2, 2), (4, 0)]],
    "R": [[(0, 0), (0, 6), (3, 6), (4, 5), (4, 4), (3, 3), (0, 3)], [(2, 3), (4, 0)]],
    "S": [[(4, 5), (3, 6), (1, 6), (0, 5), (0, 4), (1, 3), (3, 3), (4, 2), (4, 1), (3, 0), (1, 0), (0, 1)]],
    "T": [[(0, 6), (4, 6)], [(2, 6), (2, 0)]],
    "U": [[(0, 6), (0, 1), (1, 0), (3, 0), (4, 1), (4, 6)]],
    "V": [[(0, 6), (2, 0), (4, 6)]],
    "W": [[(0, 6), (1, 0), (2, 4), (3, 0), (4, 6)]],
    "X": [[(0, 6), (4, 0)], [(4, 6), (0, 0)]],
    "Y": [[(0, 6), (2, 3), (4, 6)], [(2, 3), (2, 0)]],
    "Z": [[(0, 6), (4, 6), (0, 0), (4, 0)]],
    "0": [_O, [(0, 1), (4, 5)]],
    "1": [[(1, 5), (2, 6), (2, 0)], [(1, 0), (3, 0)]],
    "2": [[(0, 5), (1, 6), (3, 6), (4, 5), (4, 4), (0, 0), (4, 0)]],
    "3": [[(0, 5), (1, 6), (3, 6), (4, 5), (4, 4), (3, 3), (4, 2), (4, 1), (3, 0), (1, 0), (0, 1)], [(1, 3), (3, 3)]],
    "4": [[(3, 0), (3, 6), (0, 2), (4, 2)]],
    "5": [[(4, 6), (0, 6), (0, 3), (3, 3), (4, 2), (4, 1), (3, 0), (0, 0)]],
    "6": [[(4, 5), (3, 6), (1, 6), (0, 5), (0, 1), (1, 0), (3, 0), (4, 1), (4, 2), (3, 3), (0, 3)]],
    "7": [[(0, 6), (4, 6), (1, 0)]],
    "8": [[(1, 3), (0, 4), (0, 5), (1, 6), (3, 6), (4, 5), (4, 4), (3, 3), (1, 3), (0, 2), (0, 1), (1, 0),
           (3, 0), (4, 1), (4, 2), (3, 3)]],
    "9": [[(4, 3), (1, 3), (0, 4), (0, 5), (1, 6), (3, 6), (4, 5), (4, 1), (3, 0), (1, 0), (0, 1)]],
    "-": [[(1, 3), (3, 3)]],
    " ": [],
}


def strokes(text: str, height_nm: float, x0_nm: float = 0.0, y0_nm: float = 0.0) -> list[np.ndarray]:
    """Strokes of ``text`` as arrays (K, 2) of (x, y) [nm]; letters ``height_nm`` tall,
    the lower-left corner of the first glyph at (``x0_nm``, ``y0_nm``)."""
    if not (height_nm > 0):
        raise AfmctlError(f"text height_nm: {height_nm!r} must be > 0")
    scale = float(height_nm) / CELL_H
    out: list[np.ndarray] = []
    for i, ch in enumerate(text.upper()):
        glyph = GLYPHS.get(ch)
        if glyph is None:
            allowed = "".join(sorted(k for k in GLYPHS if k != " "))
            raise AfmctlError(f"trajectory.text: character {ch!r} has no stroke glyph; allowed: {allowed}, space")
        ox = x0_nm + i * ADVANCE * scale
        for stroke in glyph:
            pts = np.asarray(stroke, dtype=np.float64) * scale
            pts[:, 0] += ox
            pts[:, 1] += y0_nm
            out.append(pts)
    return out
