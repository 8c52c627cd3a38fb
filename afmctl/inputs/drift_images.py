"""Drift from images in the product: successive AFM frames of the same area → the tip's
drift [nm] (phase correlation, :mod:`afmctl.compensators.phase_correlation`), and a feeder
that hands such measurements to a Kalman filter — a running controller's
(:meth:`afmctl.control.controller.Controller.submit_drift_measurement`) or, in the drift scenario
(benchmarks/drift_scenario.py), the filter the scenario steps itself.

Sign: if the sample stays put and the tip drifts by +d, features appear at −d in the image;
the drift reported is the tip's, relative to the first frame.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Callable

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
    """Phase correlation of each new frame with the previous one (``reference="previous"``,
    successive frames of the same area; the drift accumulates the steps) or with the first
    frame (``reference="first"``: no accumulation, for a sample that does not change).
    ``pixel_nm`` = (row / y, column / x) size [nm]. ``level_lines`` subtracts each scan line's
    median first (row alignment): an instrument's unflattened frames carry per-line offsets
    (feedback, tilt) that otherwise pull the correlation towards zero shift — on the real
    Nanoscope sample, a 5 × 3 px shift measured as 2.7 × 1.6 px without it, 5.0 × 3.0 with it
    (tests/test_nanoscope_files.py)."""

    pixel_nm: tuple[float, float]
    upsample: int = 100
    reference: str = "previous"
    level_lines: bool = False
    frames: list[FrameDrift] = field(default_factory=list)
    _last: np.ndarray | None = None

    def add(self, image_nm: np.ndarray, t_s: float) -> FrameDrift:
        """Measure a new frame (heights [nm], rows = slow axis) taken at ``t_s`` [s]."""
        img = np.asarray(image_nm, dtype=np.float64)
        if self.level_lines:
            img = img - np.median(img, axis=1, keepdims=True)
        if self._last is None:
            fd = FrameDrift(0, float(t_s), (0.0, 0.0), (0.0, 0.0))
        else:
            dy, dx, _ = phase_correlation(self._last, img, upsample=self.upsample)
            px, py = self.frames[-1].drift_nm if self.reference == "previous" else (0.0, 0.0)
            fd = FrameDrift(len(self.frames), float(t_s), (float(dy), float(dx)),
                            (px - dx * self.pixel_nm[1], py - dy * self.pixel_nm[0]))
        if self._last is None or self.reference == "previous":
            self._last = img
        self.frames.append(fd)
        return fd


class ImageDriftFeeder:
    """Turns frames taken while drift compensation runs into drift measurements for a Kalman
    filter. A frame shows the *residual* drift (drift − applied correction); the drift since
    the first frame is that plus the change of the mean correction applied during the frame
    (``correction_nm``, x and y [nm]). ``submit(z_nm, t_s)`` receives ``[x, y, NaN]`` (z is
    not measured by lateral registration); :meth:`for_controller` submits to a running
    :class:`afmctl.control.controller.Controller`."""

    def __init__(self, meter: FrameDriftMeter, submit: Callable[[np.ndarray, float], None]) -> None:
        self.meter, self.submit = meter, submit
        self._c0: np.ndarray | None = None

    @classmethod
    def for_controller(cls, controller: Any, meter: FrameDriftMeter, std_nm: float) -> "ImageDriftFeeder":
        return cls(meter, lambda z, t: controller.submit_drift_measurement(z, std_nm, t_s=t))

    def feed(self, image_nm: np.ndarray, t_s: float, correction_nm: Any = (0.0, 0.0)) -> FrameDrift:
        """Measure a frame (mean time ``t_s`` [s]) and submit its drift (from frame 1 on)."""
        c = np.asarray(correction_nm, dtype=np.float64)[:2]
        fd = self.meter.add(image_nm, t_s)
        if self._c0 is None:
            self._c0 = c
            return fd
        z = np.array([fd.drift_nm[0] + c[0] - self._c0[0], fd.drift_nm[1] + c[1] - self._c0[1], np.nan])
        self.submit(z, float(t_s))
        log.info("drift frame %d: x %.3f nm, y %.3f nm submitted", fd.frame, z[0], z[1])
        return fd
