"""Heat generation in a piezotube, eqs. 4–9 of the drift paper (compensators.heat)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from afmctl.compensators.base import ModelError
from afmctl.compensators.drift import DriftParams, DriftPaths, TransferPath
from afmctl.compensators.heat import AxisHeat, HeatParams, TubeGeometry, heat_coefficients, heat_generation


def test_coefficients_from_geometry_follow_eq9():
    tube = TubeGeometry(length_m=0.04, outer_diameter_m=6.0e-3, wall_m=0.5e-3, e31_C_per_m2=-6.0,
                        d31_m_per_V=-2.0e-10, E_Pa=6.0e10)
    Dt = 6.0e-3 ** 2 - 5.0e-3 ** 2
    s_de, s_ee = heat_coefficients(tube)
    assert s_de == pytest.approx(36.0 * math.pi * Dt * 0.04 / (2 * 0.5e-3 * 6.0e10), rel=1e-12)
    assert s_ee == pytest.approx(math.pi / 32 * 6.0e10 * Dt * 0.04 * (2.0e-10 / 0.5e-3) ** 2, rel=1e-12)
    # order of magnitude of the paper's "3.77e-11 J for 1 V" (its geometry is not given)
    assert 1e-13 < s_de < 1e-10


def test_given_coefficients_override_the_tube():
    h = HeatParams(S_DE_J_per_V2=2e-11, tube=TubeGeometry())
    assert h.s_de == 2e-11
    assert h.s_ee == heat_coefficients(TubeGeometry())[1]
    assert HeatParams().s_de == 0.0 and HeatParams().s_ee == 0.0


def test_eq8_on_a_block():
    dt = 1e-3
    u = np.array([0.0, 1.0, 3.0, 3.0, 2.0])
    hg = heat_generation(u, dt, 2.0, 0.5)
    expected = [0.0,
                2.0 * (1.0 - 0.0) / (2 * dt) - 0.5 * 1.0,
                2.0 * (9.0 - 1.0) / (2 * dt) - 0.5 * 9.0,
                -0.5 * 9.0,
                2.0 * (4.0 - 9.0) / (2 * dt) - 0.5 * 4.0]
    np.testing.assert_allclose(hg, expected, rtol=1e-14)


@settings(max_examples=20, deadline=None)
@given(v0=st.floats(-150, 150), v1=st.floats(-150, 150), k=st.integers(1, 50))
def test_a_voltage_ramp_deposits_the_same_energy_at_any_rate(v0, v1, k):
    """∫S_DE·V·V̇ dt = S_DE·(V1² − V0²)/2 whatever the number of samples of the ramp."""
    dt = 1e-3
    u = np.concatenate([[v0], np.linspace(v0, v1, k + 1)[1:]])
    e = np.sum(heat_generation(u, dt, 1.0, 0.0)) * dt
    assert e == pytest.approx(0.5 * (v1 * v1 - v0 * v0), rel=1e-9, abs=1e-9)


def test_predictor_heat_equals_the_reference():
    """The heat inside the drift kernel is eq. 8 exactly as heat_generation computes it."""
    heat = AxisHeat(x=HeatParams(S_DE_J_per_V2=1e-6, S_EE_W_per_V2=1e-8),
                    y=HeatParams(tube=TubeGeometry()), z=HeatParams(S_DE_J_per_V2=3e-7))
    p = DriftParams(paths=DriftPaths(xQx=TransferPath(K=1.0, poles_s=[1.0])), heat=heat)
    pred = p.predictor(1e-3)
    rng = np.random.default_rng(0)
    U = rng.uniform(0, 150, size=(50, 3))
    s_de, s_ee = heat.coefficients()
    ref = heat_generation(U, 1e-3, s_de, s_ee)
    for i in range(50):
        pred.step(20.0, U[i])
        assert np.array_equal(pred.heat_W, ref[i])


def test_zero_voltage_gives_zero_heat_and_no_heat_drift():
    p = DriftParams.named("physical_tube")
    d = p.predictor(1e-3).block(np.full(1000, 20.0), np.zeros((1000, 3)))
    assert np.all(d == 0.0)


def test_heat_drives_drift_through_the_heat_paths():
    p = DriftParams.named("physical_tube")
    U = np.zeros((5000, 3))
    U[100:, 0] = 150.0
    d = p.predictor(1e-2).block(np.full(5000, 20.0), U)
    assert np.all(d[:101] == 0.0)
    assert d[-1, 0] != 0.0 and d[-1, 2] != 0.0
    assert d[-1, 1] == 0.0  # no y path from Qx in the physical set


def test_bad_inputs():
    with pytest.raises(ValidationError):
        TubeGeometry(outer_diameter_m=1e-3, wall_m=0.6e-3)
    with pytest.raises(ValidationError):
        HeatParams(S_DE_J_per_V2=-1.0)
    with pytest.raises(ModelError, match="dt_s"):
        heat_generation(np.zeros(3), 0.0, 1.0, 1.0)
    with pytest.raises(ModelError, match="u_V"):
        heat_generation(np.array([1.0, np.nan]), 1e-3, 1.0, 1.0)
