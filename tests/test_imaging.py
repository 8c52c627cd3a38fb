"""Raster imaging: the nonlinearities paper's qualitative results (hysteresis moves the
asperities between forward and backward scans, creep acts like a delay on ascending
edges, 2 °C over a 10 min scan gives a few-nm drift error growing through the image) and
the image-based paper's Fig. 9(a) distortion."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.compensators.image_identify import feature_points
from afmctl.sim_backend.imaging import raster_image
from afmctl.sim_backend.samples import Grating2D, StandardSample
from afmctl.sim_backend.scanner import CreepConfig, DriftConfig, Scanner, default_scanner_config, linear_scanner_config

STD = StandardSample(section_nm=1000.0, amplitude_nm=1.0)


def test_linear_scanner_images_the_sample_exactly():
    s = Scanner(linear_scanner_config())
    im = s.image(STD, scan_size_nm=(3000.0, 3000.0), pixels=(96, 3), samples_per_pixel=1)
    expected = STD.height_nm(im.x_target_nm, 0 * im.x_target_nm)
    np.testing.assert_allclose(im.trace_nm[1], expected, atol=1e-9)
    np.testing.assert_allclose(im.retrace_nm[1], expected, atol=1e-9)
    np.testing.assert_allclose(im.x_trace_nm[1], im.x_target_nm, atol=1e-6)
    assert im.trace_nm.shape == (3, 96)


def test_hysteresis_places_asperities_differently_forward_and_backward():
    shifts = {}
    for name, cfg in (("linear", linear_scanner_config()), ("hysteresis", default_scanner_config())):
        im = Scanner(cfg).image(STD, scan_size_nm=(9000.0, 9000.0), pixels=(256, 3))
        ft = feature_points(im.trace_nm.mean(axis=0))
        fr = feature_points(im.retrace_nm.mean(axis=0))
        assert ft.size == fr.size == 9
        shifts[name] = (fr - ft) * im.pixel_nm
    assert np.max(np.abs(shifts["linear"])) < 0.5 * 9000 / 256
    # the backward scan sees every asperity earlier (lower commanded x): hundreds of nm
    assert np.all(shifts["hysteresis"] < -200.0)
    assert np.max(np.abs(shifts["hysteresis"])) > 1000.0


def test_creep_acts_like_a_delay_on_ascending_edges():
    """z piezo follows the profile (paper's Figs. 15–16): with creep the image lags."""
    creep = linear_scanner_config()
    creep.z.creep = CreepConfig(fraction=0.2, tau_min_s=0.005, tau_max_s=0.05, n_lags=3)
    kw = dict(scan_size_nm=(3000.0, 3000.0), pixels=(192, 2), z_mode="piezo", line_rate_Hz=1.0)
    lin = Scanner(linear_scanner_config()).image(STD, **kw)
    cr = Scanner(creep).image(STD, **kw)
    err = cr.trace_nm[-1] - lin.trace_nm[-1]
    prof = lin.trace_nm[-1]
    up = np.flatnonzero(np.diff(prof) > 0.4) + 1  # pixels right after the square's rising edge
    assert up.size >= 1
    assert np.all(err[up] < -0.1)  # the image is still low: it has not arrived yet
    flat = np.flatnonzero(np.abs(prof) < 0.01)  # substrate between asperities
    assert np.median(np.abs(err[flat])) < 0.15 * np.max(np.abs(err[up]))  # concentrated at edges
    # the asperities move in the scan direction: forward → +x, backward → −x
    dt = feature_points(cr.trace_nm[-1]) - feature_points(prof)
    dr = feature_points(cr.retrace_nm[-1]) - feature_points(lin.retrace_nm[-1])
    assert np.all(dt > 0.2) and np.all(dr < -0.2)


def test_two_degrees_over_ten_minutes_gives_a_few_nm_growing_drift_error():
    T = lambda t: 22.0 + 2.0 * t / 600.0  # noqa: E731
    kw = dict(scan_size_nm=(3000.0, 3000.0), pixels=(32, 32), line_rate_Hz=32 / 600.0, T_C=T)
    ref = Scanner(linear_scanner_config(drift=DriftConfig(kind="none"))).image(STD, **kw)
    im = Scanner(linear_scanner_config(drift=DriftConfig())).image(STD, **kw)
    assert im.t_trace_s[-1, -1] == pytest.approx(600.0, rel=0.03)  # last trace pixel
    lateral = np.hypot(im.x_trace_nm - ref.x_trace_nm, im.y_trace_nm - ref.y_trace_nm)
    assert 1.0 < lateral.max() < 10.0  # nonlinearities paper: ≈ 3.3 nm
    rows = lateral.mean(axis=1)
    assert rows[-1] > 5 * rows[2] and np.corrcoef(np.arange(rows.size), rows)[0, 1] > 0.95
    assert np.argmax(lateral.max(axis=1)) >= rows.size - 2  # largest at the end of the scan


def test_uncompensated_grating_image_is_distorted():
    """Image-based paper, Fig. 9(a): the 1.667 µm grating's period is not uniform."""
    im = Scanner().image(Grating2D(), scan_size_nm=10_000.0, pixels=128)
    px = np.diff(feature_points(im.trace_nm.mean(axis=0))) * im.pixel_nm
    py = np.diff(feature_points(im.trace_nm.mean(axis=1))) * im.pixel_nm
    for p in (px, py):
        assert (p.max() - p.min()) / p.mean() > 0.2


def test_compensator_mapping_and_callable_and_png(tmp_path):
    s = Scanner(linear_scanner_config())

    class Gain:
        def reset(self):
            pass

        def block(self, y):
            return y / 80.0

    a = s.image(STD, scan_size_nm=3000.0, pixels=16, compensator={"x": Gain()})
    s.reset()
    b = s.image(STD, scan_size_nm=3000.0, pixels=16, compensator=lambda t: t / np.array([80.0, 80.0, 80 / 6]))
    s.reset()
    c = s.image(STD, scan_size_nm=3000.0, pixels=16, keep_signals=True)
    np.testing.assert_allclose(a.trace_nm, c.trace_nm, atol=1e-9)
    np.testing.assert_allclose(b.trace_nm, c.trace_nm, atol=1e-9)
    assert a.compensated and not c.compensated
    assert c.signals["u_V"].shape == c.signals["position_nm"].shape
    p = c.save_png(tmp_path / "img.png", title="test")
    assert p.stat().st_size > 1000 and p.read_bytes()[:4] == b"\x89PNG"


def test_bad_scan_arguments():
    from afmctl.compensators.base import ModelError

    s = Scanner(linear_scanner_config())
    with pytest.raises(ModelError, match="pixels"):
        raster_image(s, STD, pixels=1)
    with pytest.raises(ModelError, match="line_rate_Hz"):
        raster_image(s, STD, line_rate_Hz=0.0)
    with pytest.raises(ModelError, match="z_mode"):
        raster_image(s, STD, pixels=8, z_mode="tapping")
