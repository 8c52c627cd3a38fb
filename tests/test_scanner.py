"""The simulated 3-axis scanner: configuration, block vs streaming, determinism, limits,
drift, coupling, external models."""
from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from afmctl.compensators.base import ModelError
from afmctl.sim_backend.scanner import (DriftConfig, ExternalModelConfig, Scanner, ScannerConfig, default_scanner_config,
                                 linear_scanner_config)


def triangle(n: int, lo: float = 0.0, hi: float = 150.0) -> np.ndarray:
    return np.concatenate([np.linspace(lo, hi, n // 2), np.linspace(hi, lo, n - n // 2)])


def raster_volts(n: int = 4000) -> np.ndarray:
    u = np.zeros((n, 3))
    u[:, 0] = np.tile(triangle(400, 0, 120), n // 400)
    u[:, 1] = np.linspace(10, 90, n)
    u[:, 2] = 40 + 5 * np.sin(np.arange(n) / 30)
    return u


def test_default_config_roundtrips_and_forbids_unknown_fields():
    cfg = default_scanner_config()
    again = ScannerConfig.model_validate_json(cfg.model_dump_json())
    assert again == cfg
    data = cfg.model_dump()
    data["x"]["amplifier"]["voltage_max"] = 3
    with pytest.raises(ValidationError, match="voltage_max"):
        ScannerConfig.model_validate(data)
    data = cfg.model_dump()
    data["x"]["amplifier"]["u_max_V"] = -1.0
    with pytest.raises(ValidationError, match="u_max_V"):
        ScannerConfig.model_validate(data)
    assert cfg.x.hysteresis.kind == "gaussian-preisach" and cfg.x.hysteresis.components


def test_block_run_equals_pieces_and_streaming():
    u = raster_volts()
    a = Scanner()
    whole = a.run(u, 1e-4)
    a.reset()
    parts = np.vstack([a.run(u[:1234], 1e-4), a.run(u[1234:], 1e-4)])
    np.testing.assert_array_equal(whole, parts)
    # streaming with the config's dt: apply() each sample, advance() to its end
    cfg = default_scanner_config()
    cfg.dt_s = 1e-4
    s = Scanner(cfg)
    got = []
    for k in range(300):
        s.apply({"x": u[k, 0], "y": u[k, 1], "z": u[k, 2]})
        s.advance((k + 1) * 1e-4)
        got.append(s.position_nm())
    # bit-exact: coupling is composed in a fixed order of operations, not by a BLAS matmul
    np.testing.assert_array_equal(np.array(got), whole[:300])
    assert s.time_s == pytest.approx(300 * 1e-4)


def test_apply_with_time_advances_with_old_voltage_first():
    cfg = default_scanner_config()
    cfg.dt_s = 1e-3
    s = Scanner(cfg)
    s.apply({"x": 50.0}, t_s=0.0)
    s.apply({"x": 0.0}, t_s=0.5)  # 0.5 s at 50 V, then 0 V held
    assert s.time_s == pytest.approx(0.5)
    assert s.position_nm()[0] > 2000
    s.advance(1.0)
    assert s.position_nm()[0] < 500
    s.advance(0.2)  # the past: ignored
    assert s.time_s == pytest.approx(1.0)


def test_deterministic_for_a_seed():
    u = raster_volts(1200)
    readings = []
    for seed in (3, 3, 4):
        cfg = default_scanner_config()
        cfg.seed = seed
        s = Scanner(cfg)
        s.run(u, 1e-4)
        readings.append(s.read_sensor_nm())
    np.testing.assert_array_equal(readings[0], readings[1])
    assert not np.array_equal(readings[0], readings[2])


def test_voltage_limits_and_slew_hold_for_any_command():
    s = Scanner()
    rng = np.random.default_rng(0)
    u = rng.uniform(-500, 500, (5000, 3))
    _, v = s.run(u, 1e-5, return_voltage=True)
    assert v.min() >= 0.0 and v.max() <= 150.0
    # slew 1e4 V/s at 10 µs → ≤ 0.1 V per sample before the (smoothing) low-pass
    assert np.max(np.abs(np.diff(v, axis=0))) <= 0.1 + 1e-9


@pytest.mark.parametrize("bad, match", [
    (np.zeros((10, 2)), "shape"),
    (np.full((3, 3), np.nan), "non-finite"),
])
def test_bad_input_is_a_model_error(bad, match):
    with pytest.raises(ModelError, match=match):
        Scanner().run(bad, 1e-4)


def test_bad_streaming_input_names_the_field():
    s = Scanner()
    with pytest.raises(ModelError, match="axis"):
        s.apply({"w": 1.0})
    with pytest.raises(ModelError, match="volts.x"):
        s.apply({"x": float("inf")})
    with pytest.raises(ModelError, match="T_C"):
        s.set_ambient_temperature(float("nan"))


def test_cross_coupling_moves_x_with_y():
    cfg = linear_scanner_config(coupling=[[1.0, 0.01, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    s = Scanner(cfg)
    u = np.zeros((10, 3))
    u[:, 1] = 100.0
    p = s.run(u, 1e-4)
    assert p[-1, 1] == pytest.approx(8000.0)
    assert p[-1, 0] == pytest.approx(80.0)


@pytest.mark.parametrize("kind", ["params", "expansion"])
def test_temperature_ramp_gives_growing_drift(kind):
    cfg = linear_scanner_config(drift=DriftConfig(kind=kind))
    s = Scanner(cfg)
    n = 600
    T = 22.0 + np.linspace(0, 2, n)  # 2 °C over 10 min
    p = s.run(np.zeros((n, 3)), 1.0, T_C=T)
    lateral = np.hypot(p[:, 0], p[:, 1])
    assert 1.0 < lateral[-1] < 10.0  # a few nm (nonlinearities paper: ≈ 3.3 nm)
    assert np.all(np.diff(lateral[10:]) >= -1e-9)
    assert s.ambient_T_C == pytest.approx(24.0)


def test_external_model_as_hysteresis():
    """Any compensators model file works as the plant's hysteresis (via forward())."""
    import afmctl.compensators.preisach as pre
    model = pre.PreisachModel.from_density(lambda a, b: np.exp(-((a - 80) ** 2 + (b - 40) ** 2) / 800.0),
                                           u_min_V=0.0, u_max_V=150.0, levels=10)
    cfg = linear_scanner_config()
    cfg.x.hysteresis = ExternalModelConfig(model=model.model_dump(mode="json"))
    s = Scanner(cfg)
    u = np.zeros((200, 3))
    u[:, 0] = triangle(200)
    p = s.run(u, 1e-3)
    np.testing.assert_allclose(p[:, 0], model.forward().block(u[:, 0]), rtol=0, atol=1e-9)
    assert s.nominal_gain_nm_per_V()[0] > 0


def test_bad_external_model_is_reported_with_its_field():
    cfg = linear_scanner_config()
    cfg.x.hysteresis = ExternalModelConfig(model={"kind": "nope"})
    with pytest.raises(ModelError, match="kind"):
        Scanner(cfg)


def test_bad_drift_parameters_name_the_field():
    with pytest.raises(ModelError, match="unknown drift parameter set"):
        Scanner(linear_scanner_config(drift=DriftConfig(kind="params", named="nope")))
    with pytest.raises(ModelError, match="drift.params"):
        Scanner(linear_scanner_config(drift=DriftConfig(kind="params", params={"kind": "drift", "bogus": 1})))


def test_reset_restores_the_state_bit_exactly():
    """reset() after runs, temperature changes and held voltages gives exactly what a new
    scanner gives: positions, piezo voltages, drift and the seeded sensor noise."""
    u = raster_volts(1200)
    T = 22.0 + np.linspace(0, 3, 1200)
    fresh = Scanner()
    first = fresh.run(u, 1e-4, T_C=T)
    reading = fresh.read_sensor_nm()
    s = Scanner()
    s.run(u[::-1], 1e-4)
    s.set_ambient_temperature(40.0)
    s.apply({"x": 100.0}, t_s=s.time_s + 0.01)
    s.reset()
    assert s.time_s == 0.0 and s.ambient_T_C == 22.0
    np.testing.assert_array_equal(s.run(u, 1e-4, T_C=T), first)
    np.testing.assert_array_equal(s.read_sensor_nm(), reading)


def test_rest_gives_a_fresh_scanners_motion_while_time_goes_on():
    """rest() after a raster: the same voltages then move the tip exactly as on a new
    scanner (hysteresis, creep, vibration and drift as at start); the clock does not go back."""
    u = raster_volts(1200)
    fresh = Scanner().run(u, 1e-4)
    s = Scanner()
    played = s.run(u, 1e-4)
    again = s.run(u, 1e-4)
    assert np.max(np.abs(again - fresh)) > 1.0          # without rest the history shows
    t = s.time_s
    s.rest()
    assert s.time_s == t
    np.testing.assert_array_equal(s.held_voltage_V(), s.rest_voltage_V())
    np.testing.assert_allclose(s.run(u, 1e-4), fresh, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(played, fresh)


def test_reference_path_equals_numba_path():
    """The whole scanner with the plain-Python kernels (fast=False) equals the numba one."""
    u = raster_volts(400)
    np.testing.assert_array_equal(Scanner(fast=False).run(u, 1e-4), Scanner().run(u, 1e-4))


def test_long_gap_is_advanced_in_bounded_chunks_with_the_same_result(monkeypatch):
    """A long idle gap is simulated in chunks of at most ADVANCE_CHUNK samples (so one
    apply() never does one huge block while holding the GIL), bit-identical to one run."""
    cfg = default_scanner_config()
    ref = Scanner(cfg)
    ref.run(np.array([[30.0, 40.0, 50.0]]), cfg.dt_s)
    expected = ref.run(np.broadcast_to([80.0, 20.0, 60.0], (5000, 3)), cfg.dt_s)[-1]
    s = Scanner(cfg)
    monkeypatch.setattr(Scanner, "ADVANCE_CHUNK", 700)
    sizes = []
    run = s.run
    monkeypatch.setattr(s, "run", lambda u, dt=None, **kw: (sizes.append(len(u)), run(u, dt, **kw))[1])
    s.apply({"x": 30.0, "y": 40.0, "z": 50.0})
    s.advance(cfg.dt_s)
    s.apply({"x": 80.0, "y": 20.0, "z": 60.0})
    s.apply({"x": 0.0}, t_s=5001 * cfg.dt_s)  # advances 5000 samples with the old voltages
    assert max(sizes) <= 700 and sum(sizes) == 5001
    np.testing.assert_array_equal(s.position_nm(), expected)


def test_kernels_and_drift_predictor_are_ready_before_the_first_apply():
    """Loading the numba cache / building the drift predictor holds the GIL for tens of
    ms; it happens in the constructor, not in the first apply() on an amplifier thread."""
    from afmctl.sim_backend import _plant_kernels as K

    s = Scanner()
    assert s._drift._predictor is not None
    for kernel in (K.amplifier_nb, K.preisach_nb, K.creep_dynamics_nb):
        assert kernel.signatures, kernel


@pytest.mark.parametrize("field, value, match", [
    (("seed",), -1, "seed"),
    (("x", "amplifier", "u_min_V"), float("nan"), "finite"),
    (("x", "hysteresis", "components", 0, "alpha_V"), float("nan"), "alpha_V"),
    (("x", "hysteresis", "linear_nm_per_V"), float("inf"), "linear_nm_per_V"),
    (("drift", "expansion_nm_per_K"), [float("nan"), 0.0, 0.0], "expansion_nm_per_K"),
    (("noise", "position_std_nm"), float("inf"), "position_std_nm"),
    (("coupling",), [[1.0, float("inf"), 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "coupling"),
])
def test_bad_config_value_names_the_field(field, value, match):
    data = default_scanner_config().model_dump()
    target = data
    for key in field[:-1]:
        target = target[key]
    target[field[-1]] = value
    with pytest.raises(ValidationError, match=match):
        ScannerConfig.model_validate(data)


def test_bad_time_or_voltage_type_in_streaming_is_a_model_error():
    s = Scanner()
    with pytest.raises(ModelError, match="t_s"):
        s.advance(float("nan"))
    with pytest.raises(ModelError, match="t_s"):
        s.apply({"x": 1.0}, t_s=float("inf"))
    with pytest.raises(ModelError, match="volts.y"):
        s.apply({"y": "ten"})
    assert s.time_s == 0.0
