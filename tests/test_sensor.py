"""The simulated scanner's position sensor (sim_backend/sensor.py): noise, resolution,
bandwidth and delay per axis, seeded, read through captures, and leaving every other
output of the scanner as it was."""
from __future__ import annotations

import math

import numpy as np
import pytest

from afmctl.sim_backend.config import SensorConfig
from afmctl.sim_backend.scanner import Scanner, default_scanner_config, linear_scanner_config


def _scanner(**sensor) -> Scanner:
    cfg = linear_scanner_config()
    s = SensorConfig(**sensor)
    for a in "xyz":
        cfg.axis(a).sensor = s
    return Scanner(cfg)


def _step_capture(scanner: Scanner, n: int = 400, volts: float = 50.0):
    cap = scanner.capture_sensor(0.0, scanner.config.dt_s, n)
    u = np.zeros((n, 3))
    u[:, 0] = volts
    pos = scanner.run(u)
    assert cap.done
    return cap, pos


def test_defaults_are_small_and_realistic():
    s = default_scanner_config().x.sensor
    assert (s.noise_nm, s.resolution_nm, s.bandwidth_Hz, s.delay_s) == (0.2, 0.1, 1.0e4, 0.0)


def test_noise_rms_and_resolution():
    cap, pos = _step_capture(_scanner(noise_nm=0.5, resolution_nm=0.25, bandwidth_Hz=None), n=20000, volts=10.0)
    err = cap.y_nm[1:, 0] - pos[:-1, 0]       # reading k: the position after k samples
    assert np.std(err) == pytest.approx(math.sqrt(0.5 ** 2 + 0.25 ** 2 / 12), rel=0.05)
    assert np.allclose(cap.y_nm / 0.25, np.round(cap.y_nm / 0.25), atol=1e-9)    # on the 0.25 nm grid


def test_bandwidth_is_a_first_order_lag_and_delay_whole_samples():
    cap, pos = _step_capture(_scanner(noise_nm=0.0, resolution_nm=0.0, bandwidth_Hz=2000.0))
    final = pos[-1, 0]
    tau_s = 1 / (2 * math.pi * 2000.0)
    k = int(round(tau_s / 1e-5))                    # one time constant: 1 - 1/e of the step
    assert cap.y_nm[k, 0] / final == pytest.approx(1 - math.exp(-k * 1e-5 / tau_s), rel=1e-9)
    late, _ = _step_capture(_scanner(noise_nm=0.0, resolution_nm=0.0, bandwidth_Hz=2000.0, delay_s=5e-5))
    np.testing.assert_allclose(late.y_nm[5:, 0], cap.y_nm[:-5, 0], rtol=0, atol=1e-9)
    assert np.all(late.y_nm[:5, 0] == 0.0)          # settled at the old position until then


def test_deterministic_for_a_seed_and_does_not_change_the_true_tip():
    a, pos_a = _step_capture(Scanner(default_scanner_config()))
    b, pos_b = _step_capture(Scanner(default_scanner_config()))
    np.testing.assert_array_equal(a.y_nm, b.y_nm)
    plain = Scanner(default_scanner_config())
    u = np.zeros((400, 3))
    u[:, 0] = 50.0
    np.testing.assert_array_equal(plain.run(u), pos_a)          # the capture changed nothing true
    other = default_scanner_config().model_copy(update={"seed": 7})
    c, _ = _step_capture(Scanner(other))
    assert not np.array_equal(a.y_nm, c.y_nm)


def test_capture_times_between_samples_hold_the_last_reading_and_past_times_the_present():
    s = _scanner(noise_nm=0.0, resolution_nm=0.0, bandwidth_Hz=None)
    s.run(np.full((10, 3), 20.0))                     # t = 100 us, x at 1600 nm
    cap = s.capture_sensor(50e-6, 25e-6, 6)          # 50, 75 us are past; 100 us is now
    assert cap.count == 3 and np.all(cap.y_nm[:3, 0] == pytest.approx(1600.0))
    u = np.zeros((10, 3))
    u[:, 0] = 20.0 + np.arange(1, 11)                 # sample i ends at 100 + 10 (i + 1) us
    pos = s.run(u)
    assert cap.done
    assert cap.y_nm[3, 0] == pytest.approx(pos[1, 0])   # 125 us: the sample that ended at 120 us
    assert cap.y_nm[4, 0] == pytest.approx(pos[4, 0])   # 150 us: exactly a sample's end


def test_bad_sensor_config_is_refused_naming_the_field():
    from pydantic import ValidationError
    with pytest.raises(ValidationError, match="noise_nm"):
        SensorConfig(noise_nm=-1.0)
    with pytest.raises(ValidationError, match="delay_s"):
        SensorConfig(delay_s=float("nan"))
