"""Drift measurement by phase correlation (compensators.phase_correlation)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmctl.compensators.base import ModelError
from afmctl.compensators.phase_correlation import image_drift_nm, phase_correlation


def _texture(n=256, seed=0, sigma=3.0):
    rng = np.random.default_rng(seed)
    k = np.fft.fftfreq(n)
    F = np.fft.fft2(rng.standard_normal((n, n))) * np.exp(-(k[:, None] ** 2 + k[None, :] ** 2) * (2 * np.pi * sigma) ** 2 / 2)
    return np.fft.ifft2(F).real, F


def _crop(big, sy, sx, n=64, at=96):
    """Window of a smooth texture moved by (sy, sx) pixels (bicubic)."""
    from scipy.ndimage import map_coordinates
    yy, xx = np.mgrid[0:n, 0:n].astype(float)
    return map_coordinates(big, [yy + at - sy, xx + at - sx], order=3)


def test_exact_for_a_periodic_translation():
    img, F = _texture(64)
    k = np.fft.fftfreq(64)
    for sy, sx in [(0.0, 0.0), (3.3, -1.7), (-0.25, 0.6), (10.46, -12.22)]:
        moved = np.fft.ifft2(F * np.exp(-2j * np.pi * (k[:, None] * sy + k[None, :] * sx))).real
        dy, dx, _ = phase_correlation(img, moved, window=False, whitening_eps=0.0, refine=False)
        assert dy == pytest.approx(sy, abs=0.021) and dx == pytest.approx(sx, abs=0.021)


@settings(max_examples=15, deadline=None)
@given(sy=st.floats(-6.0, 6.0), sx=st.floats(-6.0, 6.0))
def test_sub_pixel_on_non_periodic_windows(sy, sx):
    big, _ = _texture()
    ref = _crop(big, 0.0, 0.0)
    dy, dx, _ = phase_correlation(ref, _crop(big, sy, sx))
    assert abs(dy - sy) < 0.1 and abs(dx - sx) < 0.1


def test_image_drift_sign_and_units():
    """Tip drifts by +d: the sample appears moved by −d in the image."""
    big, _ = _texture()
    ref = _crop(big, 0.0, 0.0)
    moved = _crop(big, -0.8, -0.4)  # features moved −0.4 px in x, −0.8 px in y
    d = image_drift_nm(ref, moved, pixel_nm=(5.0, 2.0))
    np.testing.assert_allclose(d, [0.4 * 2.0, 0.8 * 5.0], atol=0.25)


def test_bad_images():
    with pytest.raises(ModelError, match="shape"):
        phase_correlation(np.zeros((16, 16)), np.zeros((16, 17)))
    with pytest.raises(ModelError, match="8"):
        phase_correlation(np.zeros((4, 4)), np.zeros((4, 4)))
    img = np.ones((16, 16))
    bad = img.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ModelError, match="finite"):
        phase_correlation(img, bad)
    with pytest.raises(ModelError, match="contrast"):
        phase_correlation(img, img)
