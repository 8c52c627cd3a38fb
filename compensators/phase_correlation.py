"""Drift measurement from images: phase correlation with a sub-pixel peak (pure numpy).

Re-imaging a reference feature and comparing it with an earlier image of the same area
gives the drift between the two images (Yang et al., "Automatic drift compensation using
phase correlation method for nanomanipulation", IEEE T-Nano 7(2) 2008 — ref. 10 of the
drift paper).

:func:`phase_correlation` returns the shift ``(dy, dx)`` in pixels such that
``moved(r) ≈ reference(r − (dy, dx))`` — i.e. the content of ``moved`` sits ``dx``
pixels further along the column index (fast scan axis) and ``dy`` along the row index.
If the sample stays put and the *tip* drifts by +d, features appear at −d in the image.

Method: mean removal and a Hann window against edge effects, the regularised
cross-power spectrum ``R = F_m·conj(F_r)/(|F_m·conj(F_r)| + eps·max)``, the integer
peak of ``ifft(R)``, then an upsampled DFT around the peak (matrix-multiply DFT,
Guizar-Sicairos et al. 2008) to ``1/upsample`` pixel; finally the two images are cropped
to their overlap at the integer shift and correlated once more (the window pulls large
shifts towards zero; on the overlap the residual shift is sub-pixel).
"""
from __future__ import annotations

import numpy as np

from .base import ModelError


def _upsampled_dft(data: np.ndarray, region: int, upsample: int, offsets: tuple[float, float]) -> np.ndarray:
    """Inverse DFT of ``data`` evaluated on a ``region×region`` grid of spacing
    ``1/upsample`` pixels starting at ``offsets`` (in upsampled pixels)."""
    ny, nx = data.shape
    ky = np.fft.ifftshift(np.arange(ny)) - ny // 2
    kx = np.fft.ifftshift(np.arange(nx)) - nx // 2
    ry = np.arange(region) - offsets[0]
    rx = np.arange(region) - offsets[1]
    ey = np.exp(2j * np.pi * np.outer(ry, ky) / (ny * upsample))
    ex = np.exp(2j * np.pi * np.outer(kx, rx) / (nx * upsample))
    return ey @ data @ ex


def _pc_once(ref: np.ndarray, mov: np.ndarray, upsample: int, window: bool, whitening_eps: float) -> tuple[float, float, float]:
    ref = ref - ref.mean()
    mov = mov - mov.mean()
    if window:
        w = np.outer(np.hanning(ref.shape[0]), np.hanning(ref.shape[1]))
        ref = ref * w
        mov = mov * w
    F = np.fft.fft2(mov) * np.conj(np.fft.fft2(ref))
    mag = np.abs(F)
    top = float(mag.max())
    if top == 0.0:
        raise ModelError("images: no contrast (constant images); phase correlation needs features")
    den = mag + whitening_eps * top
    R = np.divide(F, den, out=np.zeros_like(F), where=den > 1e-12 * top)
    corr = np.abs(np.fft.ifft2(R))
    ny, nx = ref.shape
    iy, ix = np.unravel_index(int(np.argmax(corr)), corr.shape)
    peak = float(corr[iy, ix] / corr.sum()) if corr.sum() > 0 else 0.0
    dy = float(iy - ny if iy > ny // 2 else iy)
    dx = float(ix - nx if ix > nx // 2 else ix)
    if upsample > 1:
        region = int(np.ceil(upsample * 1.5))
        centre = region // 2
        off = (centre - dy * upsample, centre - dx * upsample)
        up = np.abs(_upsampled_dft(R, region, upsample, off))
        uy, ux = np.unravel_index(int(np.argmax(up)), up.shape)
        dy += (uy - centre) / upsample
        dx += (ux - centre) / upsample
    return dy, dx, peak


def phase_correlation(reference: np.ndarray, moved: np.ndarray, upsample: int = 100,
                      window: bool = True, whitening_eps: float = 0.1,
                      refine: bool = True) -> tuple[float, float, float]:
    """Shift ``(dy, dx)`` [pixels] of ``moved`` relative to ``reference``, and a peak
    sharpness in (0, 1] (share of the correlation surface in the peak pixel).

    ``whitening_eps`` regularises the cross-power normalisation
    ``R = F/(|F| + eps·max|F|)`` (0 = classical phase correlation; larger values move
    towards plain cross-correlation and are more robust on non-periodic images).
    With ``refine``, the images are cropped to their overlap at the integer shift and
    correlated again, which removes most of the window's pull towards zero shift.
    Both images must be 2-D, the same shape, at least 8×8, and finite.
    """
    ref = np.asarray(reference, dtype=np.float64)
    mov = np.asarray(moved, dtype=np.float64)
    if ref.ndim != 2 or ref.shape != mov.shape:
        raise ModelError(f"images: shapes {ref.shape} and {mov.shape}; need two 2-D images of the same shape")
    if min(ref.shape) < 8:
        raise ModelError(f"images: shape {ref.shape}; need at least 8×8 pixels")
    if not (np.all(np.isfinite(ref)) and np.all(np.isfinite(mov))):
        raise ModelError("images: non-finite pixel values; all pixels must be finite")
    if not (1 <= upsample <= 1000):
        raise ModelError(f"upsample: {upsample}; allowed 1..1000")
    if not (0.0 <= whitening_eps <= 1e6):
        raise ModelError(f"whitening_eps: {whitening_eps}; allowed 0..1e6")
    dy, dx, peak = _pc_once(ref, mov, upsample, window, whitening_eps)
    if refine:
        iy, ix = int(round(dy)), int(round(dx))
        ny, nx = ref.shape
        if (iy or ix) and ny - abs(iy) >= 8 and nx - abs(ix) >= 8:
            # moved(r) = ref(r − s): compare ref[r] with moved[r + (iy, ix)] on the overlap
            r0y, r0x = max(0, -iy), max(0, -ix)
            hy, hx = ny - abs(iy), nx - abs(ix)
            ref_c = ref[r0y:r0y + hy, r0x:r0x + hx]
            mov_c = mov[r0y + iy:r0y + iy + hy, r0x + ix:r0x + ix + hx]
            ry, rx, peak = _pc_once(ref_c, mov_c, upsample, window, whitening_eps)
            if abs(ry) <= 1.0 and abs(rx) <= 1.0:
                dy, dx = iy + ry, ix + rx
    return dy, dx, peak


def image_drift_nm(reference: np.ndarray, moved: np.ndarray, pixel_nm: float | tuple[float, float],
                   upsample: int = 100) -> np.ndarray:
    """Drift of the *tip* [nm] ``(x, y)`` between two images of a fixed sample whose
    column index is x and row index is y: features move by −drift, hence the sign."""
    if isinstance(pixel_nm, (tuple, list, np.ndarray)):
        py, px = pixel_nm
    else:
        py = px = pixel_nm
    dy, dx, _ = phase_correlation(reference, moved, upsample=upsample)
    return np.array([-dx * float(px), -dy * float(py)])
