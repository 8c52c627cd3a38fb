"""Sample surfaces: periods, heights and shapes."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmctl.compensators.image_identify import feature_points
from afmctl.sim_backend.samples import Grating1D, Grating2D, Nanoparticles, StandardSample


@settings(max_examples=25, deadline=None)
@given(period=st.floats(100.0, 2000.0), phase=st.floats(0.0, 1000.0))
def test_grating1d_is_periodic_with_its_period(period, phase):
    g = Grating1D(period_nm=period, step_nm=20.0, phase_nm=phase, edge_nm=period / 20)
    x = np.linspace(0, 5000, 2001)
    np.testing.assert_allclose(g.height_nm(x, 0 * x), g.height_nm(x + period, 0 * x), atol=1e-6)
    assert g.height_nm(x, x).max() == pytest.approx(20.0)
    assert g.height_nm(x, x).min() == pytest.approx(0.0)


def test_grating1d_feature_spacing_is_the_period_in_pixels():
    g = Grating1D(period_nm=278.0)
    x = np.arange(4000) * 2.0  # 2 nm pixels
    f = feature_points(g.height_nm(x, 0 * x))
    np.testing.assert_allclose(np.diff(f) * 2.0, 278.0, atol=0.05)
    # a line is centred at (k + 1/2)·period
    assert f[0] * 2.0 == pytest.approx(139.0, abs=0.5)


def test_grating1d_along_y():
    g = Grating1D(period_nm=278.0, axis="y")
    y = np.linspace(0, 1000, 500)
    assert np.ptp(g.height_nm(0 * y + 123.0, y)) == pytest.approx(20.0)
    assert np.ptp(g.height_nm(y, 0 * y + 139.0)) == 0.0


def test_grating2d_pillars():
    g = Grating2D(period_nm=1667.0, step_nm=100.0, edge_nm=0.0)
    assert g.height_nm(np.array([833.5]), np.array([833.5]))[0] == 100.0  # pillar centre
    assert g.height_nm(np.array([833.5]), np.array([10.0]))[0] == 0.0  # between pillars in y
    assert g.height_nm(np.array([10.0]), np.array([833.5]))[0] == 0.0
    xx, yy = np.meshgrid(np.linspace(0, 1667, 400, endpoint=False), np.linspace(0, 1667, 400, endpoint=False))
    assert g.height_nm(xx, yy).mean() == pytest.approx(25.0, rel=0.02)  # duty 0.5 in both axes


def test_standard_sample_has_sine_square_triangle():
    s = StandardSample(section_nm=1000.0, amplitude_nm=2.0)
    x = np.linspace(0, 3000, 3001)[:-1]
    h = s.height_nm(x, 0 * x)
    kind = s.section_kind(x)
    assert list(np.unique(kind)) == [0, 1, 2]
    sine, square, tri = (h[kind == k] for k in range(3))
    assert sine.max() == pytest.approx(2.0, rel=1e-3) and tri.max() == pytest.approx(2.0, rel=1e-2)
    assert set(np.unique(square)) == {0.0, 2.0}
    assert sine.mean() == pytest.approx(1.0, rel=1e-2)  # (1 − cos)/2
    assert tri.mean() == pytest.approx(1.0, rel=1e-2)
    np.testing.assert_allclose(s.height_nm(x + 3000, x), h)  # repeats every 3 sections


def test_nanoparticles_height_is_the_sphere_top():
    p = Nanoparticles(np.array([[100.0, 100.0], [300.0, 120.0]]), np.array([15.0, 30.0]))
    assert p.height_nm(np.array([100.0]), np.array([100.0]))[0] == pytest.approx(15.0)
    assert p.height_nm(np.array([300.0]), np.array([120.0]))[0] == pytest.approx(30.0)
    assert p.height_nm(np.array([200.0]), np.array([100.0]))[0] == 0.0
    r = Nanoparticles.random(20, (1000.0, 1000.0), 15.0, seed=3)
    again = Nanoparticles.random(20, (1000.0, 1000.0), 15.0, seed=3)
    np.testing.assert_array_equal(r.centres_nm, again.centres_nm)
    assert r.centres_nm.shape == (20, 2) and np.all(r.diameters_nm == 15.0)
