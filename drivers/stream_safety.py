"""Safety check of a block of samples for a device-timed (buffered) stream.

Every sample is checked before any of the block is queued: a finite number of volts, inside
the axis limits, and no step from the previous sample (the first one: from ``prev_V``, the
last sample queued or the output when the stream started) larger than ``max_step_V`` — the
slew limit times the sample period. Plain Python (drivers do not import numpy); a numpy
array of shape (n, axes) is accepted as rows.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence

from .base import VoltageLimits
from .errors import LimitError


def check_block(block_V: Sequence[Sequence[float]], axes: Sequence[str], limits: Mapping[str, VoltageLimits],
                prev_V: Mapping[str, float], max_step_V: float | None,
                quantize: Callable[[float, float, float], float] | None = None) -> list[tuple[float, ...]]:
    """``block_V`` rows of one voltage per axis [V] (in ``axes`` order) → the rows as float
    tuples; LimitError naming the sample index and axis on the first violation.
    ``quantize(v, low, high)``: each value checked (finite, inside the limits) becomes the
    value the device is sent (e.g. the frame's nearest step inside the limits), and the
    step from the previous sample is checked on what is sent."""
    rows: list[tuple[float, ...]] = []
    lows = [limits[a].min_V for a in axes]
    highs = [limits[a].max_V for a in axes]
    prev = [prev_V.get(a) for a in axes]
    for i, row in enumerate(block_V):
        try:
            values = tuple(float(v) for v in row)
        except (TypeError, ValueError):
            raise LimitError(f"stream sample {i}: {row!r} is not a row of volts") from None
        if len(values) != len(axes):
            raise LimitError(f"stream sample {i}: {len(values)} values, expected one per axis ({', '.join(axes)})")
        for j, v in enumerate(values):
            a = axes[j]
            if not math.isfinite(v):
                raise LimitError(f"stream sample {i}, axis {a}: {v!r} V is not a finite voltage")
            if not lows[j] <= v <= highs[j]:
                raise LimitError(f"stream sample {i}, axis {a}: {v:g} V outside the limits "
                                 f"[{lows[j]:g}, {highs[j]:g}] V")
        if quantize is not None:
            values = tuple(quantize(v, lo, hi) for v, lo, hi in zip(values, lows, highs))
        for j, v in enumerate(values):
            a = axes[j]
            p = prev[j]
            if max_step_V is not None and p is not None and abs(v - p) > max_step_V:
                raise LimitError(f"stream sample {i}, axis {a}: step {p:g} V -> {v:g} V exceeds "
                                 f"{max_step_V:g} V per sample")
        prev = list(values)
        rows.append(values)
    return rows
