"""Drift transfer functions and the streaming predictor (compensators.drift)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from afmctl.compensators.base import ModelError
from afmctl.compensators.drift import (DriftParams, DriftPaths, SecondOrder, StateSpacePath, TransferPath,
                                drift_reference)

NAMES = ("physical_tube", "table_a1")


def _signals(n: int, seed: int = 0, dt: float = 1e-3):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    T = 21.0 + 0.5 * np.sin(2 * np.pi * t / (n * dt)) + 0.01 * rng.standard_normal(n)
    U = 75.0 + 60.0 * np.column_stack([np.sin(2 * np.pi * 3 * t), np.sin(2 * np.pi * 0.2 * t), np.cos(t)])
    return T, U


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("dt", [1e-3, 1e-4])
def test_block_equals_step_exactly(name, dt):
    p = DriftParams.named(name)
    T, U = _signals(600, dt=dt)
    pred = p.predictor(dt)
    whole = pred.block(T, U)
    pred.reset()
    stepped = np.array([pred.step(T[i], U[i]) for i in range(T.size)])
    assert np.array_equal(whole, stepped)
    assert np.any(whole != 0.0)


@settings(max_examples=25, deadline=None)
@given(cuts=st.lists(st.integers(min_value=0, max_value=400), min_size=1, max_size=6))
def test_block_any_split_equals_whole(cuts):
    p = DriftParams.named("table_a1")
    T, U = _signals(400, seed=3)
    pred = p.predictor(1e-3)
    whole = pred.block(T, U)
    pred.reset()
    edges = [0] + sorted(cuts) + [400]
    parts = [pred.block(T[a:b], U[a:b]) for a, b in zip(edges[:-1], edges[1:])]
    assert np.array_equal(np.concatenate(parts), whole)


@pytest.mark.parametrize("name", NAMES)
def test_numba_kernel_equals_plain_reference(name):
    p = DriftParams.named(name)
    T, U = _signals(1500, seed=1)
    fast = p.predictor(1e-3).block(T, U)
    ref = drift_reference(p, 1e-3, T, U)
    assert np.array_equal(fast, ref)


@pytest.mark.parametrize("name", NAMES)
def test_constant_temperature_zero_voltage_gives_zero_drift(name):
    pred = DriftParams.named(name).predictor(1e-3)
    d = pred.block(np.full(5000, 23.7), np.zeros((5000, 3)))
    assert np.all(d == 0.0)


@pytest.mark.parametrize("name", NAMES)
def test_no_response_before_the_input_changes(name):
    pred = DriftParams.named(name).predictor(1e-3)
    T = np.full(3000, 20.0)
    T[1700:] += 1.0
    U = np.zeros((3000, 3))
    U[2500:, 0] = 10.0
    d = pred.block(T, U)
    assert np.all(d[:1701] == 0.0)          # strictly proper: first response one sample later
    assert np.any(d[1701:] != 0.0)


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=10, deadline=None)
@given(c=st.floats(min_value=-5.0, max_value=5.0).filter(lambda v: abs(v) > 1e-3))
def test_linear_in_temperature_change(name, c):
    p = DriftParams.named(name)
    t = np.arange(2000) * 1e-2
    dT = 0.5 * np.sin(t / 3.0) + 0.002 * t
    d1 = p.predictor(1e-2).block(20.0 + dT)
    d2 = p.predictor(1e-2).block(20.0 + c * dT)
    scale = np.max(np.abs(d1), axis=0)
    assert np.all(np.abs(d2 - c * d1) <= 1e-9 * np.abs(c) * scale + 1e-300)


@pytest.mark.parametrize("name", NAMES)
def test_doubling_the_temperature_change_doubles_the_drift(name):
    p = DriftParams.named(name)
    dT = np.linspace(0, 2.0, 3000)
    d1 = p.predictor(1e-3).block(20.0 + dT)
    d2 = p.predictor(1e-3).block(20.0 + 2 * dT)
    assert np.max(np.abs(d1)) > 0
    # exact up to the rounding of T = 20 + ΔT in the input (relative 1e-15 of 20 °C)
    np.testing.assert_allclose(d2, 2 * d1, rtol=1e-9, atol=1e-9 * np.max(np.abs(d1)))


def test_first_order_lag_step_is_exact():
    """ZOH discretisation is exact for a step: K(1 − exp(−t/τ)) at every sample."""
    p = DriftParams(paths=DriftPaths(xT=TransferPath(K=3.0, poles_s=[0.25])))
    dt = 1e-3
    T = np.full(2000, 20.0)
    T[10:] = 21.0
    d = p.predictor(dt).block(T)
    j = np.arange(2000 - 10)
    expected = 3.0 * (1.0 - np.exp(-j * dt / 0.25))
    np.testing.assert_allclose(d[10:, 0], expected, rtol=1e-12, atol=1e-13)
    assert np.all(d[:, 1:] == 0.0)


@pytest.mark.parametrize("path", [
    TransferPath(K=5.8e-9, poles_s=[0.001, 907.8], zeros_s=[-6809.4]),
    TransferPath(K=2.0, poles_s=[0.5, 0.05], zeros_s=[0.2, -0.1]),
    TransferPath(K=0.7, integrators=1, poles_s=[0.3], zeros_s=[0.6]),
    TransferPath(K=1.5, second_order=SecondOrder(Tw_s=0.1, zeta=0.2), zeros_s=[0.05]),
    TransferPath(K=1.5, integrators=1, second_order=SecondOrder(Tw_s=0.05, zeta=3.0)),
])
def test_cascade_matches_the_continuous_step_response(path):
    from scipy import signal
    num = np.array([path.K])
    for tz in path.zeros_s:
        num = np.polymul(num, [tz, 1.0])
    den = np.array([1.0])
    for tp in path.poles_s:
        den = np.polymul(den, [tp, 1.0])
    for _ in range(path.integrators):
        den = np.polymul(den, [1.0, 0.0])
    if path.second_order:
        tw, z = path.second_order.Tw_s, path.second_order.zeta
        den = np.polymul(den, [tw * tw, 2 * z * tw, 1.0])
    scale = 1e9 if path.K < 1e-6 else 1.0
    p = DriftParams(output_scale_nm=scale, paths=DriftPaths(xT=path))
    dt = 1e-3
    n = 3000
    T = np.full(n + 1, 20.0)
    T[1:] = 21.0
    d = p.predictor(dt).block(T)[1:, 0]
    tt = np.arange(n) * dt
    _, y = signal.step((num, den), T=tt)
    np.testing.assert_allclose(d, scale * y, rtol=1e-6, atol=1e-9 * scale * np.max(np.abs(y)))


def test_delay_is_an_integer_number_of_samples():
    p = DriftParams(paths=DriftPaths(zT=TransferPath(K=1.0, poles_s=[0.1], delay_s=0.5)))
    dt = 0.01
    T = np.full(200, 20.0)
    T[5:] = 22.0
    d = p.predictor(dt).block(T)
    first = int(np.flatnonzero(d[:, 2])[0])
    assert first == 5 + 50 + 1


def test_state_space_path_runs_at_its_own_period():
    """A discrete path identified at Ts = 10·dt: output changes every 10 samples and
    equals the direct simulation at Ts for a constant input."""
    A = [[0.9, 0.05], [0.0, 0.8]]
    B, C = [1.0, 0.5], [0.3, -0.2]
    p = DriftParams(paths=DriftPaths(yT=StateSpacePath(A=A, B=B, C=C, Ts_s=0.1)))
    dt = 0.01
    T = np.full(1 + 300, 20.0)
    T[1:] = 21.0
    d = p.predictor(dt).block(T)[:, 1]
    x = np.zeros(2)
    ys = []
    An, Bn, Cn = np.array(A), np.array(B), np.array(C)
    for _ in range(30):
        ys.append(Cn @ x)
        x = An @ x + Bn * 1.0
    # sample 0 is the reference; sample 1 starts the first window of 10 samples with input 1
    # (window 0 spans samples 0..9: average input 0.9)
    assert np.all(d[:10] == 0.0)
    assert np.all(d[10:20] == d[10])
    x = np.zeros(2)
    x = An @ x + Bn * 0.9
    expected = [Cn @ x]
    for _ in range(10):
        x = An @ x + Bn * 1.0
        expected.append(Cn @ x)
    for k in range(10):
        np.testing.assert_allclose(d[10 + 10 * k], expected[k], rtol=1e-12)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("dt", [1e-3, 1e-4])
def test_discretisation_is_stable(name, dt):
    pred = DriftParams.named(name).predictor(dt)
    Ad = pred.system.Ad
    rho = max(abs(np.linalg.eigvals(Ad))) if Ad.size else 0.0
    assert rho <= 1.0 + 1e-12
    d = pred.block(np.full(20000, 21.0), np.full((20000, 3), 100.0))
    assert np.all(np.isfinite(d))


def test_reset_reference_temperature():
    p = DriftParams.named("physical_tube")
    pred = p.predictor(1e-3)
    pred.reset(T_ref_C=20.0)
    d = pred.block(np.full(100, 21.0))
    assert d[-1, 2] > 0.0
    pred.reset()
    assert np.all(pred.block(np.full(100, 21.0)) == 0.0)
    assert pred.T_ref_C == 21.0


@pytest.mark.parametrize("name", NAMES)
def test_json_round_trip_gives_identical_prediction(name, tmp_path):
    p = DriftParams.named(name)
    f = tmp_path / "p.json"
    p.save(f)
    q = DriftParams.load(f)
    assert q == p
    assert json.loads(f.read_text())["kind"] == "drift"
    T, U = _signals(300)
    assert np.array_equal(p.predictor(1e-3).block(T, U), q.predictor(1e-3).block(T, U))


def test_table_a1_records_its_doubts():
    p = DriftParams.named("table_a1")
    assert p.output_scale_nm == 1e9
    assert len(p.doubts) >= 5
    assert p.paths.yQx.B[0] > 0  # sign fixed by the controllability matrix A12
    # A12: first columns of [B, A·B] as printed (×1e-6)
    A, B = np.array(p.paths.yQx.A), np.array(p.paths.yQx.B)
    np.testing.assert_allclose((A @ B)[1:] * 1e6, [0.1493, 0.2321], atol=6e-4)


def test_physical_tube_reproduces_the_papers_3_3_nm():
    """2 °C over 10 min → about 3.3 nm lateral drift at the end (nonlinearities paper)."""
    p = DriftParams.named("physical_tube")
    t = np.arange(0, 600.0, 0.01)
    d = p.predictor(0.01).block(20.0 + 2.0 * t / 600.0)
    assert 2.8 < d[-1, 0] < 3.8
    assert 0.5 < d[-1, 1] < d[-1, 0]


def test_scaled_multiplies_the_drift():
    p = DriftParams.named("table_a1")
    T = 20.0 + np.linspace(0, 1, 500)
    U = np.full((500, 3), 50.0)
    np.testing.assert_allclose(p.scaled(1.3).predictor(1e-3).block(T, U), 1.3 * p.predictor(1e-3).block(T, U),
                               rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("bad, field", [
    ({"paths": {"xT": {"form": "tf", "K": 1.0, "poles_s": [-1.0]}}}, "poles_s"),
    ({"paths": {"xT": {"form": "tf", "K": 1.0, "zeros_s": [1.0]}}}, "zeros_s"),
    ({"paths": {"yQx": {"form": "ss", "A": [[1.0, 0.0]], "B": [1.0], "C": [1.0]}}}, "A"),
    ({"output_scale_nm": -1.0}, "output_scale_nm"),
    ({"paths": {"wT": {"form": "tf"}}}, "wT"),
    ({"paths": {"xT": {"form": "tf", "delay_s": -1}}}, "delay_s"),
])
def test_bad_parameters_are_rejected_naming_the_field(bad, field):
    with pytest.raises(ModelError, match=field):
        DriftParams.from_dict({"kind": "drift", **bad})


def test_unknown_named_set():
    with pytest.raises(ModelError, match="physical_tube"):
        DriftParams.named("nope")


def test_bad_step_inputs():
    pred = DriftParams.named("physical_tube").predictor(1e-3)
    with pytest.raises(ModelError, match="T_C"):
        pred.step(float("nan"), np.zeros(3))
    with pytest.raises(ModelError, match="u_V"):
        pred.step(20.0, np.zeros(2))
    with pytest.raises(ModelError, match="T_C"):
        pred.block(np.array([20.0, np.nan]))
    with pytest.raises(ModelError, match="dt_s"):
        DriftParams.named("physical_tube").predictor(0.0)
    with pytest.raises(ValidationError):
        TransferPath(K=1.0, integrators=3)


@pytest.mark.parametrize("T", ["20", None, True, 1e308, -273.15, 250.0, float("inf")])
def test_a_temperature_that_is_no_plausible_number_is_a_model_error(T):
    """A text, a flag or a sensor glitch (1e308 °C) must not reach the predictor: it
    would be taken as a temperature change and the drift would explode."""
    pred = DriftParams.named("physical_tube").predictor(1e-3)
    with pytest.raises(ModelError, match="T_C"):
        pred.step(T, np.zeros(3))
    with pytest.raises(ModelError, match="T_C"):
        pred.block(np.array([20.0, 20.0, T], dtype=object))
    if T is not None:  # reset(None) means: the first sample is the reference
        with pytest.raises(ModelError, match="T_ref_C"):
            pred.reset(T_ref_C=T)
    assert np.all(pred.block(np.full(10, 20.0)) == 0.0)  # still usable afterwards


@pytest.mark.parametrize("name", NAMES)
def test_zoh_equals_scipy_cont2discrete(name):
    from scipy.signal import cont2discrete

    from afmctl.compensators.drift import _continuous_ss, _zoh
    p = DriftParams.named(name)
    for pname in type(p.paths).model_fields:
        path = getattr(p.paths, pname)
        if not isinstance(path, TransferPath) or path.K == 0:
            continue
        A, B, C, D = _continuous_ss(path, 1e-3)
        n = A.shape[0]
        Ad, Bd, _, _ = _zoh(A, B, C, D, 1e-3)
        ref = cont2discrete((A, B.reshape(n, 1), C.reshape(1, n), np.array([[D]])), 1e-3, method="zoh")
        np.testing.assert_allclose(Ad, ref[0], rtol=1e-12, atol=1e-300)
        np.testing.assert_allclose(Bd, ref[1].ravel(), rtol=1e-12, atol=1e-300)


def test_fit_gains_recovers_every_path_gain_noise_free():
    from afmctl.compensators.drift import fit_gains, path_responses
    true = DriftParams.named("physical_tube")
    t = np.arange(0, 3600.0, 1.0)
    T = 20 + 1.5 * np.sin(2 * np.pi * t / 2400) + t / 3600
    U = np.column_stack([75 + 70 * np.sin(2 * np.pi * t / 7.3), 75 + 70 * np.sin(2 * np.pi * t / 11.1),
                         75 + 50 * np.sin(2 * np.pi * t / 300)])
    measured = true.predictor(1.0).block(T, U)
    start = true.scaled(0.5)
    resp = path_responses(start, lambda p: p.predictor(1.0).block(T, U))
    fitted, rms = fit_gains(start, resp, measured)
    for name in ("xT", "yT", "zT", "xQx", "zQx", "yQy", "zQy", "zQz"):
        assert getattr(fitted.paths, name).K == pytest.approx(getattr(true.paths, name).K, rel=1e-8)
    assert np.all(rms < 1e-9)
    # an axis not measured keeps its gains
    m2 = measured.copy()
    m2[:, 1] = np.nan
    fitted2, rms2 = fit_gains(start, resp, m2)
    assert fitted2.paths.yT.K == start.paths.yT.K and np.isnan(rms2[1])
