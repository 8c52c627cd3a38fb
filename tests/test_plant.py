"""Plant kernels of the simulated scanner: numba twins equal the Python references, the
Preisach operator equals a brute-force relay grid, exact discretisations, amplifier limits."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.signal import cont2discrete

from afmctl.sim_backend import _plant_kernels as K
from afmctl.sim_backend.config import (AmplifierConfig, AxisConfig, CreepConfig, DynamicsConfig, GaussianPreisachConfig,
                                PreisachComponent, default_preisach)
from afmctl.sim_backend.plant import AxisPlant, GaussianPreisachOperator, everett_table, mode_matrices, preisach_weights

SMALL = GaussianPreisachConfig(
    u_min_V=0.0, u_max_V=150.0, n_grid=16, linear_nm_per_V=10.0,
    components=[PreisachComponent(mass_nm=800, alpha_V=90, beta_V=30, sigma_alpha_V=30, sigma_beta_V=20, rho=0.2),
                PreisachComponent(mass_nm=300, alpha_V=60, beta_V=55, sigma_alpha_V=25, sigma_beta_V=25, rho=0.8)])

volt_lists = st.lists(st.floats(-20.0, 170.0, allow_nan=False), min_size=1, max_size=200)


def relay_reference(cfg: GaussianPreisachConfig, u: np.ndarray) -> np.ndarray:
    """Brute force: every cell of the grid is one relay, up at u ≥ v_{i+1}, down at u ≤ v_j."""
    W = preisach_weights(cfg)
    v = np.linspace(cfg.u_min_V, cfg.u_max_V, cfg.n_grid)
    n = cfg.n_grid - 1
    up_at = np.repeat(v[1:, None], n, axis=1)
    down_at = np.repeat(v[None, :-1], n, axis=0)
    state = np.zeros((n, n), dtype=bool)
    out = np.empty(u.size)
    for k, x in enumerate(np.clip(u, cfg.u_min_V, cfg.u_max_V)):
        state |= x >= up_at
        state &= ~(x <= down_at)
        out[k] = cfg.linear_nm_per_V * (x - cfg.u_min_V) + W[state].sum()
    return out


def test_everett_table_is_the_relay_mass_switched_off():
    E = everett_table(SMALL)
    W = preisach_weights(SMALL)
    assert E[-1, 0] == pytest.approx(W.sum())
    assert np.all(E[np.triu_indices_from(E)] == 0)
    # E is nondecreasing in alpha and nonincreasing in beta (nonnegative density)
    assert np.all(np.diff(E, axis=0) >= -1e-9)
    lower = np.tril(E, -1)
    assert np.all(np.diff(lower, axis=1)[np.tril_indices(E.shape[0] - 1, -1)] <= 1e-9)


@settings(max_examples=40, deadline=None)
@given(idx=st.lists(st.integers(0, 15), min_size=1, max_size=60))
def test_preisach_equals_relay_grid_on_grid_inputs(idx):
    v = np.linspace(0.0, 150.0, 16)
    u = v[np.array(idx)]
    op = GaussianPreisachOperator(SMALL, fast=False)
    np.testing.assert_allclose(op.block(u), relay_reference(SMALL, u), rtol=0, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(u=volt_lists)
def test_preisach_numba_equals_reference(u):
    u = np.array(u)
    fast = GaussianPreisachOperator(default_preisach("x"), fast=True)
    ref = GaussianPreisachOperator(default_preisach("x"), fast=False)
    np.testing.assert_array_equal(fast.block(u), ref.block(u))


@settings(max_examples=30, deadline=None)
@given(u=volt_lists, cut=st.integers(0, 200))
def test_preisach_block_equals_per_sample(u, cut):
    u = np.array(u)
    a = GaussianPreisachOperator(SMALL)
    whole = a.block(u)
    a.reset()
    steps = np.array([a.step(x) for x in u])
    a.reset()
    parts = np.concatenate([a.block(u[:cut]), a.block(u[cut:])])
    np.testing.assert_array_equal(whole, steps)
    np.testing.assert_array_equal(whole, parts)


def test_preisach_wiping_out_and_saturation():
    op = GaussianPreisachOperator(default_preisach("x"))
    y = op.block(np.array([0.0, 120.0, 40.0, 100.0, 60.0, 120.0]))
    op.reset()
    y_direct = op.block(np.array([0.0, 120.0]))
    # returning to the previous maximum wipes out the inner loop: same output as before it
    assert y[-1] == pytest.approx(y_direct[-1], abs=1e-9)
    op.reset()
    assert op.block(np.array([150.0]))[0] == pytest.approx(op.saturation_nm)
    # asymmetric loop: ascending and descending branches differ by > 5 % of the range
    op.reset()
    up = op.block(np.linspace(0, 150, 301))
    down = op.block(np.linspace(150, 0, 301))[::-1]
    assert np.max(down - up) > 0.05 * op.saturation_nm
    assert np.all(down >= up - 1e-9)


@settings(max_examples=40, deadline=None)
@given(u=volt_lists, bits=st.sampled_from([0, 8, 16]), slew=st.floats(1.0, 50.0), bw=st.sampled_from([0.0, 0.5]))
def test_amplifier_reference_equals_numba_and_respects_limits(u, bits, slew, bw):
    u = np.array(u)
    lsb = 150.0 / (2**bits - 1) if bits else 0.0
    outs = []
    for fn in (K.amplifier_py, K.amplifier_nb):
        state = np.array([0.0, 0.0])
        out = np.empty_like(u)
        fn(u, out, state, 0.0, 150.0, lsb, slew, bw)
        outs.append(out)
    np.testing.assert_array_equal(outs[0], outs[1])
    out = outs[0]
    assert np.all(out >= 0.0) and np.all(out <= 150.0)
    if bw == 0.0:  # no filter: the output is the slewed value, steps ≤ slew
        steps = np.abs(np.diff(np.concatenate([[0.0], out])))
        assert np.all(steps <= slew + 1e-9)


def test_creep_dynamics_reference_equals_numba():
    rng = np.random.default_rng(1)
    h = np.cumsum(rng.normal(0, 10, 500))
    a_c = np.exp(-1e-3 / np.geomspace(0.01, 100, 5))
    g_c = np.full(5, 0.01)
    ad, bd = mode_matrices(DynamicsConfig(resonance_Hz=1000, quality_factor=20), 1e-4)
    outs = []
    for fn in (K.creep_dynamics_py, K.creep_dynamics_nb):
        out = np.empty_like(h)
        fn(h, out, a_c, g_c, np.zeros(5), ad, bd, np.zeros(2), True)
        outs.append(out)
    np.testing.assert_array_equal(outs[0], outs[1])


def test_expansion_drift_reference_equals_numba():
    T = 22 + np.linspace(0, 2, 300)
    outs = []
    for fn in (K.expansion_drift_py, K.expansion_drift_nb):
        out = np.empty((300, 3))
        fn(T, out, np.array([1.0, 2.0, 3.0]), 0.99, np.array([22.0]), 22.0)
        outs.append(out)
    np.testing.assert_array_equal(outs[0], outs[1])


def test_mode_discretisation_is_exact_zoh():
    dyn = DynamicsConfig(resonance_Hz=1000.0, quality_factor=15.0)
    dt = 2e-5
    ad, bd = mode_matrices(dyn, dt)
    w = 2 * math.pi * 1000.0
    A = np.array([[0, 1], [-w * w, -w / 15.0]])
    B = np.array([[0], [w * w]])
    Ad, Bd, *_ = cont2discrete((A, B, np.eye(2), np.zeros((2, 1))), dt, method="zoh")
    np.testing.assert_allclose(ad, Ad, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(bd, Bd[:, 0], rtol=1e-9, atol=1e-12)


def test_axis_step_response_creep_and_resonance():
    """A step of 10 V: the mode rings at ~1 kHz with overshoot (Q = 20), then the output
    creeps up by the creep fraction towards the static value (DC gain 1)."""
    cfg = AxisConfig(amplifier=AmplifierConfig(bits=0, slew_V_per_s=None, bandwidth_Hz=None),
                     hysteresis=GaussianPreisachConfig(linear_nm_per_V=80.0),
                     creep=CreepConfig(fraction=0.04, tau_min_s=0.01, tau_max_s=1.0, n_lags=3),
                     dynamics=DynamicsConfig(resonance_Hz=1000.0, quality_factor=20.0))
    ax = AxisPlant(cfg)
    dt = 1e-5
    y = ax.run(np.full(100_000, 10.0), dt)  # 1 s
    static = 800.0
    assert y.max() > 1.5 * 0.96 * static * 0.9  # resonant overshoot
    k = np.argmax(y)
    assert 0.3e-3 < k * dt < 0.7e-3  # half a period of 1 kHz
    assert y[int(0.02 / dt)] < static * 0.985  # still creeping at 20 ms
    y2 = ax.run(np.full(1_000_000, 10.0), 1e-5)  # 10 more seconds
    assert y2[-1] == pytest.approx(static, rel=1e-3)


def test_axis_plant_reference_path_equals_fast_path():
    from afmctl.sim_backend.config import default_scanner_config

    cfg = default_scanner_config().x
    u = 75 + 70 * np.sin(np.linspace(0, 20, 3000))
    a, b = AxisPlant(cfg, fast=True), AxisPlant(cfg, fast=False)
    np.testing.assert_array_equal(a.run(u, 1e-4), b.run(u, 1e-4))


def test_kernels_release_the_gil():
    """The compiled loops are nogil, so an in-process scanner does not stall the other
    Python threads (e.g. a controller's real-time loop) while it computes."""
    for name in ("amplifier_nb", "preisach_nb", "creep_dynamics_nb", "expansion_drift_nb"):
        kernel = getattr(K, name)
        assert kernel.targetoptions.get("nogil") is True, name
        assert type(kernel._cache).__name__ != "NullCache", name  # cache=True kept


@settings(max_examples=40, deadline=None)
@given(u=volt_lists, cap=st.integers(2, 6), cut=st.integers(0, 200))
def test_preisach_memory_overflow_reference_equals_numba_and_blocks(u, cap, cut):
    """With a tiny memory (deep nesting forgets the innermost loop, the compensators'
    rule) the numba and reference kernels agree and blocks equal one run."""
    u = np.array(u)
    ops = [GaussianPreisachOperator(SMALL, fast=f) for f in (False, True)]
    outs = []
    for op in ops:
        op.s, op.P = op.s[: cap + 1].copy(), op.P[: cap + 1].copy()
        outs.append(np.concatenate([op.block(u[:cut]), op.block(u[cut:])]))
    np.testing.assert_array_equal(outs[0], outs[1])
    whole = GaussianPreisachOperator(SMALL)
    whole.s, whole.P = whole.s[: cap + 1].copy(), whole.P[: cap + 1].copy()
    np.testing.assert_array_equal(whole.block(u), outs[1])
    assert np.all(np.isfinite(outs[1]))


def test_preisach_memory_is_the_compensators_memory():
    """One piece of code: the sim's Preisach memory after any input equals the memory the
    compensators' Preisach kernel keeps (same turning points, same count)."""
    from afmctl.compensators import _preisach_kernels as PK

    rng = np.random.default_rng(3)
    u = np.clip(np.cumsum(rng.normal(0, 15, 400)) + 75, 0, 150)
    op = GaussianPreisachOperator(SMALL)
    s2 = np.zeros_like(op.s)
    s2[0] = 0.0
    K2 = 0
    for k, x in enumerate(u):
        op.block(np.array([x]))
        K2 = PK._memory_update(float(x), s2, K2, s2.shape[0] - 1)
        assert op.ist[0] == K2
        np.testing.assert_array_equal(op.s[: K2 + 1], s2[: K2 + 1])


def _linear_axis(**kw) -> AxisConfig:
    return AxisConfig(amplifier=kw.pop("amplifier", AmplifierConfig(bits=0, slew_V_per_s=None, bandwidth_Hz=None)),
                      hysteresis=GaussianPreisachConfig(linear_nm_per_V=80.0), **kw)


def test_capacitive_load_sets_bandwidth_and_slew():
    """Output resistance × piezo capacitance is a low-pass; a current limit slews at I/C."""
    amp = AmplifierConfig(bits=0, slew_V_per_s=None, bandwidth_Hz=None, load_capacitance_F=1e-6,
                          output_resistance_ohm=100.0, current_limit_A=0.05)
    assert amp.effective_bandwidth_Hz() == pytest.approx(1 / (2 * np.pi * 1e-4))
    assert amp.effective_slew_V_per_s() == pytest.approx(5e4)
    ax = AxisPlant(_linear_axis(amplifier=amp))
    dt = 1e-6
    _, v = ax.run(np.full(4000, 100.0), dt, return_voltage=True)
    assert np.max(np.diff(v)) <= 5e4 * dt * (1 + 1e-9)  # slewing at I/C
    assert v[int(1.5e-3 / dt)] < 80.0  # 2 ms of slewing to 100 V
    assert v[-1] == pytest.approx(100.0, abs=0.5)  # then settled (RC = 100 µs)
    # the smaller capacitance of a second piezo: faster
    fast = amp.model_copy(update={"load_capacitance_F": 1e-7})
    assert fast.effective_bandwidth_Hz() == pytest.approx(10 * amp.effective_bandwidth_Hz())
    # an amplifier's own figure below the RC one wins
    assert amp.model_copy(update={"bandwidth_Hz": 100.0}).effective_bandwidth_Hz() == 100.0


def test_extra_modes_in_series_match_the_linear_response_and_blocks():
    cfg = _linear_axis(dynamics=DynamicsConfig(resonance_Hz=1000.0, quality_factor=30.0),
                       extra_modes=[DynamicsConfig(resonance_Hz=3500.0, quality_factor=15.0)])
    dt = 1e-5
    f0 = 3500.0
    t = np.arange(40_000) * dt
    u = 50 + 0.5 * np.sin(2 * np.pi * f0 * t)
    fast, ref = AxisPlant(cfg), AxisPlant(cfg, fast=False)
    y = fast.run(u, dt)
    np.testing.assert_array_equal(ref.run(u, dt), y)
    blocks = AxisPlant(cfg)
    np.testing.assert_array_equal(np.concatenate([blocks.run(u[:1234], dt), blocks.run(u[1234:], dt)]), y)
    # steady-state amplitude at 3.5 kHz equals |linear_response| × 80 nm/V × 0.5 V
    g = AxisPlant(cfg).linear_response(np.array([f0]), dt)[0]
    tail = y[-int(0.1 / dt):]
    assert (tail.max() - tail.min()) / 2 == pytest.approx(abs(g) * 80 * 0.5, rel=0.01)
    one = AxisPlant(cfg.model_copy(update={"extra_modes": []})).linear_response(np.array([f0]), dt)[0]
    assert abs(g) / abs(one) == pytest.approx(15.0, rel=0.05)  # the second mode's resonance (Q 15) shows
    fast.reset()
    np.testing.assert_array_equal(fast.run(u, dt), y)


def _loop_width_nm(rate_lag_s: float, f_Hz: float, dt_s: float = 1e-5) -> float:
    """Width of the hysteresis loop [nm] at mid-range (75 V) for a 0–150 V cosine at f_Hz,
    hysteresis alone (no amplifier limits, creep or mode), third period."""
    from afmctl.sim_backend.scanner import default_scanner_config
    cfg = default_scanner_config().x.model_copy(deep=True)
    cfg.hysteresis.rate_lag_s = rate_lag_s
    cfg.creep, cfg.dynamics = None, None
    cfg.amplifier.bandwidth_Hz, cfg.amplifier.slew_V_per_s = None, None
    n = int(round(1.0 / f_Hz / dt_s))
    u = 75.0 - 75.0 * np.cos(2 * np.pi * f_Hz * np.arange(3 * n) * dt_s)
    y, uu = AxisPlant(cfg).run(u, dt_s)[-n:], u[-n:]
    rising = np.gradient(uu) > 0
    at = [np.interp(75.0, np.sort(uu[m]), y[m][np.argsort(uu[m])]) for m in (~rising, rising)]
    return float(at[0] - at[1])


def test_rate_dependent_hysteresis_widens_the_loop_with_speed():
    """rate_lag_s = 0: the loop is the same at 1 and 300 Hz (rate-independent Preisach);
    0.2 ms: it widens with the rate (measured 1710 / 2405 / 3304 nm at 1 / 100 / 300 Hz
    against 1703 nm rate-independent)."""
    still = [_loop_width_nm(0.0, f) for f in (1.0, 300.0)]
    assert still[0] == pytest.approx(still[1], rel=1e-3)
    w = [_loop_width_nm(2e-4, f) for f in (1.0, 100.0, 300.0)]
    assert w[0] == pytest.approx(still[0], rel=0.02)
    assert w[0] < w[1] < w[2] and w[2] > 1.5 * still[0]


def test_rate_dependent_hysteresis_carries_its_state_and_matches_the_reference():
    from afmctl.sim_backend.scanner import default_scanner_config
    cfg = default_scanner_config().x.model_copy(deep=True)
    cfg.hysteresis.rate_lag_s = 1e-3
    u = 75.0 + 70.0 * np.sin(np.arange(5000) * 2 * np.pi / 1000)
    whole = AxisPlant(cfg).run(u, 1e-5)
    p = AxisPlant(cfg)
    split = np.concatenate([p.run(u[:1234], 1e-5), p.run(u[1234:], 1e-5)])
    np.testing.assert_array_equal(whole, split)
    np.testing.assert_array_equal(whole, AxisPlant(cfg, fast=False).run(u, 1e-5))
