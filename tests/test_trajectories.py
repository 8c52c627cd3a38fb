"""Trajectory sources: shapes, continuity, kinematic limits, files, streaming."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmctl.inputs import trajectories as tr
from afmctl.config import IndentationSpec, MovesSpec, RasterSpec, SpiralSpec, TextSpec
from afmctl.errors import AfmctlError
from afmctl.inputs.textpath import GLYPHS, strokes

DT = 1e-3


def test_raster_trace_retrace_geometry():
    blocks = list(tr.raster(DT, x0_nm=100, y0_nm=50, width_nm=1000, height_nm=300, lines=4, line_rate_Hz=5))
    p = tr.collect(blocks)
    # 4 lines of 200 samples (+ final return sample)
    assert len(p) == 4 * 200 + 1
    assert p[:, 0].min() == pytest.approx(100) and p[:, 0].max() == pytest.approx(1100)
    assert p[:, 1].min() == pytest.approx(50) and p[:, 1].max() == pytest.approx(350)
    # during each trace the slow axis is still and the fast axis rises at constant speed
    for k in range(4):
        trace = p[200 * k:200 * k + 100]
        assert np.ptp(trace[:, 1]) == 0.0 and trace[0, 1] == pytest.approx(50 + 100 * k)
        assert np.allclose(np.diff(trace[:, 0]), 10.0)
    # no jumps anywhere: steps never exceed one fast-axis sample step
    assert np.abs(np.diff(p, axis=0)).max() <= 10.0 + 1e-9


def test_raster_bidirectional_and_repeat():
    p = tr.collect(tr.raster(DT, width_nm=500, height_nm=500, lines=3, line_rate_Hz=10, mode="bidirectional",
                             repeat=2))
    assert np.abs(np.diff(p, axis=0)).max() < 60.0
    assert p[:, 0].max() == pytest.approx(500, abs=5.0)
    # serpentine: line k runs +x for even k, -x for odd k (100 samples per line at 10 lines/s),
    # while y advances by one pitch (250 nm) per line and never goes back within a frame
    lines = p[:300].reshape(3, 100, 3)
    for k in range(3):
        dx = np.diff(lines[k, :, 0])
        assert np.all(dx > 0) if k % 2 == 0 else np.all(dx < 0)
    assert np.all(np.diff(p[:300, 1]) >= 0) and p[299, 1] == pytest.approx(500.0)
    with pytest.raises(AfmctlError, match="mode"):
        list(tr.raster(DT, mode="zigzag"))


@settings(max_examples=40, deadline=None)
@given(p0=st.tuples(*[st.floats(-5000, 5000)] * 3), p1=st.tuples(*[st.floats(-5000, 5000)] * 3),
       v=st.floats(100, 1e5), a=st.floats(1e3, 1e7), j=st.floats(1e5, 1e10))
def test_smooth_move_respects_limits(p0, p1, v, a, j):
    dt = 1e-4
    seg = tr.smooth_move(p0, p1, dt, v, a, j)
    dist = math.dist(p0, p1)
    if dist == 0:
        assert len(seg) == 0
        return
    np.testing.assert_allclose(seg[-1], p1, atol=1e-9)
    path = np.vstack([p0, seg])
    s = np.linalg.norm(path - np.asarray(p0), axis=1)
    # finite differences of a sampled quintic stay within the continuous peaks (+ rounding)
    vel = np.diff(s) / dt
    assert vel.max() <= v * (1 + 1e-6) + 1e-6
    if len(s) > 3:
        acc = np.diff(s, 2) / dt ** 2
        assert np.abs(acc).max() <= a * (1 + 1e-3) + 1e-3
    # jerk: third differences, with the tip at rest before and after (joins included)
    rest = np.concatenate([[0.0, 0.0], s, [s[-1], s[-1]]])
    jerk = np.diff(rest, 3) / dt ** 3
    assert np.abs(jerk).max() <= j * (1 + 1e-6) + 1e-9 * dist / dt ** 3


def test_moves_dwell_and_spec():
    spec = MovesSpec(points=[{"x_nm": 1000, "y_nm": 0, "dwell_s": 0.05}, {"x_nm": 1000, "y_nm": 1000}],
                     v_max_nm_per_s=10000)
    p = tr.collect(tr.build(spec, DT))
    np.testing.assert_array_equal(p[0], [0, 0, 0])
    np.testing.assert_allclose(p[-1], [1000, 1000, 0])
    at_first = np.all(np.isclose(p, [1000, 0, 0]), axis=1)
    assert at_first.sum() >= 50  # dwell


def test_indentation_array_visits_every_point():
    spec = IndentationSpec(nx=3, ny=2, pitch_x_nm=400, pitch_y_nm=300, depth_nm=80, dwell_s=0.01)
    p = tr.collect(tr.build(spec, DT))
    bottom = p[:, 2] <= -80 + 1e-9
    # indent sites: distinct x-y positions where z is at the bottom
    sites = {(round(x), round(y)) for x, y in p[bottom][:, :2]}
    assert sites == {(400 * i, 300 * j) for i in range(3) for j in range(2)}
    assert p[:, 2].max() == 0.0 and p[-1, 2] == 0.0
    assert np.abs(np.diff(p, axis=0)).max() < 10.0


def test_text_nk_strokes_and_path():
    st_nk = strokes("NK", 600.0)
    assert len(st_nk) == 1 + 3  # N: one stroke, K: three
    # N is 0.4·height wide, K starts one advance further
    assert st_nk[0][:, 0].max() == pytest.approx(400.0)
    assert st_nk[1][:, 0].min() == pytest.approx(550.0)
    p = tr.collect(tr.build(TextSpec(text="NK", height_nm=600, z_down_nm=-30), DT))
    down = p[:, 2] <= -30 + 1e-9
    assert down.any() and p[-1, 2] == 0.0
    assert p[down][:, 1].max() == pytest.approx(600.0) and p[down][:, 1].min() == pytest.approx(0.0)
    assert set("ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789") <= set(GLYPHS)
    with pytest.raises(AfmctlError, match="no stroke glyph"):
        strokes("N#", 100)


def test_spiral_radius_and_speed():
    spec = SpiralSpec(cx_nm=0, cy_nm=0, radius_nm=300, pitch_nm=30, speed_nm_per_s=3000)
    p = tr.collect(tr.build(spec, DT, block_samples=64))
    r = np.hypot(p[:, 0], p[:, 1])
    assert r[0] == pytest.approx(0.0, abs=1e-6) and r.max() == pytest.approx(300.0, rel=1e-6)
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert np.median(step) == pytest.approx(3.0, rel=0.02) and step.max() <= 3.0 + 1e-6


def test_file_csv_and_npy(tmp_path):
    t = np.arange(0, 0.05, 0.002)
    xyz = np.column_stack([t * 1e4, -t * 1e3, np.zeros_like(t)])
    csv = tmp_path / "traj.csv"
    csv.write_text("t,x,y,z\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in np.column_stack([t, xyz])))
    p = tr.collect(tr.from_file(csv, DT))
    assert len(p) == int(round((t[-1] - t[0]) / DT)) + 1
    np.testing.assert_allclose(p[:, 0], np.arange(len(p)) * DT * 1e4, atol=1e-9)
    npy = tmp_path / "traj.npy"
    t2 = np.arange(300) * DT
    np.save(npy, np.column_stack([t2, t2, 2 * t2, 3 * t2]))
    q = tr.collect(tr.from_file(npy, DT, block_samples=64))
    np.testing.assert_allclose(q, np.column_stack([t2, 2 * t2, 3 * t2]))
    np.save(npy, np.zeros((3, 2)))
    with pytest.raises(AfmctlError, match=r"shape \(N, 4\)"):
        list(tr.from_file(npy, DT))
    csv.write_text("t,x,y\n0,1,2\n")
    with pytest.raises(AfmctlError):
        list(tr.from_file(csv, DT))


def test_streaming_is_lazy():
    gen = tr.raster(DT, lines=100000, line_rate_Hz=1.0)
    first = next(gen)
    assert first.shape == (1000, 3)  # one line at a time, not the whole frame


def test_build_from_dict_validates():
    p = tr.collect(tr.build({"kind": "raster", "lines": 2, "line_rate_Hz": 20}, DT))
    assert len(p) == 2 * 50 + 1
    with pytest.raises(AfmctlError, match="lines"):
        tr.build({"kind": "raster", "lines": 0}, DT)


def test_array_source_resamples():
    src = tr.ArraySource(np.column_stack([np.arange(11.0)] * 3), 0.01)
    p = tr.collect(src.blocks_at(0.001, 16))
    assert len(p) == 101 and p[-1, 0] == pytest.approx(10.0)
    with pytest.raises(AfmctlError):
        tr.ArraySource(np.zeros((3, 2)), 0.01)


def test_spec_models_accept_defaults():
    for spec in (RasterSpec(), SpiralSpec(), TextSpec(), IndentationSpec()):
        first = next(iter(tr.build(spec, DT)))
        assert first.ndim == 2 and first.shape[1] == 3 and np.all(np.isfinite(first))


@pytest.mark.parametrize("arr, msg", [
    (np.array([["a", "b", "c", "d"]]), "real numbers"),
    (np.zeros((3, 4), complex), "real numbers"),
    (np.array([[0.0, 1.0, 2.0, 3.0], [1e-3, 1e300, 2.0, 3.0]]), "row 2: position"),
    (np.array([[0.0, 1.0, 2.0, 3.0], [5e-4, 1.0, np.inf, 3.0], [3e-3, 1.0, 2.0, 3.0]]), "at t = 0.001 s"),
    (np.zeros((2, 3)), "shape"),
])
def test_bad_npy_files_give_clear_errors(tmp_path, arr, msg):
    p = tmp_path / "bad.npy"
    np.save(p, arr)
    with pytest.raises(AfmctlError, match=msg) as e:
        tr.collect(tr.from_file(p, 1e-3))
    assert "bad.npy" in str(e.value) and "\n" not in str(e.value)
