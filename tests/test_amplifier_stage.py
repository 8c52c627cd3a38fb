"""The amplifier stage before the hysteresis (#36): kind ``amplifier`` and its place in a chain."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from afmctl.compensators.amplifier import AmplifierModel, fit_amplifier
from afmctl.compensators.base import ModelError
from afmctl.compensators.chain import ChainModel, amplifier_from_dynamics, join_structure, parse_structure
from afmctl.compensators.dynamics import LinearDynamicsModel
from afmctl.compensators.models import model_from_dict
from afmctl.compensators.pi import PIModel

DT = 1e-4


def _command(seconds: float = 2.0) -> np.ndarray:
    """Slow triangles, then square steps of 60 V (beyond an 80 kV/s slew limit at 10 kHz)."""
    t = np.arange(int(seconds / DT)) * DT
    tri = 75.0 + 60.0 * (2.0 * np.abs((t * 3.0) % 1.0 - 0.5) * 2.0 - 1.0) / 2.0
    steps = np.where((np.arange(4000) // 400) % 2 == 0, 45.0, 105.0)
    return np.concatenate([tri, steps])


def test_numba_kernels_equal_the_reference_and_blocks_equal_steps():
    amp = AmplifierModel(bandwidth_Hz=420.0, slew_V_per_s=8e4)
    u = _command(0.5)
    ref = amp.forward(DT, use_numba=False).block(u)
    fast = amp.forward(DT).block(u)
    op = amp.forward(DT)
    stepped = np.array([op.step(float(x)) for x in u])
    op2 = amp.forward(DT)
    blocks = np.concatenate([op2.block(u[:7]), op2.block(u[7:1000]), op2.block(u[1000:])])
    assert np.array_equal(ref, fast) and np.array_equal(fast, stepped) and np.array_equal(fast, blocks)
    inv_ref = amp.inverse(DT, use_numba=False).block(ref)
    inv = amp.inverse(DT)
    assert np.array_equal(inv_ref, inv.block(ref))


def test_inverse_is_exact_within_the_slew_limit_and_never_asks_for_more():
    amp = AmplifierModel(bandwidth_Hz=300.0, slew_V_per_s=5e4)
    t = np.arange(5000) * DT
    v_wanted = 75.0 + 40.0 * np.sin(2 * np.pi * 20.0 * t)          # at most 5.0e3 V/s
    inv = amp.inverse(DT)
    u = inv.block(v_wanted)
    assert inv.n_limited == 0
    assert np.allclose(amp.forward(DT).block(u), v_wanted, atol=1e-9)
    jump = np.r_[np.full(50, 20.0), np.full(200, 120.0)]           # 100 V in one sample
    inv = amp.inverse(DT)
    u = inv.block(jump)
    v = amp.forward(DT).block(u)
    assert inv.n_limited > 0
    assert np.max(np.abs(np.diff(v))) <= 5e4 * DT * (1 + 1e-12)      # the stage is never asked for more


def test_fit_recovers_bandwidth_and_slew_from_a_recorded_piezo_voltage():
    true = AmplifierModel(bandwidth_Hz=420.0, slew_V_per_s=8e4)
    u = _command()
    t = np.arange(u.size) * DT
    v = true.forward(DT).block(u) + np.random.default_rng(1).normal(0.0, 0.05, u.size)
    fit = fit_amplifier(t, u, v)
    assert fit.bandwidth_Hz == pytest.approx(420.0, rel=0.02)
    assert fit.slew_V_per_s == pytest.approx(8e4, rel=0.03)


def test_a_record_that_never_reaches_the_slew_limit_leaves_it_unset():
    true = AmplifierModel(bandwidth_Hz=420.0, slew_V_per_s=8e4)
    u = _command()[: int(2.0 / DT)]                                # the triangles only
    t = np.arange(u.size) * DT
    v = true.forward(DT).block(u) + np.random.default_rng(2).normal(0.0, 0.05, u.size)
    fit = fit_amplifier(t, u, v)
    assert fit.slew_V_per_s is None and fit.fit_info is not None
    assert fit.fit_info["slew_seen_V_per_s"] < 8e4


def test_a_scaled_monitor_is_refused_in_one_line():
    u = _command(0.5)
    t = np.arange(u.size) * DT
    with pytest.raises(ModelError, match=r"^v: the piezo voltage moves 0\.1 V per V .*allowed 0\.80 … 1\.25 V/V"):
        fit_amplifier(t, u, 0.1 * u)


def test_structures_with_the_amplifier_first():
    assert parse_structure("amplifier+preisach+creep+dynamics") == ("preisach", ("amplifier", "creep", "dynamics"))
    assert join_structure("pi", ("dynamics", "amplifier")) == "amplifier+pi+dynamics"
    for bad in ("preisach+amplifier", "amplifier", "amplifier+creep+pi"):
        with pytest.raises(ModelError, match=r"allowed \[amplifier\+\]<pi\|epi\|preisach\|bouc-wen\|rate-pi\|rate-bouc-wen>"):
            parse_structure(bad)


def _chain() -> ChainModel:
    hyst = PIModel(thresholds=[0.0, 10.0, 20.0], weights=[60.0, 15.0, 8.0])
    dyn = LinearDynamicsModel.from_modes([(900.0, 0.03)])
    return ChainModel(amplifier=AmplifierModel(bandwidth_Hz=350.0, slew_V_per_s=3e4), hysteresis=hyst, dynamics=dyn)


def test_chain_file_round_trip_and_forward_order():
    chain = _chain()
    again = model_from_dict(json.loads(chain.model_dump_json()))
    assert isinstance(again, ChainModel) and again.structure == "amplifier+pi+dynamics"
    u = _command(0.3)
    manual = chain.dynamics.forward(DT).block(chain.hysteresis.forward(DT).block(
        chain.amplifier.forward(DT).block(u)))                     # type: ignore[union-attr]
    assert np.array_equal(again.forward(DT).block(u), manual)


def test_offline_inverse_keeps_range_command_slew_and_the_amplifiers_slew():
    chain = _chain()
    t = np.arange(int(0.12 / DT)) * DT
    ph = (t * 50.0) % 1.0
    target = 2000.0 + 6000.0 * (1 - np.abs(2 * ph - 1))            # 50 lines/s, sharp corners
    res = chain.inverse_within_limits(target, DT, 0.0, 150.0, slew_V_per_s=1e5)
    u = res.u_V
    assert u.min() >= 0.0 and u.max() <= 150.0
    assert np.max(np.abs(np.diff(u))) <= 1e5 * DT * (1 + 1e-9)
    v = chain.amplifier.forward(DT).block(u)                       # type: ignore[union-attr]
    assert np.max(np.abs(np.diff(v))) <= 3e4 * DT * (1 + 1e-9)
    y = chain.forward(DT).block(u)
    keep = ((ph % 0.5) > 0.05) & ((ph % 0.5) < 0.45) & (t > 0.04)
    assert np.max(np.abs(y - target)[keep]) < 0.01 * 6000.0         # the lines are followed


def test_the_sandwich_takes_the_lag_below_the_first_mode():
    dyn = LinearDynamicsModel.from_modes([(650.0, 0.04)], real_poles_Hz=[300.0, 5000.0])
    amp = amplifier_from_dynamics(dyn)
    assert amp is not None and amp.bandwidth_Hz == pytest.approx(300.0) and amp.slew_V_per_s is None
    assert amplifier_from_dynamics(LinearDynamicsModel.from_modes([(650.0, 0.04)], real_poles_Hz=[5000.0])) is None


def test_band_limit_names_the_first_mode_not_a_slower_lag():
    dyn = LinearDynamicsModel.from_modes([(648.0, 0.04)], real_poles_Hz=[354.0])
    assert dyn.inverse_bandwidth_Hz(DT) == pytest.approx(1.5 * 648.0)
    lag_only = LinearDynamicsModel.from_modes([], real_poles_Hz=[354.0, 2000.0])
    assert lag_only.inverse_bandwidth_Hz(DT) == pytest.approx(1.5 * 354.0)
    assert math.isclose(LinearDynamicsModel.from_modes([(8000.0, 0.1)]).inverse_bandwidth_Hz(DT), 0.45 / DT)
