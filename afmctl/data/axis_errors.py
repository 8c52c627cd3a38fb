"""Tracking errors a user can check: per axis, in nm and in % of that axis's own length,
over a named part of the record — what ``afmctl run``, ``afmctl learn`` and ``afmctl
report`` print.

The part judged (:func:`judged_part`): when the target is a raster — one axis moves along
at least two straight lines (:func:`afmctl.compensators.learning_weights.find_lines`) of
one length that cover at least half the record between its first move and its last (a
wave table's rests before and after do not count) — the central ``central_pct`` % of the
raster lines the learning judges too
(:func:`afmctl.compensators.learning_weights.judged_lines`: every line, a trace and its
retrace, but the first, which the scanner starts from rest; the part an AFM images, the
turnarounds the amplifier cannot follow left out); otherwise the whole record given.

Each axis's percentages refer to (:func:`reference_nm`):

* ``line`` — the fast axis: the length of its lines (peak to peak over a line);
* ``step`` — an axis that moves by a small amount from line to line (a raster's slow axis,
  a staircase): its step per line, the median of its nonzero peak-to-peak per line;
* ``range`` — without lines: the axis's peak to peak over the record;
* none — an axis whose target holds (less than :data:`MIN_SPAN_NM`): nm only.

So a slow axis's error reads large in % (its step is short): it is the share of one line's
pitch by which the image's lines are misplaced. Units: nm, %.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from afmctl.compensators.learning_weights import (HOLD_NM, REPORT_CENTRAL_PCT, Line, find_lines, judged_lines,
                                                  lines_mask, moving_spans_nm)

#: an axis moving less than this [nm] peak to peak (over the record, or over one line for
#: a step) holds: its error is given in nm only
MIN_SPAN_NM = HOLD_NM
#: the lines of a raster cover at least this share of the record …
RASTER_SHARE = 0.5
#: … and this share of them is within LENGTH_TOL of their median length
RASTER_ALIKE = 0.9
LENGTH_TOL = 0.1
AXES = "xyz"


def _nm(v: float) -> str:
    """A length [nm] to three significant digits, without an exponent from 100 nm up."""
    return f"{v:.0f}" if abs(v) >= 100.0 else f"{v:.3g}"


@dataclass(frozen=True)
class AxisError:
    """One axis's error over the judged part: max |e| and RMS [nm], and ``ref_nm``, the
    length the percentages refer to, named by ``ref`` (``line``, ``step``, ``range``; None
    when the axis holds)."""

    axis: str
    max_nm: float
    rms_nm: float
    ref: str | None = None
    ref_nm: float | None = None

    @property
    def max_pct(self) -> float | None:
        return None if self.ref_nm is None else 100.0 * self.max_nm / self.ref_nm

    @property
    def rms_pct(self) -> float | None:
        return None if self.ref_nm is None else 100.0 * self.rms_nm / self.ref_nm

    def text(self) -> str:
        """``x max 12.3 nm (0.31 %) / RMS 4.5 nm (0.11 %) of its 4000 nm line``."""
        if self.ref_nm is None:
            return f"{self.axis} max {_nm(self.max_nm)} nm / RMS {_nm(self.rms_nm)} nm (holds)"
        return (f"{self.axis} max {_nm(self.max_nm)} nm ({self.max_pct:.3g} %) / RMS {_nm(self.rms_nm)} nm "
                f"({self.rms_pct:.3g} %) of its {self.ref_nm:.4g} nm {self.ref}")

    def as_dict(self) -> dict[str, float | str | None]:
        return {"axis": self.axis, "max_nm": self.max_nm, "rms_nm": self.rms_nm, "max_pct": self.max_pct,
                "rms_pct": self.rms_pct, "reference": self.ref, "reference_nm": self.ref_nm}


@dataclass(frozen=True)
class ErrorReport:
    """Per-axis errors (:class:`AxisError`) over ``part`` (what of the record they cover,
    in words), ``samples`` samples of it."""

    part: str
    samples: int
    axes: list[AxisError]

    def worst_pct(self) -> float:
        """The largest max error in % over the axes that have a reference (NaN: none)."""
        pct = [a.max_pct for a in self.axes if a.max_pct is not None]
        return max(pct) if pct else float("nan")

    def axis(self, name: str) -> AxisError:
        return next(a for a in self.axes if a.axis == name)

    def text(self, sep: str = "; ") -> str:
        return sep.join(a.text() for a in self.axes)

    def as_dict(self) -> dict:
        return {"part": self.part, "samples": self.samples, "axes": {a.axis: a.as_dict() for a in self.axes}}


def raster_lines(target_nm: np.ndarray, axes: str = AXES) -> tuple[str, list[Line]] | None:
    """The fast axis and its lines when ``target_nm`` (N, 3) is a raster (module docstring),
    else None. Only the columns of ``axes`` are looked at."""
    tgt = np.asarray(target_nm, dtype=float)
    moving = moving_samples(tgt)
    best: tuple[str, list[Line]] | None = None
    for a in axes:
        found = find_lines(tgt[:, AXES.index(a)])
        if len(found) < 2:
            continue
        lengths = np.array([np.ptp(tgt[ln.start:ln.stop, AXES.index(a)]) for ln in found])
        alike = np.abs(lengths - np.median(lengths)) <= LENGTH_TOL * np.median(lengths)
        covered = sum(ln.n for ln in found)
        if covered < RASTER_SHARE * moving or np.mean(alike) < RASTER_ALIKE:
            continue
        if best is None or covered > sum(ln.n for ln in best[1]):
            best = (a, found)
    return best


def moving_samples(target_nm: np.ndarray) -> int:
    """How many samples of ``target_nm`` (N, 3) [nm] lie between its first move and its
    last: the rests at its start and end (a wave table's padding) left out."""
    tgt = np.asarray(target_nm, dtype=float)
    if len(tgt) < 2:
        return len(tgt)
    changed = np.flatnonzero(np.any(np.diff(tgt, axis=0) != 0.0, axis=1))
    return int(changed[-1] - changed[0] + 2) if changed.size else 0


def judged_part(target_nm: np.ndarray, axes: str = AXES, central_pct: float = REPORT_CENTRAL_PCT
                ) -> tuple[np.ndarray, str, tuple[str, list[Line]] | None]:
    """The samples judged (a boolean mask), the part in words, and the raster's fast axis
    and lines (None without)."""
    n = len(target_nm)
    raster = raster_lines(target_nm, axes)
    if raster is None:
        return np.ones(n, bool), f"the whole record ({n} samples)", None
    fast, lines = raster
    judged, which = judged_lines(lines)
    mask = lines_mask(n, judged, central_pct) > 0
    return mask, f"the central {central_pct:g} % of {which}; {fast} is the fast axis", raster


def reference_nm(target: np.ndarray, axis: str, raster: tuple[str, list[Line]] | None) -> tuple[str | None, float | None]:
    """What axis ``axis``'s percentages refer to and its length [nm] (module docstring);
    ``target``: the axis's column (N,)."""
    if np.ptp(target) < MIN_SPAN_NM:
        return None, None
    if raster is None:
        return "range", float(np.ptp(target))
    fast, lines = raster
    moving = moving_spans_nm(target, lines)
    if axis == fast:
        return "line", float(np.median(moving))
    if moving.size:
        return "step", float(np.median(moving))
    return "range", float(np.ptp(target))


def axis_errors(target_nm: np.ndarray, position_nm: np.ndarray, axes: str = AXES,
                central_pct: float = REPORT_CENTRAL_PCT) -> ErrorReport:
    """Per-axis errors of ``position_nm`` against ``target_nm`` (both (N, 3) [nm], columns
    x, y, z) over the judged part (module docstring), for the axes named in ``axes``."""
    tgt = np.asarray(target_nm, dtype=float)
    err = np.asarray(position_nm, dtype=float) - tgt
    mask, part, raster = judged_part(tgt, axes, central_pct)
    out = []
    for a in axes:
        k = AXES.index(a)
        e = err[mask, k]
        ref, length = reference_nm(tgt[:, k], a, raster)
        out.append(AxisError(a, float(np.max(np.abs(e))) if e.size else float("nan"),
                             float(np.sqrt(np.mean(e * e))) if e.size else float("nan"), ref, length))
    return ErrorReport(part, int(np.count_nonzero(mask)), out)
