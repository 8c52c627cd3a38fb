"""The analytic Jacobian the frequency-response fit hands to least_squares equals central
differences of the model's complex log response, for every structure the fit uses."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from afmctl.compensators.dynamics_identify import log_response_jacobian, model_response

DT = 2e-5
F_HZ = np.geomspace(2.0, 20_000.0, 60)


def random_x(rng: np.random.Generator, n_modes: int, n_lags: int, delay: bool) -> np.ndarray:
    """A parameter vector inside the fit's bounds (``_initial``): log K, log mode Hz, ζ,
    log lag Hz, τ [s]."""
    return np.concatenate([[rng.uniform(-2.0, 3.0)],
                           np.log(rng.uniform(50.0, 15_000.0, n_modes)),
                           rng.uniform(1e-3, 0.9, n_modes),
                           np.log(rng.uniform(10.0, 1e5, n_lags)),
                           [rng.uniform(-2 * DT, 10 * DT) if delay else 0.0]])


def central_differences(x: np.ndarray, n_modes: int, n_lags: int, h: float = 1e-6) -> np.ndarray:
    """``∂ log G/∂x`` by central differences of ``log(G(x ± h e_k)/G(x))`` (small, so no
    branch jump in between)."""
    g0 = model_response(x, F_HZ, n_modes, n_lags)
    cols = []
    for k in range(x.size):
        e = np.zeros_like(x)
        e[k] = h
        up = np.log(model_response(x + e, F_HZ, n_modes, n_lags) / g0)
        down = np.log(model_response(x - e, F_HZ, n_modes, n_lags) / g0)
        cols.append((up - down) / (2 * h))
    return np.stack(cols, axis=1)


@pytest.mark.parametrize("n_modes, n_lags, delay", list(itertools.product((0, 1, 2), (0, 1, 2), (False, True))))
def test_the_analytic_jacobian_equals_central_differences(n_modes, n_lags, delay):
    rng = np.random.default_rng(100 * n_modes + 10 * n_lags + delay)
    for _ in range(5):
        x = random_x(rng, n_modes, n_lags, delay)
        J = log_response_jacobian(x, F_HZ, n_modes, n_lags)
        ref = central_differences(x, n_modes, n_lags)
        assert J.shape == (F_HZ.size, 1 + 2 * n_modes + n_lags + 1)
        # relative to each column's size: a mode's ζ column is ~1/ζ at its peak, ~0 far away
        scale = np.max(np.abs(ref), axis=0)
        assert np.all(np.abs(J - ref) <= 1e-6 * scale + 1e-9), np.max(np.abs(J - ref) / scale)
