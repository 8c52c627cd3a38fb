"""Bouc–Wen (eq. 20): rate independence, block == step, kernel == reference, exact
inverse, identification of synthetic data (its Jacobian from forward sensitivities), and bad input."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmctl.compensators.base import ModelError
from afmctl.compensators._bouc_wen_kernels import bw_sens_nb, bw_sens_py
from afmctl.compensators.bouc_wen import BoucWenModel, ReferenceBoucWen, _BWProblem, reference_forward
from afmctl.compensators.models import model_from_dict

TRUE = dict(d_nm_per_V=100.0, A_nm_per_V=30.0, beta=0.004, gamma=0.0015, n=1.2)


@pytest.fixture(scope="module")
def model() -> BoucWenModel:
    return BoucWenModel(**TRUE)


def _excitation() -> np.ndarray:
    t = np.linspace(0.0, 6.0, 3000)
    return np.r_[np.linspace(0.0, 75.0, 200), 75.0 + 75.0 * np.exp(-t / 4.0) * np.sin(2 * np.pi * t)]


signals = st.lists(st.floats(-50.0, 200.0, allow_nan=False), min_size=1, max_size=60).map(np.array)


@settings(max_examples=40, deadline=None)
@given(u=signals, cut=st.integers(0, 60))
def test_block_step_and_reference_agree(model, u, cut):
    y = model.forward().block(u)
    f = model.forward()
    assert np.array_equal(y, np.array([f.step(x) for x in u]))
    f.reset()
    assert np.array_equal(y, np.r_[f.block(u[:cut]), f.block(u[cut:])])
    assert np.array_equal(y, reference_forward(model, u))  # same arithmetic, bit for bit
    inv = model.inverse()
    ub = inv.block(y)
    inv.reset()
    assert np.array_equal(ub, np.array([inv.step(x) for x in y]))
    assert np.array_equal(ub, ReferenceBoucWen(model).inverse(y))  # numba == plain Python, bit for bit


def test_rate_independent_and_stable_at_any_step(model):
    """Same turning points sampled coarsely or finely give the same outputs there."""
    ext = np.array([0.0, 150.0, 20.0, 120.0, 60.0])
    fine = np.concatenate([np.linspace(a, b, 2001)[1:] for a, b in zip(ext[:-1], ext[1:])])
    y_c = model.forward().block(ext[1:])
    y_f = model.forward().block(fine)[1999::2000]
    assert np.allclose(y_c, y_f, rtol=0, atol=1e-5 * np.ptp(y_c))  # integration error only
    # the hysteretic state stays bounded by its saturation even for huge steps
    f = model.forward()
    f.block(np.array([1e5, -1e5, 1e5]))
    assert abs(f.h_nm) <= model.h_max_nm() * (1 + 1e-6)


def test_loop_is_hysteretic(model):
    up = np.linspace(0.0, 150.0, 301)
    y = model.forward().block(np.r_[up, up[::-1][1:]])
    asc, desc = y[:301], y[300:][::-1]
    assert np.max(desc - asc) > 0.02 * np.ptp(y)  # descending branch above ascending


def test_inverse_is_exact(model):
    t = np.arange(4000) * 5e-4
    target = 1500.0 + 12000.0 * (1 - np.abs((t % 1.0) * 2 - 1))
    u = model.inverse().block(target)
    assert np.max(np.abs(model.forward().block(u) - target)) < 1e-9 * np.ptp(target)


def test_identification_recovers_parameters_and_inverse_compensates(model):
    u = _excitation()
    y = model.forward().block(u)
    fit = BoucWenModel.identify(np.arange(u.size) * 1e-3, u, y)
    for name, value in TRUE.items():
        assert getattr(fit, name) == pytest.approx(value, rel=0.02), name
    assert fit.fit_residual_nm < 1e-3 * np.ptp(y)
    # the identified inverse brings the true plant within 0.5 % max error
    t = np.arange(3000) * 1e-3
    target = np.ptp(y) * (0.1 + 0.8 * (1 - np.abs((t % 1.0) * 2 - 1)))
    inv = fit.inverse()
    fit_u0 = inv.block(target)
    e = model.forward().block(fit_u0) - target
    assert np.max(np.abs(e)) <= 0.005 * np.ptp(target)


def test_identification_with_noise_and_fixed_n(model):
    u = _excitation()
    y = model.forward().block(u) + np.random.default_rng(0).normal(0, 5.0, u.size)
    fit = BoucWenModel.identify(None, u, y, n=1.2)
    assert fit.n == pytest.approx(1.2)
    assert fit.d_nm_per_V == pytest.approx(100.0, rel=0.02)
    assert fit.A_nm_per_V == pytest.approx(30.0, rel=0.1)


@pytest.mark.parametrize("patch, needle", [
    ({"A_nm_per_V": -1.0}, "A_nm_per_V"),
    ({"beta": -0.01, "gamma": 0.0}, "beta"),
    ({"gamma": 0.01}, "beta − gamma"),
    ({"n": 0.5}, "n"),
    ({"d_nm_per_V": 0.0}, "d_nm_per_V"),
])
def test_bad_model_files_name_the_field(model, patch, needle):
    data = model.model_dump(mode="json")
    data.update(patch)
    with pytest.raises(ModelError, match=needle):
        model_from_dict(data)


def test_non_invertible_model_and_bad_data(model):
    weak = BoucWenModel(d_nm_per_V=10.0, A_nm_per_V=30.0, beta=0.004, gamma=0.0015, n=1.2)
    with pytest.raises(ModelError, match="d_nm_per_V"):
        weak.inverse()
    with pytest.raises(ModelError, match="u_V"):
        model.forward().block(np.array([np.inf]))
    with pytest.raises(ModelError, match="y_nm"):
        BoucWenModel.identify(None, np.arange(30.0), np.arange(29.0))
    with pytest.raises(ModelError, match="n"):
        BoucWenModel.identify(None, np.arange(30.0), np.arange(30.0), n=0.2)
    assert "Bouc" in model.summary()


@settings(max_examples=30, deadline=None)
@given(y=st.lists(st.floats(-2000.0, 16000.0, allow_nan=False), min_size=1, max_size=50).map(np.array))
def test_forward_of_inverse_is_identity_on_random_targets(model, y):
    u = model.inverse().block(y)
    assert np.max(np.abs(model.forward().block(u) - y)) <= 1e-9 * 16000.0


# ------------------------------------------------------------------ the fit's sensitivities
def _sens(kernel, model, u, rows, want_n=True, du_sub=None, **patch):
    p = dict(A=model.A_nm_per_V, beta=model.beta, gamma=model.gamma, n=model.n)
    p.update(patch)
    h, s = np.empty(rows.size), np.empty((rows.size, 4))
    kernel(u, np.zeros(0), 0.0, 0.0, float(u[0]), p["A"], p["beta"], p["gamma"], p["n"], du_sub or model.du_sub_V(),
           1000000, rows, want_n, h, s)
    return h, s


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sensitivity_kernel_equals_reference_forward_and_differences(model, seed):
    """numba == plain Python (1e-12 relative); its h is the forward operator's bit for bit;
    dh/d(A, β, γ, n) equal central differences of h (the sub-step held fixed)."""
    rng = np.random.default_rng(seed)
    u = np.r_[0.0, np.cumsum(rng.normal(0.0, 6.0, 400))]
    rows = np.unique(rng.integers(0, u.size, 120))
    h, s = _sens(bw_sens_nb, model, u, rows)
    h_py, s_py = _sens(bw_sens_py, model, u, rows)
    assert np.allclose(h, h_py, rtol=1e-12, atol=0) and np.allclose(s, s_py, rtol=1e-12, atol=1e-300)
    y = model.model_copy(update={"u0_V": float(u[0])}).forward().block(u)
    assert np.array_equal(model.d_nm_per_V * u[rows] - h + model.offset_nm, y[rows])
    for i, name in enumerate(("A", "beta", "gamma", "n")):
        e = 1e-6 * getattr(model, {"A": "A_nm_per_V"}.get(name, name))
        hp, _ = _sens(bw_sens_nb, model, u, rows, du_sub=model.du_sub_V(), **{name: _p(model, name) + e})
        hm, _ = _sens(bw_sens_nb, model, u, rows, du_sub=model.du_sub_V(), **{name: _p(model, name) - e})
        fd = (hp - hm) / (2 * e)
        assert np.max(np.abs(fd - s[:, i])) <= 1e-6 * np.max(np.abs(s[:, i])), name
    _, s_no_n = _sens(bw_sens_nb, model, u, rows, want_n=False)
    assert np.array_equal(s_no_n[:, :3], s[:, :3]) and not s_no_n[:, 3].any()


def _p(model, name):
    return model.A_nm_per_V if name == "A" else getattr(model, name)


@pytest.mark.parametrize("nfix", [None, 1.2])
def test_fit_jacobian_equals_differences_of_residuals(model, nfix):
    """The least-squares Jacobian (chain rule from the sensitivities) equals central differences
    of the residuals, on an input whose moves take one sub-step each (no sub-step count changes)."""
    u = 60.0 + 50.0 * np.sin(np.linspace(0.0, 9.0, 2000)) * np.linspace(1.0, 0.3, 2000)
    assert np.max(np.abs(np.diff(u))) < 0.5 * model.du_sub_V()
    y = model.forward().block(u) + np.random.default_rng(3).normal(0.0, 20.0, u.size)
    sel = np.arange(100, u.size, 7)
    prob = _BWProblem(u, y, sel, float(u[0]), float(np.sum(np.abs(np.diff(u)))), float(np.ptp(y)), nfix)
    x = np.array([np.log(90.0), np.log(0.25), np.log(0.08 * np.ptp(y)), 0.2] + ([] if nfix else [1.4]) + [0.01])
    r = prob.resid(x)
    J = prob.jac(x).copy()
    ref = _BWProblem(u, y, sel, float(u[0]), float(np.sum(np.abs(np.diff(u)))), float(np.ptp(y)), nfix, False)
    assert np.array_equal(r, ref.resid(x))  # the same residuals as the forward operator's
    for i in range(x.size):
        e = np.zeros(x.size)
        e[i] = 1e-6
        fd = (prob.resid(x + e) - prob.resid(x - e)) / 2e-6
        assert np.max(np.abs(fd - J[:, i])) <= 1e-6 * np.max(np.abs(J[:, i])) + 1e-12, i


def test_sensitivity_and_two_point_fits_agree(model):
    u = _excitation()
    y = model.forward().block(u) + np.random.default_rng(0).normal(0, 5.0, u.size)
    a = BoucWenModel.identify(None, u, y)
    b = BoucWenModel.identify(None, u, y, jacobian="2-point")
    for name in ("d_nm_per_V", "A_nm_per_V", "beta", "gamma", "n", "offset_nm", "fit_residual_nm"):
        assert getattr(a, name) == pytest.approx(getattr(b, name), rel=1e-6, abs=1e-6), name  # to the fit's precision
    with pytest.raises(ModelError, match="jacobian"):
        BoucWenModel.identify(None, u, y, jacobian="3-point")
