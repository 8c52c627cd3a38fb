"""Trajectory sources: target positions [nm] for x, y, z at the loop's sample period.

Every source is a generator of blocks — float64 arrays of shape (N, 3), columns x, y, z in
nm, one row per sample period ``dt_s`` — so that a long scan never needs all its samples
in memory. :func:`build` turns a trajectory spec of :mod:`afmctl.config` into such a
generator; :func:`collect` concatenates one (for tests and short paths).

Sources:

* :func:`raster` — raster scans, trace/retrace or bidirectional (serpentine);
* :func:`moves` — point-to-point moves with jerk-limited profiles (:func:`smooth_move`);
* :func:`indentation_array` — the indentation array of the extended-PI paper (Fig. 9):
  approach each grid point, press ``depth_nm`` down, dwell, lift;
* :func:`text` — imprint a text path with the single-stroke font of
  :mod:`afmctl.inputs.textpath` ('NK' as in the image-based paper, Sec. 4.3);
* :func:`spiral` — Archimedean spiral at constant speed;
* :func:`from_file` — CSV (``t,x,y,z`` s, nm) or NPY (N, 4) resampled to ``dt_s``;
* run-time segments go through :meth:`afmctl.control.controller.Controller.submit_segment`.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from ..errors import AfmctlError

Block = np.ndarray


def blocks_of(positions_nm: np.ndarray, block_samples: int = 256) -> Iterator[Block]:
    """Split an (N, 3) array into blocks of at most ``block_samples`` rows."""
    p = np.asarray(positions_nm, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise AfmctlError(f"trajectory: positions must have shape (N, 3) [nm], got {p.shape}")
    for k in range(0, len(p), block_samples):
        yield p[k:k + block_samples]


def resample(positions_nm: np.ndarray, dt_in_s: float, dt_out_s: float) -> np.ndarray:
    """Linear resampling of (N, 3) positions [nm] from period ``dt_in_s`` to ``dt_out_s`` [s]
    (the input unchanged when the periods agree or it has fewer than 2 samples)."""
    p = np.asarray(positions_nm, dtype=np.float64)
    if abs(dt_in_s - dt_out_s) <= 1e-12 * dt_out_s or len(p) < 2:
        return p
    t_end = (len(p) - 1) * dt_in_s
    n = int(math.floor(t_end / dt_out_s + 1e-9)) + 1
    t_out = np.arange(n) * dt_out_s
    t_in = np.arange(len(p)) * dt_in_s
    return np.column_stack([np.interp(t_out, t_in, p[:, k]) for k in range(3)])


def collect(blocks: Iterable[Block]) -> np.ndarray:
    """Concatenate a block generator into one (N, 3) array."""
    parts = [np.asarray(b, dtype=np.float64).reshape(-1, 3) for b in blocks]
    return np.concatenate(parts) if parts else np.zeros((0, 3))


# --------------------------------------------------------------------------- moves
#: peak |velocity|, |acceleration|, |jerk| of the quintic s(τ) = 10τ³ − 15τ⁴ + 6τ⁵ for a
#: unit distance in unit time
_Q_V, _Q_A, _Q_J = 1.875, 10.0 / math.sqrt(3.0), 60.0


def move_duration(distance_nm: float, v_max: float, a_max: float, j_max: float) -> float:
    """Shortest duration [s] of a quintic move over ``distance_nm`` whose peak velocity,
    acceleration and jerk stay within the limits (nm/s, nm/s², nm/s³)."""
    d = abs(distance_nm)
    if d == 0.0:
        return 0.0
    return max(_Q_V * d / v_max, math.sqrt(_Q_A * d / a_max), (_Q_J * d / j_max) ** (1.0 / 3.0))


def smooth_move(p0: Sequence[float], p1: Sequence[float], dt_s: float, v_max: float = 5000.0,
                a_max: float = 1e5, j_max: float = 1e7) -> np.ndarray:
    """Samples (N, 3) [nm] of a straight move from ``p0`` (excluded) to ``p1`` (included)
    along the minimum-jerk quintic, timed so that |v| ≤ v_max, |a| ≤ a_max, |j| ≤ j_max
    (bounded jerk: an S-curve). A zero-length move gives no samples."""
    a = np.asarray(p0, dtype=np.float64)
    b = np.asarray(p1, dtype=np.float64)
    dist = math.hypot(*(b - a))  # no underflow for tiny moves
    if dist == 0.0:
        return np.zeros((0, 3))
    T = move_duration(dist, v_max, a_max, j_max)
    n = max(1, int(math.ceil(T / dt_s - 1e-9)))
    tau = np.arange(1, n + 1) / n
    s = tau ** 3 * (10.0 - 15.0 * tau + 6.0 * tau ** 2)
    return a + s[:, None] * (b - a)


def hold(p: Sequence[float], duration_s: float, dt_s: float) -> np.ndarray:
    """Samples (N, 3) holding position ``p`` for ``duration_s``."""
    n = int(round(duration_s / dt_s))
    return np.tile(np.asarray(p, dtype=np.float64), (n, 1))


def moves(points: Sequence[Sequence[float]], dt_s: float, *, start: Sequence[float] = (0.0, 0.0, 0.0),
          dwell_s: Sequence[float] | float = 0.0, v_max: float = 5000.0, a_max: float = 1e5,
          j_max: float = 1e7) -> Iterator[Block]:
    """Point-to-point moves through ``points`` (each (x, y, z) nm), starting at ``start``
    (which is emitted as the first sample), dwelling ``dwell_s`` after each arrival."""
    pts = [np.asarray(p, dtype=np.float64) for p in points]
    dw = [float(dwell_s)] * len(pts) if np.isscalar(dwell_s) else [float(d) for d in dwell_s]  # type: ignore[arg-type]
    cur = np.asarray(start, dtype=np.float64)
    yield cur[None, :].copy()
    for p, d in zip(pts, dw):
        seg = smooth_move(cur, p, dt_s, v_max, a_max, j_max)
        if len(seg):
            yield seg
        if d > 0:
            h = hold(p, d, dt_s)
            if len(h):
                yield h
        cur = p


# --------------------------------------------------------------------------- raster
def raster(dt_s: float, *, x0_nm: float = 0.0, y0_nm: float = 0.0, z_nm: float = 0.0,
           width_nm: float = 1000.0, height_nm: float = 1000.0, lines: int = 64, line_rate_Hz: float = 1.0,
           mode: str = "trace-retrace", fast_axis: str = "x", repeat: int = 1) -> Iterator[Block]:
    """A raster scan, one block per line.

    ``trace-retrace``: each line takes ``1/line_rate_Hz``: the trace (fast axis from start
    to end at constant speed, slow axis still) in the first half, the retrace back in the
    second half while the slow axis steps to the next line (linear, no jump).
    ``bidirectional``: a serpentine; each line (one direction) takes ``1/line_rate_Hz`` and
    the slow axis advances linearly during it. Frames repeat ``repeat`` times with a smooth
    return to the start in between.
    """
    if mode not in ("trace-retrace", "bidirectional"):
        raise AfmctlError(f"trajectory.mode: {mode!r}; allowed: trace-retrace, bidirectional")
    T = 1.0 / line_rate_Hz
    pitch = height_nm / (lines - 1) if lines > 1 else 0.0
    fi, si = (0, 1) if fast_axis == "x" else (1, 0)
    f0 = x0_nm if fi == 0 else y0_nm
    s0 = y0_nm if fi == 0 else x0_nm
    if mode == "trace-retrace":
        n_half = max(1, int(round(T / 2 / dt_s)))
        ramp = np.arange(n_half) / n_half                   # 0 … (n−1)/n
        up = f0 + width_nm * ramp
        down = f0 + width_nm * (1.0 - ramp)
    else:
        n_line = max(1, int(round(T / dt_s)))
        ramp = np.arange(n_line) / n_line
    for frame in range(repeat):
        for k in range(lines):
            if mode == "trace-retrace":
                blk = np.empty((2 * n_half, 3))
                blk[:, 2] = z_nm
                blk[:n_half, fi] = up
                blk[n_half:, fi] = down
                blk[:n_half, si] = s0 + k * pitch
                nxt = k + 1 if k + 1 < lines else k
                blk[n_half:, si] = s0 + k * pitch + (nxt - k) * pitch * ramp
            else:
                blk = np.empty((n_line, 3))
                blk[:, 2] = z_nm
                blk[:, fi] = f0 + width_nm * (ramp if k % 2 == 0 else 1.0 - ramp)
                nxt = k + 1 if k + 1 < lines else k
                blk[:, si] = s0 + k * pitch + (nxt - k) * pitch * ramp
            yield blk
        last = blk[-1].copy()
        if mode == "trace-retrace":
            last[fi] = f0
        else:
            last[fi] = f0 + (width_nm if (lines - 1) % 2 == 0 else 0.0)
        yield last[None, :]
        if frame + 1 < repeat:
            start = np.zeros(3)
            start[fi], start[si], start[2] = f0, s0, z_nm
            seg = smooth_move(last, start, dt_s, v_max=max(width_nm, height_nm) * line_rate_Hz * 2)
            if len(seg):
                yield seg


# --------------------------------------------------------------------------- indentation, text
def _move(p0: np.ndarray, p1: np.ndarray, dt_s: float, v_max: float, a_max: float,
          j_max: float) -> Iterator[Block]:
    """The samples of :func:`smooth_move` as a block, unless the move is empty."""
    seg = smooth_move(p0, p1, dt_s, v_max, a_max, j_max)
    if len(seg):
        yield seg


def indentation_array(dt_s: float, *, x0_nm: float = 0.0, y0_nm: float = 0.0, nx: int = 5, ny: int = 5,
                      pitch_x_nm: float = 500.0, pitch_y_nm: float = 500.0, z_up_nm: float = 0.0,
                      depth_nm: float = 100.0, dwell_s: float = 0.05, v_max: float = 5000.0, a_max: float = 1e5,
                      j_max: float = 1e7) -> Iterator[Block]:
    """The indentation array of the extended-PI paper (Sec. IV, Fig. 9): an ``nx × ny``
    grid (serpentine order). At each point the tip is lowered ``depth_nm`` below ``z_up_nm``,
    held ``dwell_s`` and lifted again; moves between points are jerk-limited at ``z_up_nm``.
    The indents mark where the tip really was, so the array measures positioning error."""
    cur = np.array([x0_nm, y0_nm, z_up_nm], dtype=np.float64)
    yield cur[None, :].copy()
    for j in range(ny):
        cols = range(nx) if j % 2 == 0 else range(nx - 1, -1, -1)
        for i in cols:
            p = np.array([x0_nm + i * pitch_x_nm, y0_nm + j * pitch_y_nm, z_up_nm])
            yield from _move(cur, p, dt_s, v_max, a_max, j_max)
            down = p.copy()
            down[2] = z_up_nm - depth_nm
            yield from _move(p, down, dt_s, v_max, a_max, j_max)
            h = hold(down, dwell_s, dt_s)
            if len(h):
                yield h
            yield from _move(down, p, dt_s, v_max, a_max, j_max)
            cur = p


def text(dt_s: float, *, text: str = "NK", x0_nm: float = 0.0, y0_nm: float = 0.0, height_nm: float = 2000.0,
         z_up_nm: float = 0.0, z_down_nm: float = -50.0, speed_nm_per_s: float = 2000.0,
         a_max: float = 1e5, j_max: float = 1e7) -> Iterator[Block]:
    """Imprint ``text`` (single-stroke font, :mod:`afmctl.inputs.textpath`): for each stroke, move
    at ``z_up_nm`` to its start, lower to ``z_down_nm``, follow the polyline (jerk-limited
    per segment, peak speed ``speed_nm_per_s``), lift. Starts at (x0, y0, z_up)."""
    from .textpath import strokes
    cur = np.array([x0_nm, y0_nm, z_up_nm], dtype=np.float64)
    yield cur[None, :].copy()
    v = speed_nm_per_s
    for st in strokes(text, height_nm, x0_nm, y0_nm):
        first = np.array([st[0, 0], st[0, 1], z_up_nm])
        yield from _move(cur, first, dt_s, v, a_max, j_max)
        pen = first.copy()
        pen[2] = z_down_nm
        yield from _move(first, pen, dt_s, v, a_max, j_max)
        for q in st[1:]:
            nxt = np.array([q[0], q[1], z_down_nm])
            yield from _move(pen, nxt, dt_s, v, a_max, j_max)
            pen = nxt
        up = pen.copy()
        up[2] = z_up_nm
        yield from _move(pen, up, dt_s, v, a_max, j_max)
        cur = up


# --------------------------------------------------------------------------- spiral, file
def spiral(dt_s: float, *, cx_nm: float = 500.0, cy_nm: float = 500.0, z_nm: float = 0.0, radius_nm: float = 500.0,
           pitch_nm: float = 50.0, speed_nm_per_s: float = 2000.0, block_samples: int = 4096) -> Iterator[Block]:
    """Archimedean spiral ``r = pitch·θ/2π`` from the centre out to ``radius_nm`` at
    constant path speed. Arc length ``s(θ) = b/2·(θ√(1+θ²) + asinh θ)``, ``b = pitch/2π``,
    inverted by Newton iteration per block."""
    b = pitch_nm / (2.0 * math.pi)
    theta_end = radius_nm / b

    def arc(th: np.ndarray) -> np.ndarray:
        return 0.5 * b * (th * np.sqrt(1.0 + th * th) + np.arcsinh(th))

    s_end = float(arc(np.array([theta_end]))[0])
    n_total = int(math.ceil(s_end / (speed_nm_per_s * dt_s))) + 1
    th = np.zeros(1)
    for k0 in range(0, n_total, block_samples):
        k = np.arange(k0, min(n_total, k0 + block_samples))
        s = np.minimum(k * speed_nm_per_s * dt_s, s_end)
        # initial guess: asymptotic inverse s ≈ b θ²/2
        th = np.sqrt(2.0 * s / b)
        for _ in range(30):
            f = arc(th) - s
            th = np.clip(th - f / (b * np.sqrt(1.0 + th * th)), 0.0, theta_end)
        r = b * th
        yield np.column_stack([cx_nm + r * np.cos(th), cy_nm + r * np.sin(th), np.full(len(th), z_nm)])


def from_file(path: str | Path, dt_s: float, block_samples: int = 4096) -> Iterator[Block]:
    """Positions from a CSV (header with columns ``t,x,y,z``; s, nm) or an NPY array (N, 4)
    of the same columns, linearly resampled to ``dt_s`` (NPY is memory-mapped and read a
    block at a time when already sampled at ``dt_s``).

    The file is opened and its columns checked here (a missing or malformed file raises
    :class:`AfmctlError` naming it before any sample is played); positions are checked
    block by block as they are generated."""
    p = Path(path)
    if p.suffix.lower() == ".npy":
        t, xyz_src = _open_npy(p)
    else:
        from ..data.datafiles import read_csv
        data = read_csv(p, ("t", "x", "y", "z"))
        t = data["t"]
        xyz_src = np.column_stack([t, data["x"], data["y"], data["z"]])
    if not np.all(np.isfinite(t)) or (len(t) > 1 and not np.all(np.diff(t) > 0)):
        raise AfmctlError(f"{p}: column t must be finite and strictly increasing [s]")
    return _file_blocks(p, t, xyz_src, dt_s, block_samples)


def _open_npy(p: Path) -> tuple[np.ndarray, np.ndarray]:
    """Memory-map an NPY trajectory (N, 4) t,x,y,z; returns (t [s], the array)."""
    try:
        arr = np.load(p, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as err:
        raise AfmctlError(f"{p}: cannot read NPY trajectory ({err})") from None
    if arr.ndim != 2 or arr.shape[1] != 4 or len(arr) < 1:
        raise AfmctlError(f"{p}: NPY trajectory must have shape (N, 4) with columns t,x,y,z (s, nm); "
                          f"got {arr.shape}")
    if arr.dtype.kind not in "fiu":
        raise AfmctlError(f"{p}: NPY trajectory must hold real numbers (float or int); got dtype {arr.dtype}")
    return np.asarray(arr[:, 0], dtype=np.float64), arr


def _file_blocks(p: Path, t: np.ndarray, xyz_src: np.ndarray, dt_s: float,
                 block_samples: int) -> Iterator[Block]:
    """Blocks of a checked file trajectory: as stored when sampled at ``dt_s``, else resampled."""
    cols = (1, 2, 3)
    if len(t) > 1 and np.allclose(np.diff(t), dt_s, rtol=1e-6, atol=0):
        for k in range(0, len(t), block_samples):
            blk = np.asarray(xyz_src[k:k + block_samples][:, cols], dtype=np.float64)
            check_positions(blk, lambda i: f"{p}: row {k + i + 1}")
            yield blk
        return
    t_end = t[-1] - t[0]
    n = int(math.floor(t_end / dt_s + 1e-9)) + 1
    for k0 in range(0, n, block_samples):
        tt = t[0] + np.arange(k0, min(n, k0 + block_samples)) * dt_s
        blk = np.column_stack([np.interp(tt, t, np.asarray(xyz_src[:, c], dtype=np.float64)) for c in cols])
        check_positions(blk, lambda i: f"{p}: at t = {tt[i]:g} s")
        yield blk


#: largest |position| a trajectory may ask for [nm] (the loop refuses more as well)
MAX_ABS_NM = 1e7


def check_positions(blk: np.ndarray, where) -> None:
    """Positions (N, 3) must be finite and within ±MAX_ABS_NM nm; ``where(i)`` names
    sample i in the error."""
    ok = np.isfinite(blk) & (np.abs(blk) <= MAX_ABS_NM)
    if not np.all(ok):
        bad = int(np.flatnonzero(~ok.all(axis=1))[0])
        raise AfmctlError(f"{where(bad)}: position {blk[bad].tolist()} is not finite or beyond "
                          f"±{MAX_ABS_NM:g} nm; positions x,y,z must be finite nm within that range")


# --------------------------------------------------------------------------- specs
def build(spec, dt_s: float, block_samples: int = 256) -> Iterator[Block]:
    """The block generator for a trajectory spec of :mod:`afmctl.config` (or a dict with a
    ``kind``). ``queue`` specs have no generator (segments come at run time)."""
    if isinstance(spec, dict):
        from pydantic import TypeAdapter, ValidationError

        from ..config import TrajectorySpec, format_validation_error
        try:
            spec = TypeAdapter(TrajectorySpec).validate_python(spec)
        except ValidationError as err:
            raise AfmctlError(format_validation_error(err, "trajectory", TrajectorySpec)) from None
    k = spec.kind
    if k == "raster":
        return raster(dt_s, x0_nm=spec.x0_nm, y0_nm=spec.y0_nm, z_nm=spec.z_nm, width_nm=spec.width_nm,
                      height_nm=spec.height_nm, lines=spec.lines, line_rate_Hz=spec.line_rate_Hz, mode=spec.mode,
                      fast_axis=spec.fast_axis, repeat=spec.repeat)
    if k == "moves":
        return moves([(m.x_nm, m.y_nm, m.z_nm) for m in spec.points], dt_s, start=spec.start_nm,
                     dwell_s=[m.dwell_s for m in spec.points], v_max=spec.v_max_nm_per_s,
                     a_max=spec.a_max_nm_per_s2, j_max=spec.j_max_nm_per_s3)
    if k == "indentation":
        return indentation_array(dt_s, x0_nm=spec.x0_nm, y0_nm=spec.y0_nm, nx=spec.nx, ny=spec.ny,
                                 pitch_x_nm=spec.pitch_x_nm, pitch_y_nm=spec.pitch_y_nm, z_up_nm=spec.z_up_nm,
                                 depth_nm=spec.depth_nm, dwell_s=spec.dwell_s, v_max=spec.v_max_nm_per_s,
                                 a_max=spec.a_max_nm_per_s2, j_max=spec.j_max_nm_per_s3)
    if k == "text":
        return text(dt_s, text=spec.text, x0_nm=spec.x0_nm, y0_nm=spec.y0_nm, height_nm=spec.height_nm,
                    z_up_nm=spec.z_up_nm, z_down_nm=spec.z_down_nm, speed_nm_per_s=spec.speed_nm_per_s)
    if k == "spiral":
        return spiral(dt_s, cx_nm=spec.cx_nm, cy_nm=spec.cy_nm, z_nm=spec.z_nm, radius_nm=spec.radius_nm,
                      pitch_nm=spec.pitch_nm, speed_nm_per_s=spec.speed_nm_per_s, block_samples=max(block_samples, 256))
    if k == "file":
        return from_file(spec.path, dt_s, max(block_samples, 256))
    raise AfmctlError(f"trajectory.kind: {k!r} has no generator (queue segments arrive at run time)")


class ArraySource:
    """An (N, 3) array of positions [nm] sampled every ``dt_s`` [s], as a source for
    :meth:`afmctl.control.controller.Controller.start` (resampled to the loop period)."""

    def __init__(self, positions_nm: np.ndarray, dt_s: float) -> None:
        p = np.asarray(positions_nm, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise AfmctlError(f"trajectory: positions must have shape (N, 3) [nm], got {p.shape}")
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise AfmctlError(f"trajectory: dt_s {dt_s!r} must be a finite number > 0")
        self.positions_nm = p
        self.dt_s = float(dt_s)

    def blocks_at(self, dt_s: float, block_samples: int = 256) -> Iterator[Block]:
        return blocks_of(resample(self.positions_nm, self.dt_s, dt_s), block_samples)
