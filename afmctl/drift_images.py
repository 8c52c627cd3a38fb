"""Drift from images in the product: successive AFM frames of the same area → the tip's
drift [nm] (phase correlation, :mod:`afmctl.compensators.phase_correlation`), and a feeder
that hands such measurements to a running controller's Kalman filter
(:meth:`afmctl.loop.Controller.submit_drift_measurement`).

Sign: if the sample stays put and the tip drifts by +d, features appear at −d in the image;
the drift reported is the tip's, relative to the first frame.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from afmctl.compensators.phase_correlation import phase_correlation

log = logging.getLogger(__name__)


@dataclass
class FrameDrift:
    """Drift of one frame: against the previous frame and accumulated from the first [nm]."""

    frame: int
    t_s: float
    step_px: tuple[float, float]       # (rows = y, columns = x) shift of the content vs the previous frame
    drift_nm: tuple[float, float]      # tip drift (x, y) since the first frame


@dataclass
class FrameDriftMeter:
    """Phase correlation of each new frame with the previous one (successive frames of the
    same area); the drift accumulates the steps. ``pixel_nm`` = (row / y, column / x) size."""

    pixel_nm: tuple[float, float]
    upsample: int = 100
    frames: list[FrameDrift] = field(default_factory=list)
    _last: np.ndarray | None = None

    def add(self, image_nm: np.ndarray, t_s: float) -> FrameDrift:
        """Measure a new frame (heights [nm], rows = slow axis) taken at ``t_s`` [s]."""
        img = np.asarray(image_nm, dtype=np.float64)
        if self._last is None:
            fd = FrameDrift(0, float(t_s), (0.0, 0.0), (0.0, 0.0))
        else:
            dy, dx, _ = phase_correlation(self._last, img, upsample=self.upsample)
            px, py = self.frames[-1].drift_nm
            fd = FrameDrift(len(self.frames), float(t_s), (float(dy), float(dx)),
                            (px - dx * self.pixel_nm[1], py - dy * self.pixel_nm[0]))
        self._last = img
        self.frames.append(fd)
        return fd


class KalmanImageFeeder:
    """Feeds frame drifts to a running controller: ``submit_drift_measurement([x, y, NaN],
    std_nm, t_s)`` per new frame (z is not measured by lateral image registration).
    ``t_offset_s`` maps the images' clock onto the controller's."""

    def __init__(self, controller: Any, meter: FrameDriftMeter, std_nm: float, t_offset_s: float = 0.0) -> None:
        self.controller, self.meter, self.std_nm, self.t_offset_s = controller, meter, float(std_nm), t_offset_s

    def feed(self, image_nm: np.ndarray, t_s: float) -> FrameDrift:
        fd = self.meter.add(image_nm, t_s)
        if fd.frame > 0:
            z = np.array([fd.drift_nm[0], fd.drift_nm[1], np.nan])
            self.controller.submit_drift_measurement(z, self.std_nm, t_s=t_s + self.t_offset_s)
            log.info("drift frame %d: x %.3f nm, y %.3f nm fed to the Kalman filter", fd.frame, *fd.drift_nm)
        return fd

    def feed_file(self, path: str | Path, t_s: float) -> FrameDrift:
        from afmctl.compensators.scan_files import read_scan_image

        return self.feed(read_scan_image(path).trace_nm, t_s)
