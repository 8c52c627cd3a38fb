"""Sample surfaces for simulated AFM imaging: height [nm] as a function of the tip's lateral
position (x_nm, y_nm), vectorised over arrays of positions.

* :class:`Grating1D` — calibration grating with lines across x (e.g. 278 nm period, the
  image-based paper's identification sample);
* :class:`Grating2D` — square pillars on a square lattice (e.g. 1.667 µm period, the sample
  of the image-based paper's Fig. 9);
* :class:`StandardSample` — the nonlinearities paper's standard sample: sinusoidal, square
  and triangular asperities one after the other along x (its Figs. 12–18);
* :class:`Nanoparticles` — spheres (e.g. 15 nm gold particles) on a flat substrate.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np


class Sample(Protocol):
    """Anything with a vectorised ``height_nm(x_nm, y_nm) -> ndarray`` and a ``name``."""

    name: str

    def height_nm(self, x_nm: np.ndarray, y_nm: np.ndarray) -> np.ndarray: ...


def _bump(phase: np.ndarray, period: float, duty: float, edge: float, profile: str) -> np.ndarray:
    """One period of a line profile in 0…1 for positions ``phase`` ∈ [0, period): a feature
    centred at period/2, ``duty`` of the period wide (at half height)."""
    s = np.abs(phase - 0.5 * period)
    if profile == "sine":
        return 0.5 * (1.0 - np.cos(2.0 * np.pi * phase / period))
    w = 0.5 * duty * period
    if edge <= 0:
        return (s <= w).astype(np.float64)
    return np.clip((w - s) / edge + 0.5, 0.0, 1.0)


@dataclass(frozen=True)
class Grating1D:
    """Lines perpendicular to ``axis`` (x by default): step_nm·bump(x) with period
    ``period_nm``; a line is centred at phase_nm + (k + ½)·period_nm. ``profile`` "square" (trapezoid with edges
    ``edge_nm`` wide) or "sine"."""

    period_nm: float = 278.0
    step_nm: float = 20.0
    duty: float = 0.5
    edge_nm: float = 10.0
    phase_nm: float = 0.0
    profile: Literal["square", "sine"] = "square"
    axis: Literal["x", "y"] = "x"
    name: str = "grating-1d"

    def height_nm(self, x_nm: np.ndarray, y_nm: np.ndarray) -> np.ndarray:
        x, y = np.broadcast_arrays(np.asarray(x_nm, dtype=np.float64), np.asarray(y_nm, dtype=np.float64))
        ph = np.mod((x if self.axis == "x" else y) - self.phase_nm, self.period_nm)
        return self.step_nm * _bump(ph, self.period_nm, self.duty, self.edge_nm, self.profile)


@dataclass(frozen=True)
class Grating2D:
    """Square pillars on a square lattice of period ``period_nm`` (both x and y); pillar
    height ``step_nm``, side ``duty``·period at half height, edges ``edge_nm`` wide."""

    period_nm: float = 1667.0
    step_nm: float = 100.0
    duty: float = 0.5
    edge_nm: float = 40.0
    phase_nm: tuple[float, float] = (0.0, 0.0)
    name: str = "grating-2d"

    def height_nm(self, x_nm: np.ndarray, y_nm: np.ndarray) -> np.ndarray:
        x = np.asarray(x_nm, dtype=np.float64)
        y = np.asarray(y_nm, dtype=np.float64)
        fx = _bump(np.mod(x - self.phase_nm[0], self.period_nm), self.period_nm, self.duty, self.edge_nm, "square")
        fy = _bump(np.mod(y - self.phase_nm[1], self.period_nm), self.period_nm, self.duty, self.edge_nm, "square")
        return self.step_nm * fx * fy


@dataclass(frozen=True)
class StandardSample:
    """The nonlinearities paper's standard sample (its Fig. 12): along x, repeating every
    3·section_nm, a sinusoidal asperity, a square asperity and a triangular asperity, each
    ``amplitude_nm`` high and one section long; flat (0) between; independent of y."""

    section_nm: float = 1000.0
    amplitude_nm: float = 1.0
    name: str = "standard-sample"

    def height_nm(self, x_nm: np.ndarray, y_nm: np.ndarray) -> np.ndarray:
        x = np.asarray(x_nm, dtype=np.float64)
        L = self.section_nm
        ph = np.mod(x, 3 * L)
        sec = np.floor(ph / L)
        u = ph / L - sec  # 0…1 within the section
        sine = 0.5 * (1.0 - np.cos(2.0 * np.pi * u))
        square = ((u >= 0.25) & (u < 0.75)).astype(np.float64)
        tri = 1.0 - np.abs(2.0 * u - 1.0)
        h = np.where(sec == 0, sine, np.where(sec == 1, square, tri))
        return self.amplitude_nm * h + np.zeros_like(np.asarray(y_nm, dtype=np.float64))

    def section_kind(self, x_nm: np.ndarray) -> np.ndarray:
        """0 sinusoidal, 1 square, 2 triangular, per position."""
        return np.floor(np.mod(np.asarray(x_nm, dtype=np.float64), 3 * self.section_nm) / self.section_nm).astype(int)


@dataclass(frozen=True)
class Nanoparticles:
    """Spheres resting on a flat substrate: height = max over particles of the sphere's top
    surface r + sqrt(r² − d²) (d = lateral distance to the centre), else 0. The tip shape
    is not convolved. ``centres_nm`` (N, 2), ``diameters_nm`` (N,)."""

    centres_nm: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    diameters_nm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    name: str = "nanoparticles"

    @classmethod
    def random(cls, n: int, area_nm: tuple[float, float], diameter_nm: float = 15.0,
               spread: float = 0.0, seed: int = 0) -> "Nanoparticles":
        """``n`` particles at uniformly random positions in [0, area) (seeded), diameters
        ``diameter_nm`` ·(1 ± spread)."""
        rng = np.random.default_rng(seed)
        c = rng.uniform((0.0, 0.0), area_nm, size=(n, 2))
        d = diameter_nm * (1.0 + spread * rng.uniform(-1.0, 1.0, n))
        return cls(c, d)

    def height_nm(self, x_nm: np.ndarray, y_nm: np.ndarray) -> np.ndarray:
        x = np.asarray(x_nm, dtype=np.float64)
        y = np.asarray(y_nm, dtype=np.float64)
        x, y = np.broadcast_arrays(x, y)
        h = np.zeros(x.shape)
        for (cx, cy), d in zip(np.asarray(self.centres_nm), np.asarray(self.diameters_nm)):
            r = 0.5 * d
            d2 = (x - cx) ** 2 + (y - cy) ** 2
            inside = d2 < r * r
            if np.any(inside):
                h[inside] = np.maximum(h[inside], r + np.sqrt(r * r - d2[inside]))
        return h
