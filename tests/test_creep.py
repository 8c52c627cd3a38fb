"""Linear creep operator (bank of first-order lags, log-spaced τ), its exact inverse and
identification."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from plants import staircase

from afmctl.compensators.base import ModelError
from afmctl.compensators.creep import LinearCreep, LinearCreepInverse, LinearCreepModel, log_spaced_time_constants
from afmctl.compensators.models import model_from_dict

DT = 1e-3


def test_step_response_creeps_in_direction_of_motion_to_static_gain_one():
    op = LinearCreep([0.01, 0.1], [0.05, 0.05], DT)
    y = op.block(np.ones(3000))
    assert y[0] == pytest.approx(1 - 0.05 * np.exp(-0.1) - 0.05 * np.exp(-0.01), rel=1e-12)
    assert np.all(np.diff(y[:1000]) > 0) and np.all(np.diff(y) >= -1e-15)
    assert y[-1] == pytest.approx(1.0, abs=1e-9)


def test_inverse_exact_block_step_and_reference():
    rng = np.random.default_rng(0)
    x = np.repeat(rng.uniform(-50, 150, 60), rng.integers(1, 200, 60))
    tau = log_spaced_time_constants(0.005, 2.0, 4)
    c = [0.02, 0.03, 0.01, 0.04]
    fwd = LinearCreep(tau, c, DT, initial=3.0, gain=80.0, out_offset=5.0)
    inv = LinearCreepInverse(tau, c, DT, initial=3.0, gain=80.0, out_offset=5.0)
    y = fwd.block(x)
    np.testing.assert_allclose(inv.block(y), x, rtol=0, atol=1e-10)
    fwd.reset()
    np.testing.assert_array_equal(np.array([fwd.step(v) for v in x]), y)
    fwd.reset()
    np.testing.assert_array_equal(np.concatenate([fwd.block(x[:77]), fwd.block(x[77:])]), y)
    ref = LinearCreep(tau, c, DT, initial=3.0, gain=80.0, out_offset=5.0, use_numba=False)
    np.testing.assert_array_equal(ref.block(x), y)
    ref_inv = LinearCreepInverse(tau, c, DT, initial=3.0, gain=80.0, out_offset=5.0, use_numba=False)
    inv.reset()
    np.testing.assert_array_equal(ref_inv.block(y), inv.block(y))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(0.0, 0.19), min_size=1, max_size=5), st.lists(st.floats(-1e3, 1e3), min_size=1, max_size=50))
def test_property_inverse(c, x):
    tau = log_spaced_time_constants(0.002, 1.0, len(c))
    x = np.array(x)
    y = LinearCreep(tau, c, DT).block(x)
    np.testing.assert_allclose(LinearCreepInverse(tau, c, DT).block(y), x, rtol=1e-9, atol=1e-9)


def test_identify_recovers_model():
    truth = LinearCreepModel(gain_nm_per_V=100.0, offset_nm=5.0, initial_V=10.0,
                             time_constants_s=[0.05, 0.5, 5.0], creep_weights=[0.03, 0.04, 0.05])
    rng = np.random.default_rng(2)
    _, u = staircase(DT, [10.0] + list(rng.uniform(0, 150, 25)), 1.0)
    t = np.arange(u.size) * DT
    y = truth.forward(DT).block(u)
    m = LinearCreepModel.identify(t, u, y, 3, tau_min_s=0.05, tau_max_s=5.0)
    assert m.gain_nm_per_V == pytest.approx(100.0, rel=1e-8)
    np.testing.assert_allclose(m.creep_weights, truth.creep_weights, rtol=1e-6, atol=1e-9)
    u_back = m.inverse(DT).block(y)
    np.testing.assert_allclose(u_back, u, atol=1e-8)
    assert "kind creep" in m.summary()


def test_bad_parameters():
    with pytest.raises(ModelError, match="sum"):
        LinearCreep([0.1, 1.0], [0.6, 0.5], DT)
    with pytest.raises(ModelError, match="time constant"):
        LinearCreep([0.0], [0.1], DT)
    with pytest.raises(ModelError, match="dt_s"):
        LinearCreep([0.1], [0.1], -1.0)
    with pytest.raises(ModelError, match="creep_weights"):
        model_from_dict({"kind": "creep", "gain_nm_per_V": 1.0, "time_constants_s": [1.0], "creep_weights": [1.5]})
    with pytest.raises(ModelError, match="dt_s"):
        LinearCreepModel(gain_nm_per_V=1.0, time_constants_s=[1.0], creep_weights=[0.1]).forward(None)


def test_creeping_test_plant_is_a_chain_of_plant_and_creep():
    from plants import CreepingPlant, RelayPreisachPlant

    p = CreepingPlant(RelayPreisachPlant(grid=20), dt_s=DT, time_constants_s=[0.1], weights=[0.1])
    _, u = staircase(DT, [0.0, 100.0], 0.5)
    y = p.run(u)
    held = y[501:]
    assert np.all(np.diff(held) > 0)                       # creeps up after the step up
    p.reset()
    np.testing.assert_array_equal(p.run(u), y)             # reset gives the same run
