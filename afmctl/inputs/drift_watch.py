"""``afmctl run --drift-images DIR``: while the controller scans, watch a directory for the AFM
frames the acquisition software writes (.gwy, .gsf, .tif, .ibw, Nanoscope .spm/.000–.999; all of
the same area), measure each new frame's drift by phase correlation (:mod:`afmctl.inputs.drift_images`)
and hand it to the controller's Kalman filter (``compensation.drift.kalman = true``).

A frame shows the residual drift (drift − the correction applied while it was taken), so the
watcher also listens to the controller's setpoints (a sink: ``corrected = target − drift
estimate``) and adds the change of the mean correction over the frame. The frame is taken to
have been scanned during the ``frame period`` [s] before it appeared (lines / line rate from
its metadata, or ``frame_period_s``); its measurement refers to the middle of that window.
"""
from __future__ import annotations

import logging
import threading
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from .drift_images import FrameDriftMeter, ImageDriftFeeder
from ..errors import AfmctlError

log = logging.getLogger(__name__)


class DriftImageWatcher:
    """Polls ``directory`` every ``poll_s`` [s]; frames are taken in file-name order."""

    def __init__(self, controller: Any, directory: str | Path, std_nm: float = 0.5,
                 frame_period_s: float | None = None, poll_s: float = 0.25) -> None:
        if getattr(getattr(controller, "pipeline", None), "kalman", None) is None:
            raise AfmctlError("--drift-images: the Kalman filter is off (set compensation.drift.enabled = true "
                              "and compensation.drift.kalman = true)")
        self.dir = Path(directory)
        if not self.dir.is_dir():
            raise AfmctlError(f"--drift-images: {self.dir} is not a directory")
        if not (np.isfinite(std_nm) and 1e-3 <= std_nm <= 1e4):
            raise AfmctlError(f"--drift-image-std-nm: {std_nm!r} nm is outside the allowed range 0.001…10000 nm")
        self.controller, self.std_nm, self.frame_period_s, self.poll_s = controller, float(std_nm), frame_period_s, poll_s
        self._blocks: deque[tuple[float, float, float, float, int]] = deque(maxlen=200_000)
        self._t_last = 0.0
        self._seen: set[str] = set(p.name for p in self._frames())   # frames already there are not ours
        self._feeder: ImageDriftFeeder | None = None
        self.measured: list[tuple[str, np.ndarray]] = []
        self._stop = threading.Event()
        controller.add_sink(self)
        self._thread = threading.Thread(target=self._run, name="afmctl-drift-images", daemon=True)
        self._thread.start()

    # ---------------------------------------------------------------- controller sink
    def on_setpoints(self, sp: np.ndarray) -> None:
        """Keep the mean correction (target − corrected) [nm] of every block of records."""
        c = sp["target_nm"][:, :2] - sp["corrected_nm"][:, :2]
        t = sp["t_s"]
        self._blocks.append((float(t[0]), float(t[-1]), float(c[:, 0].sum()), float(c[:, 1].sum()), len(t)))
        self._t_last = float(t[-1])

    def _mean_correction(self, t0: float, t1: float) -> np.ndarray:
        sx = sy = 0.0
        n = 0
        for a, b, cx, cy, k in list(self._blocks):
            if b >= t0 and a <= t1:
                sx, sy, n = sx + cx, sy + cy, n + k
        return np.array([sx / n, sy / n]) if n else np.zeros(2)

    # ---------------------------------------------------------------- watching
    def _frames(self) -> list[Path]:
        from afmctl.compensators.scan_files import is_image_file

        return sorted(p for p in self.dir.iterdir() if is_image_file(p))

    def _run(self) -> None:
        while not self._stop.wait(self.poll_s):
            try:
                for p in self._frames():
                    if p.name not in self._seen:
                        self._seen.add(p.name)
                        self._process(p)
            except OSError as err:
                log.warning("drift images: cannot list %s (%s)", self.dir, err)

    def _process(self, path: Path) -> None:
        from afmctl.compensators.base import ModelError
        from afmctl.compensators.scan_files import read_scan_image

        try:
            img = read_scan_image(path)
        except ModelError as err:
            log.warning("drift images: %s", err)
            return
        period = self.frame_period_s or (img.trace_nm.shape[0] / img.line_rate_Hz if img.line_rate_Hz else None)
        if not period:
            log.warning("drift images: %s has no line rate; give a frame period", path)
            return
        if self._feeder is None:
            meter = FrameDriftMeter(img.pixel_nm(), level_lines=True)
            self._feeder = ImageDriftFeeder(meter, self._submit)
        t1 = self._t_last
        corr = self._mean_correction(t1 - period, t1)
        self._feeder.feed(img.trace_nm, t1 - period / 2, corr)

    def _submit(self, z: np.ndarray, t_s: float) -> None:
        try:
            self.controller.submit_drift_measurement(z, self.std_nm, t_s=max(t_s, 0.0))
            self.measured.append((f"t={t_s:.3f}", z))
        except AfmctlError as err:
            log.warning("drift images: measurement refused (%s)", err)

    def close(self) -> None:
        """Stop watching (idempotent)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        try:
            self.controller.remove_sink(self)
        except (ValueError, KeyError):
            pass
