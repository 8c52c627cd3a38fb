"""The sensor's noise in a learning iteration's recording, so that it is not counted as error
(:mod:`afmctl.compensators.learning`).

A raster repeats its lines: where the target of three consecutive judged lines is the same,
the recording's second difference across them, ``y_{j+2} − 2 y_{j+1} + y_j``, holds the
noise (variance ``6 σ²`` for noise independent from line to line) and no more than the
curvature of a slow drift across the lines. Its spectrum, averaged over the triples, is the
noise's power spectrum (coloured noise included: a sensor's low-pass shows in it); σ comes
from its median (robust to a few samples a transient still moves). Without three repeating
lines the noise is taken as white at the level of the recording's error in the top quarter
of the band (where a scan's harmonics are weakest): an upper bound when the error still has
content there.

:func:`noise_gain` is the per-bin gain of a spectral subtraction (Boll, IEEE Trans. ASSP
27(2), 1979): ``max(0, 1 − κ N(f) / |E(f)|²)``, so the learning takes out what stands above
the noise and leaves the noise alone. Units: nm, s, Hz.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .learning_weights import Line

#: the median of a χ²(1) variable: median(d²) = 0.455 · var(d) for Gaussian d
CHI2_MEDIAN = 0.4549
#: over-subtraction of the spectral subtraction (a bin counts as error once its power is
#: this many times the noise's)
OVER_SUBTRACT = 2.0
#: the noise spectrum is clipped to this many times its median: a narrow peak is a
#: deterministic difference between the lines (a mode still ringing from the start)
PEAK_CLIP = 3.0
#: the noise is at most this many times the top quarter band's level (a sensor's low-pass
#: may take up to 3/4 of the noise's power there; deterministic differences between the
#: lines, a transient's or creep's, stand mostly below it)
TOP_BAND_BOUND = 2.0
#: the fallback's band: the top quarter of the frequencies
HIGH_BAND = 0.75


@dataclass(frozen=True)
class Noise:
    """The recording's noise: ``sigma_nm`` [nm] per sample, its power per sample at
    ``f_Hz`` (``psd_nm2``, [nm²]: the mean over the band is σ² for white noise), and how it
    was measured (``source``)."""

    sigma_nm: float
    f_Hz: np.ndarray
    psd_nm2: np.ndarray
    source: str

    def at(self, f_Hz: np.ndarray) -> np.ndarray:
        """The noise power per sample [nm²] at ``f_Hz``."""
        if self.f_Hz.size < 2:
            return np.full(np.shape(f_Hz), self.sigma_nm ** 2)
        return np.interp(f_Hz, self.f_Hz, self.psd_nm2)


NO_NOISE = Noise(0.0, np.zeros(1), np.zeros(1), "none")


def repeating_triples(target_nm: np.ndarray, groups: list[list[Line]]) -> tuple[int, list[tuple[int, int, int]]]:
    """``(length, triples)``: the first samples of every three consecutive raster lines
    (``groups``, :func:`~afmctl.compensators.learning_weights.raster_lines`) whose targets are
    the same over ``length`` samples — the shortest line, and no more than the spacing of
    consecutive lines' starts (a trace and retrace share their turning sample with the next
    line's: each line is one sample longer than its period); ``(0, [])`` when none."""
    if len(groups) < 3:
        return 0, []
    starts = [g[0].start for g in groups]
    length = min(min(g[-1].stop - g[0].start for g in groups), min(b - a for a, b in zip(starts, starts[1:])))
    tol = 1e-6 * (float(np.ptp(target_nm)) or 1.0)
    seg = [target_nm[s:s + length] for s in starts]
    same = [seg[j].size == length and np.max(np.abs(seg[j] - seg[0])) <= tol for j in range(len(seg))]
    out = [(starts[j], starts[j + 1], starts[j + 2]) for j in range(len(seg) - 2) if same[j] and same[j + 1]
           and same[j + 2]]
    return (length, out) if out else (0, [])


def estimate_noise(y_nm: np.ndarray, target_nm: np.ndarray, groups: list[list[Line]], dt_s: float,
                   error_nm: np.ndarray | None = None) -> Noise:
    """The noise of the recording ``y_nm`` (module docstring): from repeating judged lines
    ``groups``, else from the top band of ``error_nm`` (the target less the recording), which also bounds
    the lines' estimate (:data:`TOP_BAND_BOUND`)."""
    y = np.asarray(y_nm, dtype=float)
    length, starts = repeating_triples(np.asarray(target_nm, dtype=float), groups)
    top = _top_band(np.asarray(error_nm if error_nm is not None else target_nm - y, dtype=float), dt_s)
    if starts and length >= 8:
        best: tuple[float, np.ndarray] | None = None
        for a, b, c in starts:                # the quietest triple: a transient only ever adds
            d = y[c: c + length] - 2 * y[b: b + length] + y[a: a + length]
            d = d - _trend(d[None, :])[0]
            var = float(np.median(d * d)) / CHI2_MEDIAN / 6.0
            if best is None or var < best[0]:
                best = (var, d)
        assert best is not None
        sigma = math.sqrt(best[0])
        psd = _smooth(np.abs(np.fft.rfft(best[1])) ** 2 / (6.0 * length))
        level = float(np.median(psd[1:])) if psd.size > 2 else sigma * sigma
        psd = np.minimum(psd, PEAK_CLIP * level)             # a transient's line, not noise
        sigma = min(sigma, math.sqrt(float(np.mean(psd))))
        if top is not None and sigma > TOP_BAND_BOUND * top.sigma_nm:
            # the lines differ by more than noise (a transient, creep): the top band bounds it
            scale = TOP_BAND_BOUND * top.sigma_nm / sigma
            return Noise(sigma * scale, np.fft.rfftfreq(length, dt_s), psd * scale * scale,
                         f"{len(starts) + 2} repeating lines, bounded by the top quarter band")
        return Noise(sigma, np.fft.rfftfreq(length, dt_s), psd, f"{len(starts) + 2} repeating lines")
    return top or NO_NOISE


def _top_band(e: np.ndarray, dt_s: float) -> Noise | None:
    """White noise at the level of ``e``'s top quarter band (None: too short)."""
    spec = np.abs(np.fft.rfft(np.diff(e))) ** 2 / max(e.size - 1, 1)
    f = np.fft.rfftfreq(e.size - 1, dt_s)
    w = 2.0 * np.sin(np.pi * f * dt_s)                      # the difference's gain
    top = (f >= HIGH_BAND * f[-1]) & (w > 0)
    if e.size < 8 or not np.any(top):
        return None
    level = float(np.median(spec[top] / w[top] ** 2)) / math.log(2.0)   # an exponential power: median = ln 2 · mean
    return Noise(math.sqrt(level), np.zeros(1), np.zeros(1), "the record's top quarter band")


def _trend(d: np.ndarray, degree: int = 3) -> np.ndarray:
    """Each row's least-squares polynomial of ``degree`` (a drift's slow curvature)."""
    x = np.linspace(-1.0, 1.0, d.shape[1])
    basis = np.vander(x, degree + 1)
    coef, *_ = np.linalg.lstsq(basis, d.T, rcond=None)
    return (basis @ coef).T


def _smooth(p: np.ndarray) -> np.ndarray:
    """A 3-bin running mean (the spectrum of a few short segments scatters)."""
    if p.size < 3:
        return p
    q = np.convolve(p, np.ones(3) / 3.0, mode="same")
    q[0], q[-1] = p[:2].mean(), p[-2:].mean()
    return q


def noise_gain(err_spectrum: np.ndarray, noise_power: np.ndarray) -> np.ndarray:
    """Per bin ``max(0, 1 − κ N/|E|²)`` (module docstring): ``noise_power`` the noise's
    expected ``|N(f)|²`` on the same grid as ``err_spectrum``."""
    p = np.abs(err_spectrum) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        g = 1.0 - OVER_SUBTRACT * noise_power / p
    return np.where(p > 0, np.clip(g, 0.0, 1.0), 0.0)
