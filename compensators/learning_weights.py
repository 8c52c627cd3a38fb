"""Where accuracy matters: the lines of a raster, found in its target, and the error weight.

An AFM images along the central part of each scan line; at the turnarounds the amplifier
cannot follow the sharp corner of a triangle (slew limit, band limit), and an error there
that the learning tried to remove would pull the table off the lines. :func:`find_lines`
finds the lines of a target — maximal runs of one slope sign in which the slope stays
within :data:`SLOPE_TOL` of the run's median over :data:`LINEAR_SHARE` of the run (a
straight ramp; a smooth approach is not one) — and :func:`error_weights` gives weight 1 to
the central ``central_pct`` % of each line and 0 around its ends (on both sides of each
corner); everything else (rests, smooth approaches) keeps weight 1 unless ``lines_only``.

:func:`error_figures` is the report: max / RMS error in % of the target's span over the
whole record and over the central 80 % of each line.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: a line's slope stays within this fraction of its median slope …
SLOPE_TOL = 0.05
#: … over at least this share of its samples
LINEAR_SHARE = 0.9
#: a line is at least this many samples long
MIN_LINE_SAMPLES = 16
#: the share of each line the error report calls "central" [%]
REPORT_CENTRAL_PCT = 80.0


@dataclass(frozen=True)
class Line:
    """One line (a straight ramp) of a raster: samples ``start`` … ``stop − 1``, ``rising``
    or falling."""

    start: int
    stop: int
    rising: bool = True

    @property
    def n(self) -> int:
        return self.stop - self.start

    def central(self, pct: float) -> slice:
        """The central ``pct`` % of the line."""
        m = int(round(self.n * (100.0 - pct) / 200.0))
        return slice(self.start + m, self.stop - m)


def find_lines(y_nm: np.ndarray) -> list[Line]:
    """The straight ramps (lines) of ``y_nm`` (module docstring), in order."""
    y = np.asarray(y_nm, dtype=float)
    if y.size < MIN_LINE_SAMPLES:
        return []
    d = np.diff(y)
    scale = float(np.max(np.abs(d)))
    if scale <= 0:
        return []
    sign = np.where(np.abs(d) > 1e-6 * scale, np.sign(d), 0.0)
    edges = np.flatnonzero(np.diff(sign)) + 1
    starts = np.concatenate([[0], edges])
    stops = np.concatenate([edges, [d.size]])
    lines = []
    for a, b in zip(starts, stops):
        if sign[a] == 0 or b - a < MIN_LINE_SAMPLES:
            continue
        seg = d[a:b]
        med = float(np.median(seg))
        if np.mean(np.abs(seg - med) <= SLOPE_TOL * abs(med)) >= LINEAR_SHARE:
            lines.append(Line(int(a), int(b) + 1, med > 0))    # differences a..b-1 join samples a..b
    return lines


def raster_lines(lines: list[Line]) -> list[list[Line]]:
    """The ramps of :func:`find_lines` grouped into the raster's lines: a ramp and the one
    right after it in the other direction (a trace and its retrace) make one line; a ramp
    with no such partner (a trace-only raster's, whose flyback is no straight ramp) is a
    line of its own."""
    groups: list[list[Line]] = []
    k = 0
    while k < len(lines):
        a = lines[k]
        b = lines[k + 1] if k + 1 < len(lines) else None
        if b is not None and b.start - a.stop <= max(2, a.n // 10) and a.rising != b.rising:
            groups.append([a, b])
            k += 2
        else:
            groups.append([a])
            k += 1
    return groups


def judged_lines(lines: list[Line], named: tuple[int, ...] | None = None) -> tuple[list[Line], str]:
    """The ramps whose central part the error is judged on, and a phrase saying which: by
    default every raster line (:func:`raster_lines`) but the first (the scanner starts it
    from rest and cannot follow its first milliseconds), all of them when there is only
    one; ``named``: the raster lines (1-based) to judge instead. Raises ``ValueError``
    naming a line the raster does not have."""
    groups = raster_lines(lines)
    if named:
        bad = [k for k in named if not 1 <= k <= len(groups)]
        if bad:
            raise ValueError(f"judged line {bad[0]}: the target has raster lines 1..{len(groups)}")
        picked = sorted(set(named))
        return [ln for k in picked for ln in groups[k - 1]], f"lines {_ranges(picked)} of {len(groups)} (as named)"
    if len(groups) < 2:
        return [ln for g in groups for ln in g], f"{'the only line' if groups else 'no line'}"
    return ([ln for g in groups[1:] for ln in g],
            f"lines 2..{len(groups)} of {len(groups)} (every line but the first, which starts from rest)")


def _ranges(ks: list[int]) -> str:
    out, start = [], ks[0]
    for a, b in zip(ks, ks[1:] + [-1]):
        if b != a + 1:
            out.append(f"{start}" if start == a else f"{start}..{a}")
            start = b
    return ", ".join(out)


def error_weights(y_nm: np.ndarray, central_pct: float = 80.0, lines_only: bool = False,
                  lines: list[Line] | None = None) -> np.ndarray:
    """Weight per sample (0 or 1) of the learning error (module docstring). No lines found:
    all ones. ``central_pct`` 100 weights every sample of a line."""
    y = np.asarray(y_nm, dtype=float)
    found = find_lines(y) if lines is None else lines
    if not found or central_pct >= 100.0:
        return np.ones(y.size) if not (found and lines_only) else lines_mask(y.size, found, 100.0)
    w = np.zeros(y.size) if lines_only else np.ones(y.size)
    for ln in found:
        m = int(round(ln.n * (100.0 - central_pct) / 200.0))
        w[max(0, ln.start - m): ln.start + m] = 0.0
        w[max(0, ln.stop - m): ln.stop + m] = 0.0
    return np.maximum(w, lines_mask(y.size, found, central_pct))


def rounded_reference(y_nm: np.ndarray, weights: np.ndarray, lines: list[Line]) -> np.ndarray:
    """``y_nm`` with its corners inside the zero-weight zones around the line ends replaced
    by a Gaussian-smoothed copy whose σ is a third of the zone's half-width, so the
    rounding stays inside the zone and the weighted parts are untouched: a reference the
    scanner can follow at the turnarounds, which the learning may then also track there
    (at a lower weight) instead of leaving the turnarounds to chance."""
    y = np.asarray(y_nm, dtype=float)
    if not lines:
        return y.copy()
    from scipy.ndimage import gaussian_filter1d

    zero = weights <= 0
    if not np.any(zero):
        return y.copy()
    edges = np.flatnonzero(np.diff(zero.astype(int)))
    runs = np.diff(np.concatenate([[0], edges + 1, [y.size]]))
    half = max(1.0, float(np.median(runs[::2] if zero[0] else runs[1::2])) / 2.0)
    smooth = gaussian_filter1d(y, half / 3.0, mode="nearest")
    return np.where(zero, smooth, y)


def learning_weights(zone_weights: np.ndarray, lines: list[Line], judged: list[Line],
                     turnaround_weight: float) -> np.ndarray:
    """The weight per sample the learning gives the error: 1 where ``zone_weights``
    (:func:`error_weights`) is positive, ``turnaround_weight`` in the turnaround zones, and
    0 on a raster line that is not ``judged`` between judged ones and — when the raster
    starts moving less than one line's time after the record starts — on everything before
    the first judged line. The learning filter is non-causal (the scanner's inverse acts
    ahead of the error it removes); a line that starts with the record leaves it no time
    before it, and a change learned there is a truncated one that only moves the lines after
    it (on the shared reference scanners, whose rasters start at their first sample, learning
    the first line too left 0.18 % instead of 0.11 % at 100 lines/s); after an approach or a
    rest of at least a line's time the first line is learned like the others (the in-house
    benchmark's model-free law, learning from a linear calibration 92 % off on its first
    line, stayed at 5 % on the second line without it and reached 0.04 % with it), and
    with it the last line's time of that rest, where the non-causal inverse acts ahead of
    the first line; the rest before that (a wave table's padding, where the scanner creeps
    after its approach) is not learned, nor what follows the last judged line by more than
    a line's time. Learning there moved the table's first row, the approach's end, by up to
    1.5 V from play to play (the creep after the approach then differs every play), and the
    creep transient learned into the rest took the hysteresis inverse to a deeper reversal
    just before the raster (on the simulated E-727 at 200 lines/s: the change in the rest
    fell back to 0.14 V and jumped by 0.6 V within the first line).
    Where the weight falls to 0 it does so along a raised cosine over :func:`taper_samples`
    samples, inside the unjudged part: a hard edge would put the error's jump there into
    every frequency, and the scanner's inverse, large at high frequencies, answers it with
    voltage spikes (on the in-house 300 Hz plant, steps the amplifier could not slew, which
    turned 0.14 % into 1.0 % and then 4.9 %)."""
    w = np.where(zone_weights > 0, 1.0, turnaround_weight if lines else 0.0)
    if not judged:
        return w
    groups = raster_lines(lines)
    first = min(ln.start for ln in judged)
    spans = [(g[0].start, g[-1].stop) for g in groups if g[0] not in judged and g[0].start >= first]
    lead = groups[0][-1].stop - groups[0][0].start            # one raster line's time [samples]
    if groups[0][0] not in judged and groups[0][0].start < lead:
        spans.insert(0, (0, first))
    elif groups[0][0].start > lead:
        spans.insert(0, (0, groups[0][0].start - lead))
    last = max(ln.stop for ln in judged)
    if w.size - last > lead:
        spans.append((last + lead, w.size))
    width = taper_samples(w.size, lines)
    fall = 0.5 + 0.5 * np.cos(np.pi * np.arange(1, width + 1) / (width + 1))      # 1 → 0, ends excluded
    keep = np.ones(w.size)
    for a, b in spans:
        keep[a:b] = 0.0
        k = min(width, (b - a) // 2 if a > 0 else b - a)
        if a > 0:
            keep[a:a + k] = fall[:k]
        if b < w.size:
            keep[b - k:b] = np.maximum(keep[b - k:b], fall[:k][::-1])
    return w * keep


#: the raised-cosine edge of :func:`learning_weights`: this share of a raster line (the
#: judged part's margin at each end), or of the record without lines …
TAPER_SHARE = (100.0 - REPORT_CENTRAL_PCT) / 200.0
#: … and at least this many samples
MIN_TAPER = 8


def taper_samples(n: int, lines: list[Line]) -> int:
    """The width [samples] of :func:`learning_weights`' raised-cosine edges."""
    length = float(np.median([ln.n for ln in lines])) if lines else float(n) / 10.0
    return max(MIN_TAPER, int(round(TAPER_SHARE * length)))


def lines_mask(n: int, lines: list[Line], pct: float) -> np.ndarray:
    """1 on the central ``pct`` % of each line, 0 elsewhere (``n`` samples)."""
    w = np.zeros(n)
    for ln in lines:
        w[ln.central(pct)] = 1.0
    return w


def error_figures(y_nm: np.ndarray, target_nm: np.ndarray, lines: list[Line] | None = None,
                  judged: list[Line] | None = None) -> dict[str, float]:
    """``max_pct``, ``rms_pct`` over the whole record and, when the target has lines,
    ``central_max_pct`` / ``central_rms_pct`` over the central 80 % of each line and (with
    ``judged``, :func:`judged_lines`) ``judged_max_pct`` / ``judged_rms_pct`` over the central
    80 % of the judged ones; % of the target's span (peak to peak) [nm], of the line for
    the line figures. ``line_nm``: the line's length [nm] (the span without lines)."""
    tgt = np.asarray(target_nm, dtype=float)
    e = np.asarray(y_nm, dtype=float) - tgt
    span = float(np.ptp(tgt)) or 1.0
    pct = 100.0 * e / span
    out = {"max_pct": float(np.max(np.abs(pct))), "rms_pct": float(np.sqrt(np.mean(pct * pct))), "line_nm": span}
    found = find_lines(tgt) if lines is None else lines
    if found:
        line = line_span_nm(tgt, found)
        out["line_nm"] = line
        for key, part in (("central", found), ("judged", judged)):
            if part:
                c = 100.0 * e[lines_mask(tgt.size, part, REPORT_CENTRAL_PCT) > 0] / line
                out[f"{key}_max_pct"] = float(np.max(np.abs(c)))
                out[f"{key}_rms_pct"] = float(np.sqrt(np.mean(c * c)))
    return out


#: a target moving less than this [nm] over a line holds there (a slow axis during a trace)
HOLD_NM = 1.0


def moving_spans_nm(target_nm: np.ndarray, lines: list[Line]) -> np.ndarray:
    """The spans [nm] of ``target_nm`` over each line on which it moves (by at least
    :data:`HOLD_NM`)."""
    spans = np.array([np.ptp(target_nm[ln.start:ln.stop]) for ln in lines])
    return spans[spans >= HOLD_NM]


def line_span_nm(target_nm: np.ndarray, lines: list[Line]) -> float:
    """The length of the raster's lines [nm] along ``target_nm``: the median of its spans
    over the lines on which it moves (for a slow axis judged on the fast axis's lines, its
    step per line); 1 without lines or movement."""
    moving = moving_spans_nm(target_nm, lines)
    return float(np.median(moving)) if moving.size else 1.0


def judged_max_pct(y_nm: np.ndarray, target_nm: np.ndarray, named: tuple[int, ...] | None = None) -> float:
    """The largest error [% of the line] over the central 80 % of the judged raster lines
    (:func:`judged_lines`; of the span over the whole record without lines): the figure
    ``afmctl learn`` prints per axis, for a recording checked the same way."""
    tgt = np.asarray(target_nm, dtype=float)
    found = find_lines(tgt)
    fig = error_figures(y_nm, tgt, found, judged_lines(found, named)[0] if found else None)
    return fig.get("judged_max_pct", fig["max_pct"])
