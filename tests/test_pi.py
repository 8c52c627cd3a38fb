"""PI operator, its closed-form inverse (eqs. 8–11, Table I), streaming contract, numba vs
reference, model files."""
from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmctl.compensators.base import ModelError
from afmctl.compensators.models import load_model, model_from_dict, save_model
from afmctl.compensators.pi import PIModel, PIOperator, check_pi_parameters, default_thresholds, invert_pi_parameters
from afmctl.compensators.play import PlayOperator, play_reference

# Table I of the extended-PI paper: forward and inverse weight vectors
TABLE_I_FORWARD = [0.793172317251542, 0.442071134534941, 0.020794338851802, 0.106723904368183,
                   0.065040417898840, 0.135513334974812, 0.063105484487529, 0.094334675503508,
                   -0.04126196165719, 0.198065016399163, 0.083849403629362, 0.259960105191838,
                   -0.36562028779604]
TABLE_I_INVERSE = [1.26076008737313, -0.451203073689922, -0.0134026244973307, -0.0623503765956520,
                   -0.0334268448010620, -0.0607110010177552, -0.0248191858337850, -0.0337069309353110,
                   0.0142775047197761, -0.0628110269408285, -0.0227687142171887, -0.0596648017871405,
                   0.0886932904922409]


def multiloop(rng: np.random.Generator, n_turns: int = 40, lo: float = 0.0, hi: float = 150.0,
              max_len: int = 60) -> np.ndarray:
    """Random piecewise-linear signal with many reversals (nested minor loops)."""
    pts = rng.uniform(lo, hi, n_turns)
    segs = [np.array([pts[0]])]
    for a, b in zip(pts[:-1], pts[1:]):
        segs.append(np.linspace(a, b, int(rng.integers(2, max_len)))[1:])
    return np.concatenate(segs)


def table_model(offset: float = 0.0, spacing: float = 6.0) -> PIModel:
    r = (np.arange(13) * spacing).tolist()
    return PIModel(thresholds=r, weights=TABLE_I_FORWARD, offset_nm=offset)


# ------------------------------------------------------------------- Table I ----------

def test_table_I_inverse_weights_reproduced_to_1e12():
    r = np.arange(13) * 5.0
    _, w_inv, _ = invert_pi_parameters(r, TABLE_I_FORWARD)
    assert np.max(np.abs(w_inv - np.array(TABLE_I_INVERSE))) < 1e-12


def test_eq10_needs_its_minus_sign():
    # the printed eq. 10 (without the minus) would give positive w'_1; Table I has it negative
    w = np.array(TABLE_I_FORWARD)
    printed = w[1] / (w[0] * (w[0] + w[1]))
    assert printed > 0 > TABLE_I_INVERSE[1]
    assert abs(-printed - TABLE_I_INVERSE[1]) < 1e-12


def test_inverse_thresholds_eq8_and_partial_sums():
    r = np.array([0.0, 2.0, 5.0, 9.0])
    w = np.array([1.0, 0.5, -0.2, 0.3])
    ri, wi, _ = invert_pi_parameters(r, w)
    # eq. 8 says r'_i is the initial loading curve at r_i: the output of the forward
    # operator (relaxed, no offset) after a ramp from 0 V up to r_i — measured, not recomputed
    ramp = np.linspace(0.0, 9.0, 9001)
    y = PIOperator(r, w).block(ramp)
    for i in range(4):
        assert ri[i] == pytest.approx(y[int(round(r[i] * 1000))], rel=1e-12, abs=1e-12)
    # and the inverse's branch slopes are the reciprocals of the forward ones (eqs. 9-10)
    np.testing.assert_allclose(np.cumsum(wi), 1.0 / np.cumsum(w), rtol=1e-14)


def test_invert_twice_gives_forward_back():
    m = table_model(offset=12.5)
    back = m.inverted().inverted()
    assert back.direction == "forward"
    np.testing.assert_allclose(back.weights, m.weights, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(back.thresholds, m.thresholds, rtol=1e-12, atol=1e-12)


# --------------------------------------------------------- forward∘inverse = identity --

@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forward_of_inverse_is_identity_on_multiloop(seed):
    rng = np.random.default_rng(seed)
    m = table_model(offset=-40.0)
    target = multiloop(rng, lo=-20, hi=160)   # nm
    u = m.inverse().block(target)
    y = m.forward().block(u)
    assert np.max(np.abs(y - target)) <= 1e-9 * np.max(np.abs(target))
    # and the other way round (PI is a bijection on trajectories)
    u2 = multiloop(rng)
    np.testing.assert_allclose(m.inverse().block(m.forward().block(u2)), u2, rtol=0, atol=1e-9 * 150)


def test_identity_with_nonzero_initial_state():
    r = [0.0, 3.0, 7.0, 12.0]
    x0 = [50.0, 48.0, 52.0, 48.0]   # reachable: |x_i - x_{i-1}| <= r_i - r_{i-1}
    m = PIModel(thresholds=r, weights=[0.8, 0.3, 0.2, 0.1], initial_state=x0, offset_nm=5.0)
    target = multiloop(np.random.default_rng(4), lo=0, hi=100)
    y = m.forward().block(m.inverse().block(target))
    assert np.max(np.abs(y - target)) <= 1e-9 * 100


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.05, 3.0), min_size=1, max_size=8),
       st.lists(st.floats(-0.3, 1.0), min_size=8, max_size=8),
       st.lists(st.floats(-1e3, 1e3), min_size=2, max_size=60),
       st.floats(-100, 100))
def test_property_identity_random_models(gaps, wraw, target, offset):
    n = len(gaps) + 1
    r = np.concatenate(([0.0], np.cumsum(gaps)))
    w = np.array([0.5] + wraw[:n - 1])
    S = np.cumsum(w)
    if np.any(S <= 0.05):
        w[np.argmax(S <= 0.05)] += 1.0 - float(S.min())  # keep it invertible
    m = PIModel(thresholds=r.tolist(), weights=w.tolist(), offset_nm=offset)
    tgt = np.array(target)
    y = m.forward().block(m.inverse().block(tgt))
    assert np.max(np.abs(y - tgt)) <= 1e-9 * max(1.0, float(np.max(np.abs(tgt))))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-200, 200), min_size=1, max_size=80), st.integers(1, 7))
def test_property_rate_independent_and_monotone(u, rep):
    m = table_model()
    u = np.array(u)
    y = m.forward().block(u)
    # repeating every sample does not change the values (rate independence)
    y_rep = m.forward().block(np.repeat(u, rep))
    np.testing.assert_array_equal(y_rep[rep - 1::rep], y)
    # a larger input at the same step never gives a smaller output (monotone, S_k > 0)
    op = m.forward()
    for v in u[:-1]:
        op.step(v)
    lo = op.peek(u[-1] - 1.0)
    hi = op.peek(u[-1] + 1.0)
    assert hi > lo


# ------------------------------------------------------------- streaming contract ----

def test_block_equals_step_and_chunking():
    rng = np.random.default_rng(7)
    m = table_model(offset=3.0)
    u = multiloop(rng)
    for op, x in ((m.forward(), u), (m.inverse(), m.forward().block(u))):
        whole = op.block(x)
        op.reset()
        steps = np.array([op.step(v) for v in x])
        op.reset()
        cuts = np.sort(rng.choice(np.arange(1, x.size), 7, replace=False))
        chunks = np.concatenate([op.block(c) for c in np.split(x, cuts)])
        np.testing.assert_array_equal(whole, steps)
        np.testing.assert_array_equal(whole, chunks)


@pytest.mark.parametrize("n", [1, 13, 64])
def test_numba_equals_reference_bit_for_bit(n):
    rng = np.random.default_rng(n)
    r = np.concatenate(([0.0], np.cumsum(rng.uniform(0.5, 3.0, n - 1))))
    w = rng.uniform(0.01, 0.3, n)
    x = multiloop(rng, n_turns=30)
    fast = PIOperator(r, w, in_offset=1.5, out_offset=-2.0)
    ref = PIOperator(r, w, in_offset=1.5, out_offset=-2.0, use_numba=False)
    np.testing.assert_array_equal(fast.block(x), ref.block(x))
    np.testing.assert_array_equal(fast.state, ref.state)
    fast.reset()
    ref.reset()
    a = [fast.step(v) for v in x[:200]]
    b = [ref.step(v) for v in x[:200]]
    assert a == b


def test_play_operator_matches_textbook():
    rng = np.random.default_rng(3)
    u = multiloop(rng, lo=-5, hi=5, n_turns=20)
    p = PlayOperator(1.25, initial_state=0.3)
    np.testing.assert_array_equal(p.block(u), play_reference(u, 1.25, 0.3))
    p.reset()
    assert p.step(10.0) == 8.75 and p.state == 8.75
    with pytest.raises(ModelError, match="threshold"):
        PlayOperator(-1.0)


def test_non_finite_input_rejected():
    op = table_model().forward()
    with pytest.raises(ModelError, match="input: non-finite"):
        op.block(np.array([1.0, np.nan]))


# ------------------------------------------------------------------- model file ----

def test_model_json_roundtrip(tmp_path):
    m = table_model(offset=7.0)
    p = tmp_path / "pi.json"
    save_model(m, p)
    data = json.loads(p.read_text())
    assert data["kind"] == "pi" and len(data["thresholds"]) == 13 and len(data["weights"]) == 13
    m2 = load_model(p)
    assert m2 == m
    inv = m.inverted()
    save_model(inv, tmp_path / "inv.json")
    inv2 = load_model(tmp_path / "inv.json")
    assert inv2.direction == "inverse"
    np.testing.assert_allclose(inv2.weights[:3], TABLE_I_INVERSE[:3], rtol=1e-12)
    # both files describe the same scanner
    x = multiloop(np.random.default_rng(1))
    np.testing.assert_allclose(inv2.forward().block(x), m.forward().block(x), rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("bad, field", [
    (dict(thresholds=[0, 1], weights=[1.0, -2.0]), "weights"),
    (dict(thresholds=[0, 1], weights=[-1.0, 2.0]), "weights"),
    (dict(thresholds=[1, 2], weights=[1.0, 1.0]), "thresholds"),
    (dict(thresholds=[0, 2, 1], weights=[1.0, 1.0, 1.0]), "thresholds"),
    (dict(thresholds=[0, 1], weights=[1.0]), "weights"),
    (dict(thresholds=[0, 1], weights=[1.0, 1.0], initial_state=[0.0, 5.0]), "initial_state"),
    (dict(thresholds=[0, 1], weights=[1.0, float("inf")]), "weights"),
    (dict(thresholds=[], weights=[]), "thresholds"),
])
def test_bad_model_rejected_naming_field(bad, field):
    with pytest.raises(ModelError, match=field):
        model_from_dict({"kind": "pi", **bad}, where="m.json")


def test_check_parameters_and_default_thresholds():
    r = default_thresholds(np.array([10.0, 150.0]), 4)
    np.testing.assert_allclose(r, [0, 17.5, 35, 52.5])
    rr, ww, xx = check_pi_parameters(r, [1, 1, 1, 1])
    assert np.all(xx == 0)


def test_summary_mentions_invertible():
    s = table_model().summary()
    assert "kind pi" in s and "invertible" in s


@pytest.mark.parametrize("n", [3, 13, 64])
def test_peek_equals_step_without_changing_state(n):
    rng = np.random.default_rng(n)
    r = np.concatenate(([0.0], np.cumsum(rng.uniform(0.5, 3.0, n - 1))))
    op = PIOperator(r, rng.uniform(0.01, 0.3, n), in_offset=0.5, out_offset=1.0)
    for v in multiloop(rng, n_turns=10).tolist():
        before = op.state.copy()
        p = op.peek(v)
        np.testing.assert_array_equal(op.state, before)
        assert op.step(v) == p
