"""Raster imaging with the simulated scanner, the way an AFM images a sample.

:func:`raster_image` turns a scan (size, pixels, line rate) into the whole voltage sequence
of the raster — trace (+x) and retrace (−x) of every line, y stepping line by line — runs
it through :meth:`Scanner.run <sim_backend.scanner.Scanner.run>` in one block, and reads the
sample height at the tip's ACTUAL (x, y) at every pixel. Without a compensator the
voltages are the targets divided by the nominal sensitivity (what an uncompensated AFM
does); with one, the compensator turns target positions into voltages.

Height channel (``z_mode``):

* ``"surface"`` — an ideal z feedback keeps the tip on the surface; the recorded height is
  the sample height at the actual (x, y) plus the z drift (nonlinearities paper, Fig. 17);
* ``"piezo"`` — the z voltage follows the topography under the target (x, y)
  (u_z = h/nominal z gain) and the image is the z piezo's true displacement, so z
  hysteresis, creep and dynamics show in the image as in the nonlinearities paper,
  Figs. 13–16.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from afmctl.compensators.base import ModelError, StreamingOperator

log = logging.getLogger(__name__)


@dataclass
class ScanImage:
    """Result of :func:`raster_image`. Arrays are (rows, cols); row r is line r (y target
    ascending), column c is pixel c along +x for BOTH trace and retrace (the retrace is
    flipped back so the two images overlay). Heights in nm, positions in nm, times in s."""

    trace_nm: np.ndarray
    retrace_nm: np.ndarray
    x_target_nm: np.ndarray  # (cols,)
    y_target_nm: np.ndarray  # (rows,)
    x_trace_nm: np.ndarray  # actual x at each trace pixel
    y_trace_nm: np.ndarray
    x_retrace_nm: np.ndarray
    y_retrace_nm: np.ndarray
    t_trace_s: np.ndarray  # time of each trace pixel from the start of the scan
    line_rate_Hz: float
    sample_name: str = ""
    compensated: bool = False
    signals: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def pixel_nm(self) -> float:
        """Nominal pixel size along x [nm]."""
        return float(self.x_target_nm[1] - self.x_target_nm[0]) if self.x_target_nm.size > 1 else 0.0

    @property
    def pixel_y_nm(self) -> float:
        """Nominal line spacing along y [nm]."""
        return float(self.y_target_nm[1] - self.y_target_nm[0]) if self.y_target_nm.size > 1 else self.pixel_nm

    def grating_periods_nm(self, axis: str = "x", which: str = "trace") -> np.ndarray:
        """Local periods of a grating in the image along ``axis`` [nm, in commanded
        coordinates]: distances between consecutive feature points (image-based paper,
        eqs. 4–5) of the image averaged across the other axis."""
        from afmctl.compensators.image_identify import feature_points

        img = self.trace_nm if which == "trace" else self.retrace_nm
        if axis == "x":
            return np.diff(feature_points(img.mean(axis=0))) * self.pixel_nm
        return np.diff(feature_points(img.mean(axis=1))) * self.pixel_y_nm

    @property
    def extent_nm(self) -> tuple[float, float, float, float]:
        px = self.pixel_nm
        py = float(self.y_target_nm[1] - self.y_target_nm[0]) if self.y_target_nm.size > 1 else px
        return (self.x_target_nm[0] - px / 2, self.x_target_nm[-1] + px / 2,
                self.y_target_nm[0] - py / 2, self.y_target_nm[-1] + py / 2)

    def save_png(self, path: str | Path, title: str | None = None, which: str = "both") -> Path:
        """Write the trace (and retrace) image as a PNG (matplotlib Agg); axes in µm as
        commanded (what the AFM believes), colour = height [nm]."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        panels = [("trace", self.trace_nm), ("retrace", self.retrace_nm)]
        if which != "both":
            panels = [p for p in panels if p[0] == which]
        fig, axs = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 4.2), squeeze=False)
        ext = [e / 1000.0 for e in self.extent_nm]
        for ax, (name, img) in zip(axs[0], panels):
            im = ax.imshow(img, origin="lower", extent=ext, cmap="afmhot", interpolation="nearest")
            ax.set_title(name)
            ax.set_xlabel("x (commanded) [µm]")
            ax.set_ylabel("y (commanded) [µm]")
            fig.colorbar(im, ax=ax, label="height [nm]", shrink=0.85)
        if title:
            fig.suptitle(title)
        fig.tight_layout()
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(p, dpi=110)
        plt.close(fig)
        return p


Compensator = Mapping[str, StreamingOperator] | Callable[[np.ndarray], np.ndarray] | None


def raster_targets(scan_size_nm: tuple[float, float], pixels: tuple[int, int], samples_per_pixel: int,
                   origin_nm: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Target x along one trace (cols·spp,), pixel centres x (cols,), line y (rows,) [nm]."""
    (Lx, Ly), (cols, rows) = scan_size_nm, pixels
    ns = cols * samples_per_pixel
    x_line = origin_nm[0] + (np.arange(ns) + 0.5) * (Lx / ns)
    x_pix = origin_nm[0] + (np.arange(cols) + 0.5) * (Lx / cols)
    y_rows = origin_nm[1] + (np.arange(rows) + 0.5) * (Ly / rows)
    return x_line, x_pix, y_rows


def _volts(scanner: Any, targets: np.ndarray, compensator: Compensator) -> np.ndarray:
    """Target positions (N, 3) nm → command voltages (N, 3) V."""
    gain = scanner.nominal_gain_nm_per_V()
    lim = scanner.voltage_limits_V()
    u = lim[:, 0] + targets / gain
    if compensator is None:
        pass
    elif callable(compensator) and not isinstance(compensator, Mapping):
        u = np.asarray(compensator(targets), dtype=np.float64)
        if u.shape != targets.shape:
            raise ModelError(f"compensator: returned shape {u.shape}, expected {targets.shape}")
    else:
        for i, a in enumerate(("x", "y", "z")):
            op = compensator.get(a)
            if op is not None:
                u[:, i] = op.block(np.ascontiguousarray(targets[:, i]))
    return np.clip(u, lim[:, 0], lim[:, 1])


def raster_image(scanner: Any, sample: Any, *, scan_size_nm: float | tuple[float, float] = 10_000.0,
                 pixels: int | tuple[int, int] = 256, line_rate_Hz: float = 1.0,
                 origin_nm: tuple[float, float] = (0.0, 0.0), samples_per_pixel: int = 2,
                 compensator: Compensator = None, z_mode: Literal["surface", "piezo"] = "surface",
                 z_nm: float = 0.0, T_C: Callable[[np.ndarray], np.ndarray] | None = None,
                 settle_lines: int = 1, keep_signals: bool = False) -> ScanImage:
    """Image ``sample`` with ``scanner`` (from its current state) and return a
    :class:`ScanImage`.

    scan_size_nm: side(s) of the scanned square/rectangle [nm] (x, y), from ``origin_nm``.
    pixels: columns (and rows) — an int means a square image.
    line_rate_Hz: lines per second; each line is a trace (+x) and a retrace (−x) of equal
    duration, so the sample period of the simulation is 1/(2·line_rate·cols·spp).
    samples_per_pixel: simulation samples per pixel; the pixel's height is their mean.
    compensator: None (nominal linear calibration), a mapping axis → streaming operator
    y_nm → u_V (e.g. ``{"x": model.inverse(dt), "y": ...}``, applied to the whole target
    sequence in order — reset it yourself), or a callable (N, 3) nm → (N, 3) V.
    z_mode: "surface" or "piezo" (module docstring); z_nm is the z target in "surface" mode.
    T_C: ambient temperature as a function of time since the scan start (array of s →
    array of °C); default the scanner's held value.
    settle_lines: lines scanned first on row 0 and not recorded, so the scanner is on the
    periodic raster path when recording starts.
    """
    if isinstance(scan_size_nm, (int, float)):
        scan_size_nm = (float(scan_size_nm), float(scan_size_nm))
    if isinstance(pixels, int):
        pixels = (pixels, pixels)
    cols, rows = int(pixels[0]), int(pixels[1])
    spp = int(samples_per_pixel)
    if cols < 2 or rows < 1 or spp < 1:
        raise ModelError(f"pixels: need ≥ 2 columns and ≥ 1 row, samples_per_pixel ≥ 1; got {pixels}, {spp}")
    if not (math.isfinite(line_rate_Hz) and line_rate_Hz > 0):
        raise ModelError(f"line_rate_Hz: {line_rate_Hz!r} must be > 0")
    ns = cols * spp
    dt = 1.0 / (2.0 * line_rate_Hz * ns)
    x_line, x_pix, y_rows = raster_targets(scan_size_nm, (cols, rows), spp, origin_nm)
    x_one = np.concatenate([x_line, x_line[::-1]])  # trace then retrace
    n_lines = rows + settle_lines
    line_y = np.concatenate([np.full(settle_lines, y_rows[0]), y_rows])
    targets = np.empty((n_lines * 2 * ns, 3))
    targets[:, 0] = np.tile(x_one, n_lines)
    targets[:, 1] = np.repeat(line_y, 2 * ns)
    if z_mode == "surface":
        targets[:, 2] = z_nm
    elif z_mode == "piezo":
        targets[:, 2] = sample.height_nm(targets[:, 0], targets[:, 1])
    else:
        raise ModelError(f"z_mode: {z_mode!r}; allowed 'surface', 'piezo'")
    u = _volts(scanner, targets, compensator)
    t_rel = (np.arange(targets.shape[0]) - settle_lines * 2 * ns) * dt
    T = None if T_C is None else np.asarray(T_C(np.maximum(t_rel, 0.0)), dtype=np.float64)
    pos = scanner.run(u, dt, T_C=T)
    rec = pos[settle_lines * 2 * ns:].reshape(rows, 2, cols, spp, 3)
    z0 = pos[settle_lines * 2 * ns - 1, 2] if settle_lines else scanner_z_before(pos)
    if z_mode == "surface":
        h = sample.height_nm(rec[..., 0], rec[..., 1]) + (rec[..., 2] - z0)
    else:
        h = rec[..., 2] - z0 + 0.0
    std = scanner.config.noise.height_std_nm
    if std > 0:
        h = h + scanner.rng.normal(0.0, std, h.shape)
    hp = h.mean(axis=3)
    xy = rec.mean(axis=3)
    t_pix = (np.arange(rows)[:, None] * 2 * ns + (np.arange(cols)[None, :] + 0.5) * spp) * dt
    img = ScanImage(
        trace_nm=hp[:, 0], retrace_nm=hp[:, 1, ::-1],
        x_target_nm=x_pix, y_target_nm=y_rows,
        x_trace_nm=xy[:, 0, :, 0], y_trace_nm=xy[:, 0, :, 1],
        x_retrace_nm=xy[:, 1, ::-1, 0], y_retrace_nm=xy[:, 1, ::-1, 1],
        t_trace_s=t_pix, line_rate_Hz=float(line_rate_Hz),
        sample_name=getattr(sample, "name", type(sample).__name__), compensated=compensator is not None,
    )
    if keep_signals:
        img.signals = {"t_s": t_rel, "target_nm": targets, "u_V": u, "position_nm": pos}
    log.debug("imaged %s: %dx%d px, %d samples at dt=%.3g s", img.sample_name, cols, rows, targets.shape[0], dt)
    return img


def scanner_z_before(pos: np.ndarray) -> float:
    """z reference when no settle line was scanned: the first sample's z."""
    return float(pos[0, 2])
