"""Classical Preisach model: memory properties, exactness of the inverse, block == step,
compiled kernels == plain-Python reference, model files and bad input."""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmctl.compensators.base import ModelError
from afmctl.compensators.models import load_model, model_from_dict, save_model
from afmctl.compensators.preisach import PreisachModel, ReferencePreisach


def _density(a, b):
    # asymmetric, smooth, strictly positive Preisach density [nm/V²]
    return np.exp(-((a - b - 40.0) ** 2) / (2 * 30.0 ** 2) - ((a + b) / 2 - 10.0) ** 2 / (2 * 80.0 ** 2)) + 0.3


@pytest.fixture(scope="module")
def model() -> PreisachModel:
    return PreisachModel.from_density(_density, -160.0, 160.0, 32, offset_nm=-50.0)


@pytest.fixture(scope="module")
def small_memory_model() -> PreisachModel:
    return PreisachModel.from_density(_density, -160.0, 160.0, 8, memory_depth=4)


def _multi_loop(rng, n_ext=40, lo=-160.0, hi=160.0, pts=25):
    ext = rng.uniform(lo, hi, n_ext)
    start = np.r_[lo, ext[:-1]]
    return np.concatenate([np.linspace(a, b, pts)[1:] for a, b in zip(start, ext)])


signals = st.lists(st.floats(-170.0, 170.0, allow_nan=False), min_size=1, max_size=120).map(np.array)


# ---------------------------------------------------------------- reference and block == step
@settings(max_examples=60, deadline=None)
@given(u=signals)
def test_kernel_equals_plain_python_reference(model, small_memory_model, u):
    for m in (model, small_memory_model):
        y = m.forward().block(u)
        ref = ReferencePreisach(m)
        assert np.array_equal(y, ref.forward(u))
        ref.reset()
        assert np.array_equal(m.inverse().block(y), ref.inverse(y))


@settings(max_examples=60, deadline=None)
@given(u=signals, cuts=st.lists(st.integers(0, 120), max_size=6))
def test_block_equals_per_sample(model, small_memory_model, u, cuts):
    for m in (model, small_memory_model):
        whole = m.forward().block(u)
        op = m.forward()
        steps = np.array([op.step(x) for x in u])
        assert np.array_equal(whole, steps)
        op.reset()
        edges = sorted({0, len(u), *[c for c in cuts if c < len(u)]})
        pieces = np.concatenate([op.block(u[a:b]) for a, b in zip(edges[:-1], edges[1:])])
        assert np.array_equal(whole, pieces)
        inv = m.inverse()
        ib = inv.block(whole)
        inv.reset()
        assert np.array_equal(ib, np.array([inv.step(x) for x in whole]))


# ---------------------------------------------------------------- exact inverse
@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1))
def test_forward_of_inverse_is_identity(model, seed):
    rng = np.random.default_rng(seed)
    lo, hi = model.output_range_nm()
    span = hi - lo
    # random targets inside the reachable range, and outputs of random inputs
    for y in (rng.uniform(lo, hi, 300), model.forward().block(_multi_loop(rng, 12, pts=8))):
        u = model.inverse().block(y)
        assert np.all((u >= model.u_min_V) & (u <= model.u_max_V))
        assert np.max(np.abs(model.forward().block(u) - y)) <= 1e-9 * span


def test_inverse_recovers_the_input_for_strictly_positive_density(model):
    u = _multi_loop(np.random.default_rng(3), 50)
    u_back = model.inverse().block(model.forward().block(u))
    assert np.max(np.abs(u_back - u)) < 1e-9 * 320


def test_inverse_clamps_unreachable_targets_with_a_warning(model, caplog):
    lo, hi = model.output_range_nm()
    inv = model.inverse()
    with caplog.at_level(logging.WARNING, logger="afmctl.compensators.preisach"):
        u = inv.block(np.array([hi + 100.0, lo - 100.0, 0.5 * (lo + hi)]))
    assert u[0] == model.u_max_V and u[1] == model.u_min_V
    assert inv.n_clamped == 2
    assert "clamped" in caplog.text


# ---------------------------------------------------------------- Preisach properties
def test_wiping_out(model):
    """A new maximum above every past maximum erases the memory below it."""
    f = model.forward()
    f.block(np.array([100.0, -80.0, 60.0, -20.0, 40.0, 10.0]))
    assert len(f.memory_V()) == 7
    y1 = f.block(np.array([120.0, 30.0, 90.0, -10.0]))
    g = model.forward()
    y2 = g.block(np.array([120.0, 30.0, 90.0, -10.0]))  # same, without the wiped history
    assert np.array_equal(f.memory_V(), g.memory_V())
    assert np.allclose(y1, y2, rtol=0, atol=1e-9)


def test_return_point_memory(model):
    """After a minor loop the output returns to the reversal point's value and the
    memory is as if the loop never happened."""
    f = model.forward()
    f.block(np.array([150.0, -100.0]))
    y_r = f.step(70.0)
    mem = f.memory_V()
    f.block(np.linspace(70.0, -30.0, 17))     # minor loop down …
    y_back = f.block(np.linspace(-30.0, 70.0, 23))[-1]  # … and back to the reversal point
    assert abs(y_back - y_r) < 1e-9
    y_cont = f.block(np.array([90.0, 0.0]))
    g = model.forward()
    g.block(np.array([150.0, -100.0, 70.0]))
    assert np.allclose(g.block(np.array([90.0, 0.0])), y_cont, atol=1e-9)
    assert len(mem) == 4


def test_congruency_of_minor_loops(model):
    """Minor loops between the same extremes after different histories are congruent
    (they differ by a constant)."""
    loop = np.concatenate([np.linspace(-20.0, 50.0, 30), np.linspace(50.0, -20.0, 30)[1:]])
    fa = model.forward()
    fa.block(np.array([140.0, -20.0]))
    ya = fa.block(loop)
    fb = model.forward()
    fb.block(np.array([80.0, -150.0, 120.0, -20.0]))
    yb = fb.block(loop)
    diff = ya - yb
    assert abs(diff[0]) > 1.0  # the histories really differ
    assert np.ptp(diff) < 1e-9


def test_memory_is_bounded_by_capacity(small_memory_model):
    m = small_memory_model
    f = m.forward()
    # ever smaller nested loops: unbounded memory in the ideal model
    ext = np.array([160.0 * (-0.8) ** k for k in range(40)])
    depth = []
    for x in ext:
        f.step(x)
        depth.append(int(f.ist[0]))  # remembered pairs (memory_V() is a view of a cap+1 array)
    assert max(depth) == m.cap
    g = PreisachModel(**{**m.model_dump(), "memory_depth": 100}).forward()
    g.block(ext)
    assert len(g.memory_V()) == 41  # without the bound every reversal is remembered


def test_forc_and_everett_consistency(model):
    F = model.forc_nm()
    G = model.everett_matrix()
    v = model.nodes_V()
    f = model.forward()
    y = f.block(np.array([v[20], v[7]]))
    assert y[0] == pytest.approx(F[20, 20])
    assert y[1] == pytest.approx(F[20, 7])
    assert np.allclose(G, -G.T)
    w = model.cell_masses()
    assert np.nansum(w) == pytest.approx(model.everett_nm[-1][0])


# ---------------------------------------------------------------- model files and bad input
def test_json_round_trip(model, tmp_path):
    p = tmp_path / "m.json"
    save_model(model, p)
    back = load_model(p)
    assert isinstance(back, PreisachModel)
    u = _multi_loop(np.random.default_rng(0), 10)
    assert np.array_equal(back.forward().block(u), model.forward().block(u))
    assert json.loads(p.read_text())["kind"] == "preisach"


@pytest.mark.parametrize("patch, needle", [
    ({"u_max_V": -200.0}, "u_max_V"),
    ({"levels": 0}, "levels"),
    ({"everett_nm": [[0.0], [1.0]]}, "everett_nm"),
    ({"everett_nm": [[0.0], [-5.0, 0.0], [1.0, 2.0, 0.0]], "levels": 2}, "negative Preisach mass"),
    ({"everett_nm": [[0.0], [5.0, 1.0]], "levels": 1}, "diagonal"),
])
def test_bad_model_files_name_the_field(model, patch, needle):
    data = model.model_dump(mode="json")
    data.update(patch)
    with pytest.raises(ModelError, match=needle):
        model_from_dict(data)


def test_out_of_range_inputs_are_clamped_with_a_warning(model, caplog):
    f = model.forward()
    with caplog.at_level(logging.WARNING, logger="afmctl.compensators.preisach"):
        y = f.block(np.array([500.0, -500.0]))
    assert f.n_clamped == 2
    assert "clamped" in caplog.text
    g = model.forward()
    assert np.array_equal(y, g.block(np.array([160.0, -160.0])))


def test_non_finite_input_is_a_model_error(model):
    with pytest.raises(ModelError, match="u_V"):
        model.forward().block(np.array([0.0, np.nan]))
    with pytest.raises(ModelError, match="y_nm"):
        model.inverse().step(float("inf"))


def test_summary_mentions_grid(model):
    s = model.summary()
    assert "32 levels" in s and "-160" in s


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), levels=st.integers(1, 12), zero_frac=st.floats(0.0, 0.9))
def test_inverse_exact_with_flat_regions(seed, levels, zero_frac):
    """Cell masses with many zeros (flat Everett regions, non-unique inverse): forward of
    the inverse is still the identity and the inverse never leaves the range."""
    rng = np.random.default_rng(seed)
    w = rng.uniform(0.0, 10.0, (levels, levels)) * (rng.uniform(size=(levels, levels)) >= zero_frac)
    m = PreisachModel.from_cell_masses(w, 0.0, 150.0, offset_nm=3.0)
    lo, hi = m.output_range_nm()
    y = np.r_[rng.uniform(lo, hi, 200), m.forward().block(rng.uniform(0.0, 150.0, 100))]
    inv = m.inverse()
    u = inv.block(y)
    assert np.all((u >= 0.0) & (u <= 150.0))
    assert np.max(np.abs(m.forward().block(u) - y)) <= 1e-9 * max(hi - lo, 1.0)
    ref = ReferencePreisach(m)
    assert np.array_equal(u, ref.inverse(y))
