"""The approach before a compensated wave table (afmctl/control/approach_history.py): the
creep of the ramp to the first row and the settle hold, which the table's inverse did not
see, taken out; on a scanner that is the model itself the table then lands on the target."""
from __future__ import annotations

import numpy as np

from afmctl.compensators.chain import ChainModel
from afmctl.compensators.creep import LinearCreepModel
from afmctl.compensators.models import save_model
from afmctl.compensators.pi import PIModel
from afmctl.config import Config
from afmctl.control.approach_history import approach_corrected, approach_term_nm, with_approach_taken_out
from afmctl.control.pipeline import axis_models
from afmctl.control.wave_plan import WaveTable

DT_S = 1e-3
CREEP = dict(time_constants_s=[0.05, 0.5, 5.0, 50.0], creep_weights=[0.01, 0.01, 0.01, 0.01], offset_nm=0.0,
             initial_V=0.0)


def _played(model, start_V: float, u_V: np.ndarray, rate_V_per_s: float, settle_s: float) -> np.ndarray:
    """What the model, taken as the scanner, does during ``u_V`` after resting at
    ``start_V``, a ramp to the first row and a hold [nm]."""
    op = model.forward(DT_S)
    op.block(np.full(int(2000.0 / DT_S), start_V))                 # rested there
    step = np.sign(u_V[0] - start_V) * rate_V_per_s * DT_S               # one step a sample, the last one short
    n = int(np.ceil((u_V[0] - start_V) / step))
    op.block(np.append(start_V + step * np.arange(1, n), u_V[0]))
    op.block(np.full(int(round(settle_s / DT_S)), u_V[0]))
    return op.block(np.ascontiguousarray(u_V))


def test_the_approach_term_taken_out_lands_a_creep_scanner_on_the_target():
    """A creep stage (voltage in) as the scanner: the table its inverse computes from rest is
    off by the approach's creep (tens of nm, decaying through the table); with the term
    taken out it lands on the target to rounding (the creep stage is linear)."""
    model = LinearCreepModel(gain_nm_per_V=50.0, **CREEP)
    t = np.arange(0.0, 0.5, DT_S)
    target = 2500.0 + 1000.0 * np.abs(((t * 20.0) % 1.0) * 2.0 - 1.0)      # triangles at 20 Hz
    u = model.inverse(DT_S).block(target)
    term, ago = approach_term_nm(model, DT_S, u, 10.0, 2000.0, 0.5)
    assert ago is None and term[0] > term[-1] > 1.0                          # what the hold let creep on
    before = _played(model, 10.0, u, 2000.0, 0.5) - target
    np.testing.assert_allclose(before, term, atol=1e-6 * np.max(term))      # the term is the error
    corrected, term_again, _ = approach_corrected(model, DT_S, u, 10.0, 2000.0, 0.5)
    after = _played(model, 10.0, corrected, 2000.0, 0.5) - target
    # the approach now ramps to the corrected first row: a creep fraction of the correction
    # less, left after three passes to ~0.04³ of the term
    assert np.max(np.abs(after)) < 1e-3 * np.max(np.abs(before))
    assert 0.9 < np.mean(term_again) / np.mean(term) < 1.0


def test_a_planned_table_is_corrected_per_creep_axis_within_its_limits(tmp_path):
    """Only an axis whose model has a creep stage and that moves is changed; the corrected
    column keeps the limits and the slew limit; the report says what was taken out."""
    pi = PIModel(thresholds=[0.0, 20.0, 40.0], weights=[40.0, 8.0, 4.0])
    save_model(ChainModel(hysteresis=pi, creep=LinearCreepModel(gain_nm_per_V=1.0, **CREEP)), tmp_path / "x.json")
    save_model(pi, tmp_path / "y.json")
    config = Config.model_validate({
        "amplifier": {"driver": "gcs", "output": "wave", "settle_s": 0.5, "slew_V_per_s": 1e4,
                      "port": "socket://127.0.0.1:50000"},
        "loop": {"rate_Hz": 1000.0}, "safety": {"ramp_V_per_s": 2000.0, "slew_V_per_s": 1e4},
        "compensation": {"x": {"model": str(tmp_path / "x.json")}, "y": {"model": str(tmp_path / "y.json")}}})
    n = 400
    u = np.zeros((n, 3))
    u[:, 0] = 60.0 + 40.0 * np.sin(np.linspace(0.0, 4.0 * np.pi, n))
    u[:, 1] = np.linspace(10.0, 30.0, n)
    table = WaveTable(np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), u, np.full(n, 22.0), 0, ["x: inverse"])
    limits = {"x": (0.0, 100.0), "y": (0.0, 100.0)}
    models = [model for model, _source in axis_models(config)[0]]
    out = with_approach_taken_out(table, config, models, [0.0, 0.0, 0.0], limits, 5.0)
    assert out is not table and out.report[0] == "x: inverse" and len(out.report) == 2
    assert out.report[1].startswith("x: the approach's creep (a ramp from 0 V, a 0.5 s hold) adds +")
    assert np.all(out.u_V[:, 0] < u[:, 0]) and np.max(u[:, 0] - out.u_V[:, 0]) > 0.01   # creep ahead: less voltage
    np.testing.assert_array_equal(out.u_V[:, 1:], u[:, 1:])
    assert out.u_V[:, 0].min() >= 0.0 and out.u_V[:, 0].max() <= 100.0
    assert np.max(np.abs(np.diff(out.u_V[:, 0]))) <= 5.0 + 1e-9
    np.testing.assert_array_equal(table.u_V, u)                                   # the table itself unchanged
