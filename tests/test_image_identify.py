"""Image-based identification (image-based paper, eqs. 4–6 and Steps 1–4): the pieces on
synthetic data, and the whole procedure on the simulated scanner — never reading its true
position — against identification from the true position, and the compensated image of
the 1.667 µm grating (Fig. 9(b))."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmctl.compensators.base import ModelError
from afmctl.compensators.image_identify import (check_scans, feature_points, fit_closed_loop, fit_polynomial, poly_eval,
                                         range_branches, reversal_record, threshold)
from afmctl.sim_backend.samples import Grating1D

import afmctl.compensators.preisach as pre


def test_threshold_is_eq4():
    h = np.array([0.0, 1.0, 2.0, 5.0])
    assert threshold(h) == pytest.approx(2.0)
    assert threshold(h, a=0.5, c=1.0) == pytest.approx(2.0)


@settings(max_examples=30, deadline=None)
@given(centres=st.lists(st.floats(20.0, 480.0), min_size=1, max_size=6, unique=True), base=st.floats(-50, 50))
def test_feature_points_are_centres_of_gravity(centres, base):
    centres = sorted(centres)
    if np.min(np.diff(centres), initial=100.0) < 40.0:
        return  # bumps must not overlap
    x = np.arange(500, dtype=float)
    h = base + sum(10.0 * np.exp(-0.5 * ((x - c) / 3.0) ** 2) for c in centres)
    f = feature_points(h, a=1.0, c=0.0)
    np.testing.assert_allclose(f, centres, atol=0.1)  # discrete truncation at T: < 0.1 px


def test_feature_points_drop_partial_features_at_the_ends():
    x = np.arange(200, dtype=float)
    g = Grating1D(period_nm=50.0, step_nm=1.0, edge_nm=2.0, phase_nm=-25.0)
    h = g.height_nm(x, 0 * x)  # a line straddles pixel 0
    f = feature_points(h)
    assert f[0] == pytest.approx(50.0, abs=0.01) and np.allclose(np.diff(f), 50.0, atol=0.01)
    assert feature_points(h, drop_edges=False)[0] < 10


def test_fit_polynomial_is_eq6():
    rng = np.random.default_rng(0)
    u = np.sort(rng.uniform(0, 150, 60))
    theta = np.array([3.0, 40.0, 0.2, -1e-3])
    y = poly_eval(theta, u)
    np.testing.assert_allclose(fit_polynomial(u, y, 3), theta, rtol=1e-8, atol=1e-8)
    # with noise: the normal-equation solution of eq. 6
    yn = y + rng.normal(0, 5, u.size)
    Phi = np.vander(u, 4, increasing=True)
    normal = np.linalg.solve(Phi.T @ Phi, Phi.T @ yn)
    np.testing.assert_allclose(fit_polynomial(u, yn, 3), normal, rtol=1e-6)
    with pytest.raises(ModelError, match="order"):
        fit_polynomial(u[:3], y[:3], 5)


def test_closed_loop_fit_meets_at_both_ends():
    ua = np.linspace(5, 95, 20)
    ud = np.linspace(95, 5, 20)
    ta, td = fit_closed_loop(ua, 50 * ua, ud, 50 * ud + 300 * np.sin(np.pi * ud / 100), 0.0, 100.0, order=4)
    assert poly_eval(ta, 100.0) == pytest.approx(poly_eval(td, 100.0), abs=1e-6)
    assert poly_eval(ta, 0.0) == pytest.approx(poly_eval(td, 0.0), abs=1e-6)


def synthetic_range(u_max: float, period: float = 278.0, pixels: int = 800):
    """A loop with known branches: asc f(u) = 60u + 0.1u², desc g(u) = f(u) + bump that
    vanishes at u_min = 0 and u_max; the grating line images rendered at those positions."""
    u = np.linspace(0.0, u_max, pixels)
    f = 60.0 * u + 0.1 * u**2
    g = f + 0.08 * f.max() * np.sin(np.pi * u / u_max)
    g_time = g[::-1]  # retrace in time order
    grating = Grating1D(period_nm=period, step_nm=20.0, edge_nm=10.0, phase_nm=37.0)
    tr = grating.height_nm(f, 0 * f)[None, :].repeat(2, axis=0)
    rt = grating.height_nm(g_time, 0 * g)[None, :].repeat(2, axis=0)
    return u, f, g, tr, rt


@pytest.mark.parametrize("u_max", [40.0, 100.0, 150.0])
def test_range_branches_recover_known_loop(u_max):
    u, f, g, tr, rt = synthetic_range(u_max)
    rb = range_branches(tr, rt, u, u[::-1], 278.0, order=12)
    span = f.max()
    assert np.max(np.abs(rb.ascending(u) - f)) < 0.005 * span
    assert np.max(np.abs(rb.descending(u) - g)) < 0.005 * span
    assert rb.ascending(np.array([0.0]))[0] == pytest.approx(0.0, abs=1e-6)


def test_reversal_record_is_first_order_reversal_curves():
    branches = [range_branches(*synthetic_range(m)[3:], synthetic_range(m)[0], synthetic_range(m)[0][::-1], 278.0)
                for m in (150.0, 60.0, 100.0)]
    t, u, y = reversal_record(branches, points_per_branch=50)
    assert t.shape == u.shape == y.shape
    tops = u[1:-1][(np.diff(u)[:-1] > 0) & (np.diff(u)[1:] < 0)]
    np.testing.assert_allclose(tops, [60.0, 100.0, 150.0])  # sorted by u_max
    assert u.min() == 0.0


def good_scans() -> dict[str, np.ndarray]:
    u, f, g, tr, rt = synthetic_range(150.0)
    return {"period_nm": np.float64(278.0), "u_trace_V": u[None], "u_retrace_V": u[::-1][None],
            "trace_nm": tr[None], "retrace_nm": rt[None]}


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d.pop("trace_nm"), "missing array"),
    (lambda d: d.update(period_nm=np.float64(-1.0)), "period_nm"),
    (lambda d: d.update(u_retrace_V=d["u_retrace_V"][:, :5]), "u_retrace_V"),
    (lambda d: d.update(trace_nm=d["trace_nm"][0]), "trace_nm"),
    (lambda d: d["retrace_nm"].__setitem__((0, 0, 3), np.nan), "non-finite"),
    (lambda d: d.update(u_trace_V=np.array([["a", "b"]])), "u_trace_V: not a real numeric"),
    (lambda d: d.update(trace_nm=d["trace_nm"] + 1j), "trace_nm: not a real numeric"),  # no silent cast
    (lambda d: d.update(skip_lines=np.float64(1.5)), "skip_lines"),
    (lambda d: d.update(skip_lines=np.int64(10**6)), r"skip_lines: must be one integer in 0…"),  # ≥ lines
])
def test_bad_scan_arrays_name_the_array(mutate, match):
    d = good_scans()
    check_scans(d)
    mutate(d)
    with pytest.raises(ModelError, match=match):
        check_scans(d)


# --------------------------------------------------------------------------- on the plant
@pytest.fixture(scope="module")
def x_scans():
    from afmctl.sim_backend.image_scans import scan_grating_lines
    from afmctl.sim_backend.scanner import Scanner

    return scan_grating_lines(Scanner(), axis="x", pixels=1024, lines_per_range=3)


def test_image_identification_matches_true_position_identification(x_scans):
    """Never reading the true position: the compensator is within 1.5 % of the one
    identified from the true position of the same plant on the same voltages."""
    from afmctl.compensators.image_identify import identify_from_images
    from afmctl.compensators.preisach import PreisachModel
    from afmctl.sim_backend.image_scans import DEFAULT_LEVELS

    arrays = x_scans.arrays()
    assert not set(arrays) & set(x_scans.truth)  # the scan file holds no position
    m_img = identify_from_images(arrays, kind="preisach", n_operators=DEFAULT_LEVELS)
    tr = x_scans.truth
    m_true = PreisachModel.identify(tr["t_s"], tr["u_V"], tr["y_nm"], n_operators=DEFAULT_LEVELS,
                                    u_min_V=0.0, u_max_V=150.0)
    # compensator: voltages for a nested-loop target path, difference relative to 150 V
    lo, hi = m_true.output_range_nm()
    y = np.concatenate([np.linspace(lo + 100, hi - 100, 400), np.linspace(hi - 100, 0.3 * hi, 200),
                        np.linspace(0.3 * hi, 0.8 * hi, 200), np.linspace(0.8 * hi, lo + 100, 300)])
    du = np.abs(m_img.inverse().block(y) - m_true.inverse().block(y))
    assert du.max() / 150.0 < 0.015
    u = np.interp(np.linspace(0, 1, 1100), np.linspace(0, 1, 5), [0, 150, 40, 120, 0])
    dy = np.abs(m_img.forward().block(u) - m_true.forward().block(u))
    assert dy.max() / (hi - lo) < 0.015


def test_compensated_grating_period_is_uniform(tmp_path):
    """Image-based paper, Fig. 9(b): 10 µm scan of the 1.667 µm grating at 512×512, 1
    line/s, with Preisach compensators identified from images on x and y. The scan sits
    0.5 µm inside the scanner's range (0.5…10.5 µm of ≈ 12 µm), as a user would place it."""
    from afmctl.sim_backend.image_scans import identify_axes_from_images
    from afmctl.sim_backend.samples import Grating2D
    from afmctl.sim_backend.scanner import Scanner

    s = Scanner()
    models = identify_axes_from_images(s, ("x", "y"))
    comp = {a: m.inverse() for a, m in models.items()}
    im = s.image(Grating2D(), scan_size_nm=10_000.0, pixels=512, line_rate_Hz=1.0, compensator=comp,
                 origin_nm=(500.0, 500.0))
    for axis, which in (("x", "trace"), ("x", "retrace"), ("y", "trace")):
        p = im.grating_periods_nm(axis, which)
        assert p.size >= 4
        assert np.max(np.abs(p / p.mean() - 1.0)) < 0.01, (axis, which, p)
        assert p.mean() == pytest.approx(1667.0, rel=0.015)
    s.reset()
    raw = s.image(Grating2D(), scan_size_nm=10_000.0, pixels=128)
    assert np.ptp(raw.grating_periods_nm("x")) / 1667.0 > 0.2  # Fig. 9(a), for contrast


def test_scan_file_roundtrip_and_errors(tmp_path, x_scans):
    from afmctl.compensators.scan_files import identify_from_scan_files, load_scans_npz

    p = x_scans.save_npz(tmp_path / "scans.npz")
    data = load_scans_npz(p)
    np.testing.assert_array_equal(data["trace_nm"], x_scans.trace_nm)
    model = identify_from_scan_files([p], "preisach", n_operators=15)
    assert model.kind == "preisach" and model.u_max_V == 150.0
    with pytest.raises(ModelError, match="no such scan file"):
        load_scans_npz(tmp_path / "missing.npz")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ModelError, match="bad.npz"):
        load_scans_npz(tmp_path / "bad.npz")
    raw = p.read_bytes()
    (tmp_path / "truncated.npz").write_bytes(raw[: len(raw) // 2])  # zipfile.BadZipFile
    with pytest.raises(ModelError, match="truncated.npz: not a readable"):
        load_scans_npz(tmp_path / "truncated.npz")
    hurt = bytearray(raw)
    hurt[200:260] = bytes(60)  # inside the first compressed member: zlib.error
    (tmp_path / "corrupt.npz").write_bytes(bytes(hurt))
    with pytest.raises(ModelError, match="corrupt.npz"):
        load_scans_npz(tmp_path / "corrupt.npz")
    np.savez(tmp_path / "partial.npz", period_nm=278.0)
    with pytest.raises(ModelError, match="missing array"):
        load_scans_npz(tmp_path / "partial.npz")
    with pytest.raises(ModelError, match="option not accepted"):
        identify_from_scan_files([p], "preisach", n_operators=15, colour="red")


def test_cli_identify_from_images(tmp_path, x_scans, capsys):
    """``afmctl identify --model preisach --from-images SCANS.npz --out MODEL.json``."""
    import json

    from afmctl.cli import main

    scans = x_scans.save_npz(tmp_path / "scans.npz")
    out = tmp_path / "model.json"
    rc = main(["identify", "--model", "preisach", "--from-images", str(scans), "--out", str(out), "--operators", "15",
               "--param", "order=10"])
    assert rc == 0, capsys.readouterr().err
    model = json.loads(out.read_text())
    assert model["kind"] == "preisach" and model["levels"] == 15
    assert "written" in capsys.readouterr().out
    (tmp_path / "broken.npz").write_bytes(b"garbage")
    rc = main(["identify", "--model", "preisach", "--from-images", str(tmp_path / "broken.npz"), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("afmctl: error:") and "broken.npz" in err and "Traceback" not in err
