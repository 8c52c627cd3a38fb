"""Temperature inputs of the drift predictor (compensators.temperature)."""
from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from afmctl.compensators.base import ModelError
from afmctl.compensators.drift import DriftParams
from afmctl.compensators.temperature import TemperatureProfile, check_temperature_series, resample_uniform


def test_profiles():
    t = np.array([0.0, 100.0, 400.0, 700.0, 1000.0])
    ramp = TemperatureProfile(shape="ramp", T0_C=22.0, delta_K=2.0, t_start_s=100.0, duration_s=600.0)
    np.testing.assert_allclose(ramp.at(t), [22.0, 22.0, 23.0, 24.0, 24.0])
    step = TemperatureProfile(shape="step", T0_C=20.0, delta_K=-1.0, t_start_s=400.0)
    np.testing.assert_allclose(step.at(t), [20.0, 20.0, 19.0, 19.0, 19.0])
    sine = TemperatureProfile(shape="sine", T0_C=20.0, delta_K=0.5, period_s=1200.0, t_start_s=100.0)
    np.testing.assert_allclose(sine.at(t), [20.0, 20.0, 20.5, 20.0, 19.5], atol=1e-12)
    assert np.all(TemperatureProfile(T0_C=21.0).at(t) == 21.0)


def test_profile_validation_and_json():
    with pytest.raises(ValidationError):
        TemperatureProfile(shape="zigzag")
    with pytest.raises(ValidationError):
        TemperatureProfile(duration_s=0.0)
    p = TemperatureProfile(shape="ramp", delta_K=2.0)
    assert TemperatureProfile.model_validate_json(p.model_dump_json()) == p
    # a profile must stay within the temperatures the predictor accepts (-50..150 °C)
    for shape, T0, d in (("ramp", 150.0, 90.0), ("step", -50.0, -60.0), ("sine", -50.0, 60.0)):
        with pytest.raises(ValidationError, match="delta_K"):
            TemperatureProfile(shape=shape, T0_C=T0, delta_K=d)
    TemperatureProfile(shape="ramp", T0_C=150.0, delta_K=-90.0)  # going down is fine


def test_profile_drives_the_predictor():
    prof = TemperatureProfile(shape="step", T0_C=20.0, delta_K=1.0, t_start_s=1.0)
    t = np.arange(0, 2000) * 0.01
    d = DriftParams.named("physical_tube").predictor(0.01).block(prof.at(t))
    assert np.all(d[:101] == 0.0) and np.all(d[102:, 2] > 0.0)


@pytest.mark.parametrize("t, T, needle", [
    ([0.0, 1.0, np.nan], [20.0, 20.0, 20.0], "column t: row 3"),
    ([0.0, 1.0, 2.0], [20.0, np.inf, 20.0], "column T: row 2"),
    ([0.0, 2.0, 1.0], [20.0, 20.0, 20.0], "strictly increasing; row 3"),
    ([0.0, 1.0, 1.0], [20.0, 20.0, 20.0], "strictly increasing"),
    ([0.0, 1.0], [20.0, 500.0], "-50..150"),
    ([0.0, 1.0, 100.0], [20.0, 20.0, 20.0], "gap of 99 s"),
    ([], [], "no samples"),
])
def test_series_validation(t, T, needle):
    with pytest.raises(ModelError, match=needle.replace("(", r"\(").replace(".", r"\.")):
        check_temperature_series(np.array(t), np.array(T), max_gap_s=10.0)


def test_resample_uniform():
    t = np.array([0.0, 1.0, 4.0])
    grid, v = resample_uniform(t, np.array([0.0, 1.0, 4.0]), 0.5)
    np.testing.assert_allclose(grid, np.arange(0, 4.01, 0.5))
    np.testing.assert_allclose(v, grid)
    grid, v2 = resample_uniform(t, np.column_stack([t, -t]), 1.0)
    assert v2.shape == (5, 2)
    with pytest.raises(ModelError, match="at most"):
        resample_uniform(t, t, 1e-9, max_samples=1000)
