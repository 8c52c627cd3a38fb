"""Identification scans for the image-based hysteresis identification (image-based paper,
Step 1): one line of a calibration grating scanned repeatedly with the UNCOMPENSATED
scanner, a triangular voltage u_min → u_max → u_min per line, for several scan ranges.

:func:`scan_grating_lines` returns a :class:`GratingScans` whose :meth:`GratingScans.arrays`
is exactly the ``--from-images`` file of ``afmctl identify`` (read by
:mod:`afmctl.compensators.scan_files`; see :mod:`afmctl.compensators.image_identify` and docs/SIM.md). The plant's true position is kept
apart in :attr:`GratingScans.truth` (for tests that compare with sensor-based
identification); the image-based identification never reads it.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from afmctl.compensators.base import ModelError
from .samples import Grating1D

log = logging.getLogger(__name__)

#: scan ranges u_max [V] (u_min = 0 V), scanned in this order: 10 V steps, the 278 nm
#: grating shows ≥ 2 periods in the smallest one; with 15 Preisach levels the reversal
#: points fall on grid nodes. Largest first: the creep left over at u_min then varies
#: less from range to range (halves the difference to sensor-based identification).
DEFAULT_RANGES_V = tuple(float(v) for v in range(150, 9, -10))
#: Preisach levels used with DEFAULT_RANGES_V (10 V cells over 0…150 V)
DEFAULT_LEVELS = 15


@dataclass
class GratingScans:
    """Images and voltage ramps of the identification scans (shapes in the module doc of
    :mod:`afmctl.compensators.image_identify`); ``truth`` holds the true positions, for tests."""

    period_nm: float
    u_trace_V: np.ndarray
    u_retrace_V: np.ndarray
    trace_nm: np.ndarray
    retrace_nm: np.ndarray
    skip_lines: int
    axis: str
    line_rate_Hz: float | np.ndarray  # lines/s; one per range for scans at several rates
    truth: dict[str, np.ndarray] = field(default_factory=dict)

    def arrays(self) -> dict[str, Any]:
        """The arrays of the scan file (no truth)."""
        return {
            "period_nm": np.float64(self.period_nm),
            "u_trace_V": self.u_trace_V,
            "u_retrace_V": self.u_retrace_V,
            "trace_nm": self.trace_nm,
            "retrace_nm": self.retrace_nm,
            "skip_lines": np.int64(self.skip_lines),
            "axis": np.str_(self.axis),
            "line_rate_Hz": np.asarray(self.line_rate_Hz, dtype=np.float64),
        }

    def save_npz(self, path: str | Path) -> Path:
        """Write the scan file (``numpy.savez_compressed``)."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(p, **self.arrays())
        return p


def scan_grating_lines(scanner: Any, sample: Any | None = None, *, axis: Literal["x", "y"] = "x",
                       ranges_V: tuple[float, ...] = DEFAULT_RANGES_V, u_min_V: float | None = None,
                       pixels: int = 1024, lines_per_range: int = 4, line_rate_Hz: float = 1.0,
                       samples_per_pixel: int = 1, other_axis_nm: float = 0.0, skip_lines: int = 1,
                       keep_truth: bool = True) -> GratingScans:
    """Scan one line of ``sample`` (default: the 278 nm 1-D grating, lines across ``axis``)
    ``lines_per_range`` times for every voltage range u_min…u_max in ``ranges_V`` with the
    scanner as it is (no compensation). Pixel i of the trace is at voltage
    u_min + i·(u_max − u_min)/(pixels − 1); the retrace runs the same voltages backwards.
    The other lateral axis is held at the voltage for ``other_axis_nm`` (nominal gain),
    z in surface mode. Returns :class:`GratingScans`."""
    if axis not in ("x", "y"):
        raise ModelError(f"axis: {axis!r}; allowed 'x', 'y'")
    if sample is None:
        sample = Grating1D(period_nm=278.0, step_nm=20.0, duty=0.5, edge_nm=10.0)
    period = float(getattr(sample, "period_nm"))
    lim = scanner.voltage_limits_V()
    ia = 0 if axis == "x" else 1
    io = 1 - ia
    lo = float(lim[ia, 0] if u_min_V is None else u_min_V)
    gain = scanner.nominal_gain_nm_per_V()
    u_other = float(np.clip(lim[io, 0] + other_axis_nm / gain[io], lim[io, 0], lim[io, 1]))
    spp = int(samples_per_pixel)
    dt = 1.0 / (2.0 * line_rate_Hz * pixels * spp)
    R = len(ranges_V)
    ut = np.empty((R, pixels))
    trace = np.empty((R, lines_per_range, pixels))
    retrace = np.empty((R, lines_per_range, pixels))
    t_all, u_all, y_all = [], [], []
    t0 = scanner.time_s
    for r, hi in enumerate(ranges_V):
        if not lim[ia, 0] <= lo < hi <= lim[ia, 1]:
            raise ModelError(f"ranges_V: {hi} V outside {lo}…{lim[ia, 1]} V")
        ramp = np.linspace(lo, float(hi), pixels)
        ut[r] = ramp
        line = np.repeat(np.concatenate([ramp, ramp[::-1]]), spp)
        u, pos, h = scan_lines(scanner, sample, line, lines_per_range, ia, u_other, dt, pixels, spp)
        trace[r] = h[:, 0]
        retrace[r] = h[:, 1]
        if keep_truth:
            t_all.append(scanner.time_s - t0 - dt * (u.shape[0] - 1 - np.arange(u.shape[0])))
            u_all.append(u[:, ia].copy())
            y_all.append(pos[:, ia].copy())
    truth = {}
    if keep_truth:
        truth = {"t_s": np.concatenate(t_all), "u_V": np.concatenate(u_all), "y_nm": np.concatenate(y_all)}
    log.info("identification scans on %s: %d ranges × %d lines × %d px", axis, R, lines_per_range, pixels)
    return GratingScans(period, ut, ut[:, ::-1].copy(), trace, retrace, skip_lines, axis, float(line_rate_Hz), truth)


def scan_lines(scanner: Any, sample: Any, line_V: np.ndarray, lines: int, axis_index: int, u_other_V: float,
               dt_s: float, pixels: int, spp: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scan ``lines`` repeats of one line's voltages ``line_V`` (trace then retrace, ``spp``
    samples per pixel) on axis ``axis_index``, the other lateral axis at ``u_other_V`` and
    z at its lowest voltage, z in surface mode. Returns the voltages (N, 3) [V], the
    positions (N, 3) [nm] and the pixel heights (lines, 2, pixels) [nm] with the scanner's
    height noise."""
    u = np.empty((line_V.size * lines, 3))
    u[:, axis_index] = np.tile(line_V, lines)
    u[:, 1 - axis_index] = u_other_V
    u[:, 2] = scanner.voltage_limits_V()[2, 0]
    pos = scanner.run(u, dt_s)
    h = sample.height_nm(pos[:, 0], pos[:, 1]) + (pos[:, 2] - pos[0, 2])
    std = scanner.config.noise.height_std_nm
    if std > 0:
        h = h + scanner.rng.normal(0.0, std, h.shape)
    return u, pos, h.reshape(lines, 2, pixels, spp).mean(axis=3)


def identify_axes_from_images(scanner: Any, axes: tuple[Literal["x", "y"], ...] = ("x", "y"), *, n_operators: int = DEFAULT_LEVELS,
                              ranges_V: tuple[float, ...] = DEFAULT_RANGES_V, pixels: int = 1024,
                              lines_per_range: int = 3, line_rate_Hz: dict[str, float] | None = None,
                              reset: bool = True, **options: Any) -> dict[str, Any]:
    """Image-based Preisach models for the lateral axes of a simulated scanner: for each
    axis, :func:`scan_grating_lines` on the 278 nm grating (lines across that axis) and
    :func:`afmctl.compensators.image_identify.identify_from_images`. ``line_rate_Hz`` per axis
    (default x: 1 line/s; y: 1/512 lines/s, i.e. one ramp as slow as the slow axis of a
    512-line image at 1 line/s — identify each axis at the speed it is used, so that creep
    is seen as it will be). The scanner is reset before each axis if ``reset``.
    Returns {axis: PreisachModel}."""
    from afmctl.compensators.image_identify import identify_from_images

    rates = {"x": 1.0, "y": 1.0 / 512.0}
    rates.update(line_rate_Hz or {})
    models: dict[str, Any] = {}
    for ax in axes:
        if reset:
            scanner.reset()
        sample = Grating1D(period_nm=278.0, step_nm=20.0, duty=0.5, edge_nm=10.0, axis=ax)
        scans = scan_grating_lines(scanner, sample, axis=ax, ranges_V=ranges_V, pixels=pixels,
                                   lines_per_range=lines_per_range, line_rate_Hz=rates[ax], keep_truth=False)
        models[ax] = identify_from_images(scans.arrays(), kind="preisach", n_operators=n_operators, **options)
    if reset:
        scanner.reset()
    return models
