"""The image as it builds up: height samples [nm] at the tip's true (x, y) [nm], binned."""
from __future__ import annotations

from typing import Any

import numpy as np


class HeightImage:
    """The last ``max_samples`` height samples, binned into a ``cols`` × ``rows`` grid over
    the area they cover (the mean height of the samples in each pixel, None where none
    fell). Memory is bounded by ``max_samples`` whatever the run's length."""

    def __init__(self, cols: int = 128, rows: int = 64, max_samples: int = 30_000) -> None:
        self.cols, self.rows = cols, rows
        self._xyh = np.zeros((max_samples, 3))      # a ring, allocated once
        self.samples = 0
        self.sample_name = ""

    @property
    def held(self) -> int:
        """Samples held (at most ``max_samples``)."""
        return min(self.samples, len(self._xyh))

    def add(self, x_nm: float, y_nm: float, height_nm: float, sample_name: str = "") -> None:
        self._xyh[self.samples % len(self._xyh)] = (x_nm, y_nm, height_nm)
        self.samples += 1
        if sample_name:
            self.sample_name = sample_name

    def grid(self) -> dict[str, Any] | None:
        """``{"x_nm": [min, max], "y_nm": [min, max], "height_nm": rows × cols (None = empty),
        "h_range_nm": [min, max], "samples": n, "sample": name}``; None before 2 samples.
        The area binned is the central 98 % of the samples in x and in y (the ramp from the
        safe position to the scan's start stays out)."""
        if self.held < 2:
            return None
        a = self._xyh[:self.held]
        x, y, h = a[:, 0], a[:, 1], a[:, 2]
        xr = [float(v) for v in np.percentile(x, [1.0, 99.0])]
        yr = [float(v) for v in np.percentile(y, [1.0, 99.0])]
        xr[1], yr[1] = max(xr[1], xr[0] + 1e-6), max(yr[1], yr[0] + 1e-6)
        bins = (self.rows, self.cols)
        s, _, _ = np.histogram2d(y, x, bins=bins, range=[yr, xr], weights=h)
        n, _, _ = np.histogram2d(y, x, bins=bins, range=[yr, xr])
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = s / n
        rows = [[None if not np.isfinite(v) else round(float(v), 3) for v in row] for row in mean]
        return {"x_nm": xr, "y_nm": yr, "height_nm": rows, "h_range_nm": [float(h.min()), float(h.max())],
                "samples": self.samples, "sample": self.sample_name}
