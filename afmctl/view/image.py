"""The image as it builds up: the sample height [nm] under the tip's true (x, y) [nm], on a
fixed grid of pixels over the scan area, each pixel holding the latest height that fell in
it (as an AFM display shows the frame being scanned over the previous one)."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

#: headroom added on each side when the area has to grow [fraction of its span]
GROW_HEADROOM = 0.25


class HeightImage:
    """A ``cols`` × ``rows`` grid of the latest height [nm] per pixel over ``area`` [nm]
    (``[[x_min, y_min], [x_max, y_max]]``). Memory is the grid, whatever the run's length.

    :meth:`set_area` is given the scan area (the targets' extent); when it no longer fits
    in the grid's area, the grid grows (with headroom, so a raster that grows line by line
    regrows rarely) and what it held is re-binned into the new pixels. Samples outside
    the area, or before any area is known, are counted in ``outside`` and dropped."""

    def __init__(self, cols: int = 128, rows: int = 64) -> None:
        self.cols, self.rows = cols, rows
        self._h = np.full((rows, cols), np.nan)
        self._area: np.ndarray | None = None
        self.samples = self.outside = 0
        self.sample_name = ""
        self._h_min, self._h_max = math.inf, -math.inf

    @property
    def area_nm(self) -> np.ndarray | None:
        return None if self._area is None else self._area.copy()

    def set_area(self, area_nm: np.ndarray) -> None:
        """Make the grid cover ``area_nm`` (grows only; re-bins what it holds)."""
        area = np.asarray(area_nm, float).reshape(2, 2)
        if not np.all(np.isfinite(area)) or not np.all(area[1] > area[0]):
            return
        if self._area is not None and np.all(area[0] >= self._area[0]) and np.all(area[1] <= self._area[1]):
            return
        if self._area is not None:      # grow only the sides that must, each with headroom
            span = area[1] - area[0]
            lo = np.where(area[0] < self._area[0], area[0] - GROW_HEADROOM * span, self._area[0])
            hi = np.where(area[1] > self._area[1], area[1] + GROW_HEADROOM * span, self._area[1])
            area = np.vstack([lo, hi])
        old_h, old_area = self._h, self._area
        self._area, self._h = area, np.full((self.rows, self.cols), np.nan)
        if old_area is not None:
            r, c = np.nonzero(np.isfinite(old_h))
            x = old_area[0, 0] + (c + 0.5) / self.cols * (old_area[1, 0] - old_area[0, 0])
            y = old_area[0, 1] + (r + 0.5) / self.rows * (old_area[1, 1] - old_area[0, 1])
            rr, cc = self._pixel(area, x, y)
            self._h[rr, cc] = old_h[r, c]

    def _pixel(self, a: np.ndarray, x: float | np.ndarray, y: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row and column of positions ``x, y`` [nm] in the scan area ``a``."""
        c = np.floor((np.asarray(x) - a[0, 0]) / (a[1, 0] - a[0, 0]) * self.cols).astype(int)
        r = np.floor((np.asarray(y) - a[0, 1]) / (a[1, 1] - a[0, 1]) * self.rows).astype(int)
        return np.clip(r, 0, self.rows - 1), np.clip(c, 0, self.cols - 1)

    def add(self, x_nm: float, y_nm: float, height_nm: float, sample_name: str = "") -> None:
        self.samples += 1
        if sample_name:
            self.sample_name = sample_name
        a = self._area
        if a is None or not (a[0, 0] <= x_nm <= a[1, 0] and a[0, 1] <= y_nm <= a[1, 1]):
            self.outside += 1
            return
        r, c = self._pixel(a, x_nm, y_nm)
        self._h[r, c] = height_nm
        self._h_min, self._h_max = min(self._h_min, height_nm), max(self._h_max, height_nm)

    def grid(self) -> dict[str, Any] | None:
        """``{"x_nm": [min, max], "y_nm": [min, max], "height_nm": rows × cols (row 0 at
        y_min; None = no sample yet), "h_range_nm": [min, max], "samples": n, "outside": n,
        "sample": name}``; None before any pixel is set."""
        if self._area is None or not np.isfinite(self._h).any():
            return None
        rows = [[None if not math.isfinite(v) else round(v, 3) for v in row] for row in self._h.tolist()]
        return {"x_nm": self._area[:, 0].tolist(), "y_nm": self._area[:, 1].tolist(), "height_nm": rows,
                "h_range_nm": [self._h_min, self._h_max], "samples": self.samples, "outside": self.outside,
                "sample": self.sample_name}
