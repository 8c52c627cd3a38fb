"""What goes into a run of :class:`afmctl.control.controller.Controller`, checked before it
reaches the loop thread: trajectory sources as iterators of blocks, run-time segments resampled
to the loop period, drift measurements for the Kalman filter, and the feeder that moves
blocks into the loop's sample deque. Bad input raises :class:`afmctl.errors.AfmctlError` with
one line naming the field and the allowed range.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from ..errors import AfmctlError, error_line
from ..inputs import trajectories
from ..inputs.trajectories import check_positions, resample
from .machine import END_OF_TRAJECTORY

log = logging.getLogger(__name__)

#: largest run-time segment after resampling to the loop period [samples]
MAX_SEGMENT_SAMPLES = 1_000_000


def as_block(arr: Any, where: str = "trajectory") -> np.ndarray:
    """Validate a block of positions (N, 3) [nm]; returns it as a float64 array."""
    a = np.ascontiguousarray(arr, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise AfmctlError(f"{where}: positions must have shape (N, 3) [nm], got {a.shape}")
    check_positions(a, lambda i: f"{where}: sample {i}")
    return a


def flat(rows: np.ndarray) -> list[float]:
    """A block as one flat list x0, y0, z0, x1, ... (one GC-tracked object per block)."""
    return rows.ravel().tolist()


def source_blocks(source: Any, dt_s: float, block_samples: int) -> tuple[bool, bool, Iterator | None]:
    """``Controller.start``'s source → (queue mode, end the queue when idle, iterator of
    blocks (N, 3) [nm] or None in queue mode). ``source``: None (run-time segments), a
    trajectory spec of :mod:`afmctl.config`, an array (N, 3) [nm] at the loop period ``dt_s``
    [s], or an iterable of such blocks."""
    if source is None:
        return True, False, None
    if getattr(source, "kind", None) == "queue":
        return True, source.idle == "end", None
    if hasattr(source, "blocks_at"):
        return False, False, iter(source.blocks_at(dt_s, block_samples))
    if hasattr(source, "kind"):
        return False, False, iter(trajectories.build(source, dt_s, block_samples))
    if isinstance(source, np.ndarray):
        return False, False, iter(trajectories.blocks_of(source, block_samples))
    if isinstance(source, Iterable):
        return False, False, iter(source)
    raise AfmctlError(f"start: unsupported trajectory source {type(source).__name__}")


def check_segment_dt(dt_s: Any) -> float:
    """A segment's sample period [s], 1e-6..10 s."""
    try:
        dt = float(dt_s)
    except (TypeError, ValueError):
        raise AfmctlError(f"segment: dt_s {dt_s!r} is not a number") from None
    if not (math.isfinite(dt) and 1e-6 <= dt <= 10.0):
        raise AfmctlError(f"segment: dt_s {dt_s!r} outside the allowed range 1e-6..10 s")
    return dt


def segment_rows(positions_nm: Any, dt_s: float, loop_dt_s: float) -> np.ndarray:
    """A segment (N, 3) [nm] sampled every ``dt_s`` [s], validated and resampled to the loop
    period ``loop_dt_s`` [s] (at most :data:`MAX_SEGMENT_SAMPLES` samples)."""
    src = as_block(positions_nm, "segment")  # validate before resampling
    n_out = int(math.floor(max(len(src) - 1, 0) * dt_s / loop_dt_s + 1e-9)) + 1
    if n_out > MAX_SEGMENT_SAMPLES:
        raise AfmctlError(f"segment: {len(src)} samples every {dt_s:g} s make {n_out} loop samples; "
                          f"at most {MAX_SEGMENT_SAMPLES} per segment (split it)")
    return as_block(resample(np.asarray(positions_nm, dtype=np.float64), dt_s, loop_dt_s), "segment")


def _number_or_nan(v: Any) -> float:
    if isinstance(v, (str, bytes, bool)):
        return math.nan
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def check_drift_measurement(pipeline: Any, measured_drift_nm: Any, std_nm: Any,
                            t_s: Any) -> tuple[tuple[float, float, float], float, float]:
    """A drift measurement for the Kalman filter, checked: (drift x, y, z [nm] with NaN for an
    axis not measured, 1-σ [nm], controller time [s] or NaN for now)."""
    if getattr(pipeline, "kalman", None) is None:
        raise AfmctlError("drift-measurement: the Kalman filter is off "
                          "(set compensation.drift.enabled = true and compensation.drift.kalman = true)")
    try:
        z = np.asarray(measured_drift_nm, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        z = np.empty(0)
    if z.shape != (3,) or np.any(np.isinf(z)) or np.all(np.isnan(z)) or np.any(np.abs(z[np.isfinite(z)]) > 1e6):
        raise AfmctlError(f"drift-measurement: measured_drift_nm {measured_drift_nm!r:.80} must be 3 values "
                          "in -1e6..1e6 nm (NaN = axis not measured, at least one measured)")
    std = _number_or_nan(std_nm)
    if not (math.isfinite(std) and 1e-6 <= std <= 1e6):
        raise AfmctlError(f"drift-measurement: std_nm {std_nm!r:.40} outside the allowed range 1e-6..1e6 nm")
    t = math.nan
    if t_s is not None:
        t = _number_or_nan(t_s)
        if not (math.isfinite(t) and 0.0 <= t <= 1e7):
            raise AfmctlError(f"drift-measurement: t_s {t_s!r:.40} outside the allowed range 0..1e7 s "
                              "(controller time since start)")
    return (float(z[0]), float(z[1]), float(z[2])), std, t


def feed_blocks(ctl: Any, it: Iterator) -> None:
    """Feeder thread of ``ctl``: split the trajectory's blocks into ``loop.block_samples`` and
    append them to the loop's sample deque, keeping at most ``loop.prefetch_blocks`` ahead,
    until the trajectory ends (then the end marker) or the run stops (``_feed_stop``). A
    trajectory that fails ends the run safely (``_feed_error``, then the end marker)."""
    bs = ctl.config.loop.block_samples
    prefetch = ctl.config.loop.prefetch_blocks
    dq = ctl._deque
    try:
        for blk in it:
            rows = as_block(blk)
            for k in range(0, len(rows), bs):
                while len(dq) >= prefetch and not ctl._feed_stop:
                    time.sleep(0.002)
                if ctl._feed_stop:
                    return
                dq.append(flat(rows[k:k + bs]))
    except Exception as err:  # a trajectory generator failed: end the run safely
        ctl._feed_error = error_line(err)
        log.error("trajectory: %s", ctl._feed_error)
    dq.append(END_OF_TRAJECTORY)
