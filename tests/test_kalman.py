"""Online drift correction with a Kalman filter (compensators.drift_kalman)."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.compensators.base import ModelError
from afmctl.compensators.drift_kalman import DriftKalman, KalmanParams


def test_converges_to_a_constant_bias():
    rng = np.random.default_rng(0)
    kf = DriftKalman(1.0, with_rate=False, q_bias_nm2_per_s=0.0)
    bias = np.array([2.0, -1.0, 5.0])
    for k in range(200):
        model = np.array([0.1 * k, 0.0, -0.05 * k])
        kf.predict(model)
        kf.update(model + bias + rng.normal(0, 0.5, 3), 0.5)
    np.testing.assert_allclose(kf.bias_nm, bias, atol=0.2)
    assert np.all(kf.std_nm < 0.05)
    np.testing.assert_allclose(kf.estimate_nm, kf.model_nm + kf.bias_nm)


def test_tracks_a_growing_bias_with_the_rate_state():
    """Model 30 % too small on a drift growing at 0.01 nm/s: one measurement per 60 s."""
    rng = np.random.default_rng(1)
    kf = DriftKalman(1.0, KalmanParams(q_rate_nm2_per_s3=1e-8))
    errs = []
    for k in range(1, 1201):
        true = np.array([0.01, 0.005, 0.1]) * k
        est = kf.predict(0.7 * true)
        errs.append(np.abs(est - true))
        if k % 60 == 0:
            kf.update(true + rng.normal(0, 0.2, 3), 0.2)
    late = np.array(errs[-300:])
    assert np.all(late < 0.6)                      # within 3σ of the measurement noise
    assert np.all(late[:, 2] < 0.02 * 0.1 * 900)   # < 2 % of the z drift (the model misses 30 %)
    np.testing.assert_allclose(kf.rate_nm_per_s, 0.3 * np.array([0.01, 0.005, 0.1]), atol=0.001)


def test_nan_axis_is_not_updated_and_uncertainty_shrinks():
    kf = DriftKalman(0.1)
    kf.predict(np.zeros(3))
    before = kf.std_nm.copy()
    kf.update(np.array([1.0, np.nan, 2.0]), [0.1, 0.1, 0.1])
    assert kf.bias_nm[1] == 0.0
    assert kf.std_nm[0] < before[0] and kf.std_nm[2] < before[2]
    assert kf.std_nm[1] == before[1]


def test_uncertainty_grows_between_measurements():
    kf = DriftKalman(1.0)
    kf.predict(np.zeros(3))
    kf.update(np.zeros(3), 0.1)
    s0 = kf.std_nm.copy()
    for _ in range(100):
        kf.predict(np.zeros(3))
    assert np.all(kf.std_nm > s0)


def test_one_long_predict_equals_many_short_ones():
    a, b = DriftKalman(0.01), DriftKalman(0.01)
    for kf in (a, b):
        kf.predict(np.zeros(3))
        kf.update(np.array([1.0, 2.0, 3.0]), 0.3)
        kf.predict(np.zeros(3))
        kf.update(np.array([1.5, 2.0, 3.5]), 0.3)
    for _ in range(1000):
        a.predict(np.ones(3))
    b.predict(np.ones(3), dt_s=10.0)
    np.testing.assert_allclose(a.estimate_nm, b.estimate_nm, rtol=1e-9)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-6)


def test_bad_inputs():
    kf = DriftKalman(1e-3)
    with pytest.raises(ModelError, match="model_drift_nm"):
        kf.predict(np.array([np.nan, 0, 0]))
    with pytest.raises(ModelError, match="meas_std_nm"):
        kf.update(np.zeros(3), 0.0)
    with pytest.raises(ModelError, match="measured_drift_nm"):
        kf.update(np.zeros(2), 1.0)
    with pytest.raises(ModelError, match="dt_s"):
        DriftKalman(0.0)
    for bad in ("x", None, True):
        with pytest.raises(ModelError, match="dt_s"):
            DriftKalman(bad)
    with pytest.raises(ModelError, match="model_drift_nm"):
        kf.predict("abc")
    with pytest.raises(ModelError, match="dt_s"):
        kf.predict(np.zeros(3), dt_s="1")
    with pytest.raises(ModelError, match="measured_drift_nm"):
        kf.update([1.0, 2.0, "a"], 1.0)
    with pytest.raises(ModelError, match="meas_std_nm"):
        kf.update(np.zeros(3), "x")
    with pytest.raises(ModelError, match="age_s"):
        kf.update(np.zeros(3), 1.0, age_s=None)
    kf.reset()
    assert np.all(kf.estimate_nm == 0.0)


def test_age_of_a_measurement_uses_the_rate():
    """A measurement of the bias 30 s ago, while the bias grows at 0.01 nm/s: with
    age_s the filter puts today's bias 0.3 nm above the measured value."""
    kf = DriftKalman(1.0, KalmanParams(bias_std0_nm=10.0, rate_std0_nm_per_s=1.0, q_rate_nm2_per_s3=0.0,
                                       q_bias_nm2_per_s=0.0))
    for k in range(1, 11):
        kf.predict(np.zeros(3), dt_s=60.0)
        kf.update(np.full(3, 0.01 * (60.0 * k - 30.0)), 1e-3, age_s=30.0)
    np.testing.assert_allclose(kf.rate_nm_per_s, 0.01, rtol=1e-3)
    np.testing.assert_allclose(kf.bias_nm, 6.0, atol=0.01)
    with pytest.raises(ModelError, match="age_s"):
        kf.update(np.zeros(3), 1.0, age_s=-1.0)


@pytest.mark.parametrize("with_rate", [True, False])
def test_numba_time_update_equals_the_python_reference(with_rate):
    from afmctl.compensators.drift_kalman import _predict_kernel, _predict_loop
    rng = np.random.default_rng(2)
    n = 2 if with_rate else 1
    x0 = rng.normal(size=(3, n))
    A = rng.normal(size=(3, n, n))
    P0 = A @ np.transpose(A, (0, 2, 1))
    m = rng.normal(size=3)
    outs = []
    for fn in (_predict_kernel, _predict_loop):
        x, P, est = x0.copy(), P0.copy(), np.zeros(3)
        for dt in (1e-3, 0.5, 60.0):
            fn(x, P, m, dt, 1e-7, 1e-4, est)
        outs.append((x, P, est))
    for a, b in zip(*outs):
        assert np.array_equal(a, b)
