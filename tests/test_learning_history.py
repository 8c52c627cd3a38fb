"""The history term of a play (compensators/learning_history.py, control/learn_history.py):
what the creep of earlier voltages adds to a recording, relative to a play from rest."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.compensators.chain import ChainModel
from afmctl.compensators.creep import LinearCreepModel
from afmctl.compensators.learning_history import VoltageHistory, creep_stages, history_term_nm
from afmctl.compensators.pi import PIModel
from afmctl.config import Config
from afmctl.control.learn_history import PlayTimeline

DT_S = 1e-3
TAU_S = [0.05, 0.5, 5.0, 50.0]
WEIGHTS = [0.01, 0.01, 0.01, 0.01]


def creep_model(gain: float = 50.0) -> LinearCreepModel:
    return LinearCreepModel(time_constants_s=TAU_S, creep_weights=WEIGHTS, gain_nm_per_V=gain, offset_nm=0.0,
                            initial_V=0.0)


def test_the_term_is_the_lag_states_difference_decaying_through_the_table():
    """For the linear creep stage the term is exact and closed-form: Δy[n] = g·Σ_k c_k·Δz_k·a_k^(n+1)
    (nonlinearities paper, eq. 21), whatever the table."""
    model = creep_model()
    rest = VoltageHistory(model, DT_S, 0.0, settle_s=1000.0)
    played = rest.copy()
    played.hold(0.0)
    played.ramp_over(80.0, 0.01)
    played.hold(2.0)
    played.ramp(0.0, 1e4)
    played.hold(0.7)
    table = 40.0 + 30.0 * np.sin(np.linspace(0.0, 6.0 * np.pi, 400))
    term = history_term_nm(played, rest, table)
    # the same from the lag states by hand (z: the lags' states, in the input's unit [V])
    a = np.exp(-DT_S / np.array(TAU_S))
    dz = played.creep.z - rest.creep.z
    n = np.arange(table.size)[:, None]
    expected = 50.0 * np.sum(np.array(WEIGHTS) * dz * a ** (n + 1), axis=1)
    assert np.max(np.abs(term)) > 1.0                     # the history left something to see
    np.testing.assert_allclose(term, expected, rtol=1e-9, atol=1e-9)


def test_a_history_like_the_reference_adds_nothing_and_a_rest_lets_it_decay():
    model = ChainModel(hysteresis=PIModel(thresholds=[0.0, 20.0, 40.0], weights=[40.0, 8.0, 4.0]),
                       creep=creep_model(gain=1.0))
    table = np.linspace(30.0, 70.0, 300)
    rest = VoltageHistory(model, DT_S, 0.0, settle_s=500.0, peak_V=70.0)
    same = rest.copy()
    assert np.max(np.abs(history_term_nm(same, rest, table))) == 0.0
    after_play = rest.copy()
    after_play.ramp_over(70.0, 0.02)
    after_play.hold(3.0)
    after_play.ramp(0.0, 5000.0)
    terms = []
    for rest_s in (0.2, 2.0, 20.0):
        h = after_play.copy()
        h.hold(rest_s)
        terms.append(float(np.mean(history_term_nm(h, rest, table))))
    assert terms[0] > terms[1] > terms[2] > 0.0, terms     # creep charged, then relaxing at rest
    assert terms[2] < 0.5 * terms[0], terms


def test_models_without_a_creep_stage_predict_no_term():
    pi = PIModel(thresholds=[0.0, 20.0], weights=[40.0, 8.0])
    assert creep_stages(pi) is None
    assert creep_stages(ChainModel(hysteresis=pi)) is None
    assert creep_stages(creep_model())[0] is None
    with pytest.raises(ValueError, match="no creep stage"):
        VoltageHistory(pi, DT_S, 0.0)


def test_the_timeline_of_a_learn_run_against_a_play_from_rest():
    """Two plays of one table from the host clock readings a learn run keeps; the first, from
    rest with the nominal approach and settle, has no term; the second carries the first's
    creep; a long rest before a third lets most of it decay."""
    config = Config.model_validate({"amplifier": {"driver": "gcs", "output": "wave", "settle_s": 0.2, "slew_V_per_s": 1e5,
                                                  "port": "/dev/null"},
                                    "loop": {"rate_Hz": 1000.0},
                                    "safety": {"ramp_V_per_s": 5000.0, "slew_V_per_s": 1e5}})
    timeline = PlayTimeline(config, {"x": creep_model(gain=1.0)}, {"x": 0.0}, {"x": 70.0})
    table = {"x": np.linspace(60.0, 70.0, 500)}
    t0 = timeline.t_last_s + 1.0
    ramp_s = 60.0 / 5000.0

    def play(t: float) -> float:
        times = {"approach": t, "settle": t + ramp_s, "start": t + ramp_s + 0.2}
        return float(np.mean(timeline.played(table, times, 500)["x"]))

    first = play(t0)
    second = play(timeline.t_last_s + 0.5)
    third = play(timeline.t_last_s + 60.0)
    assert abs(first) < 1e-3 * abs(second), (first, second)
    assert second > 0.0 and 0.0 < third < 0.5 * second, (first, second, third)


def test_the_history_offset_is_what_moved_beyond_the_models_term():
    """Two plays of one table differ only by their history; what the scanner moved beyond
    what the model's history term says is the term's offset (afmctl.control.learn_run)."""
    from afmctl.control.learn_run import history_offset_nm
    term = np.linspace(9.0, 7.0, 500)                  # the model: 9 nm decaying to 7 over the record
    moved = term + 5.7 + np.random.default_rng(0).normal(0.0, 0.2, 500)
    assert history_offset_nm(moved, term) == pytest.approx(5.7, abs=0.05)
    assert history_offset_nm(moved - term, 0.0) == pytest.approx(5.7, abs=0.05)   # no creep stage: all of it


def test_only_an_axis_with_a_creep_stage_is_calibrated_and_offset():
    """The first table's second play measures the offset of the axes whose model has a creep
    stage; an axis without one (model-free) is learned from its recordings as they are — no
    offset from the first play — so its table is right for the play right after learning."""
    from afmctl.control.learn_history import HistoryTerms
    config = Config.model_validate({"amplifier": {"driver": "gcs", "output": "wave", "settle_s": 0.2, "slew_V_per_s": 1e5,
                                                  "port": "/dev/null"},
                                    "loop": {"rate_Hz": 1000.0},
                                    "safety": {"ramp_V_per_s": 5000.0, "slew_V_per_s": 1e5}})
    y0 = {"x": np.zeros(500), "y": np.zeros(500)}
    again = {"x": np.full(500, 3.0), "y": np.full(500, 4.0)}
    free = HistoryTerms(None)
    free.first_play(y0, {"x": np.zeros(500), "y": np.zeros(500)})
    assert not free.wants_calibration
    assert np.all(free.term("y", 5, (500,)) == 0.0)
    timeline = PlayTimeline(config, {"x": creep_model(gain=1.0)}, {"x": 0.0}, {"x": 70.0})
    mixed = HistoryTerms(timeline)
    mixed.first_play(y0, {"x": np.zeros(500), "y": np.zeros(500)})
    assert mixed.wants_calibration
    mixed.calibrate(again)
    assert set(mixed.offsets) == {"x"} and mixed.offsets["x"] == pytest.approx(3.0)
    assert np.all(mixed.term("y", 5, (500,)) == 0.0)


def test_a_short_settle_hold_is_said_and_a_long_one_not():
    from afmctl.config import LEARN_SETTLE_S
    from afmctl.control.learn_run import settle_advice
    config = Config.model_validate({"amplifier": {"driver": "gcs", "output": "wave", "settle_s": 0.2, "port": "/dev/null"}})
    assert "amplifier.settle_s = 0.2 s" in settle_advice(config)
    config.amplifier.settle_s = LEARN_SETTLE_S
    assert settle_advice(config) is None
    config.amplifier.settle_s = None                   # unset: learning holds LEARN_SETTLE_S
    assert settle_advice(config) is None


def test_learning_holds_two_seconds_unless_the_configuration_says_otherwise():
    from afmctl.config import DEFAULT_SETTLE_S, LEARN_SETTLE_S
    from afmctl.control.learn_run import with_learning_hold
    unset = Config.model_validate({"amplifier": {"driver": "gcs", "output": "wave", "port": "/dev/null"}})
    learning = with_learning_hold(unset)
    assert learning.amplifier.settle_s == LEARN_SETTLE_S == 2.0
    assert unset.amplifier.settle_s is None and unset.amplifier.hold_s() == DEFAULT_SETTLE_S == 0.2
    short = Config.model_validate({"amplifier": {"driver": "gcs", "output": "wave", "settle_s": 0.5,
                                                 "port": "/dev/null"}})
    assert with_learning_hold(short).amplifier.settle_s == 0.5


def _timeline_config(**amplifier) -> Config:
    return Config.model_validate({"amplifier": {"driver": "gcs", "output": "wave", "settle_s": 0.2, "slew_V_per_s": 1e5,
                                                "port": "socket://127.0.0.1:50000", **amplifier},
                                  "loop": {"rate_Hz": 1000.0},
                                  "safety": {"ramp_V_per_s": 5000.0, "slew_V_per_s": 1e5}})


def test_a_history_resumed_from_its_lag_states_continues_as_the_history_itself():
    """What `afmctl calibrate` keeps of its plays (the creep lag states where they ended) is
    all the history term needs: a history resumed from them gives the same term, to the
    last digits, as the history that played them."""
    model = ChainModel(hysteresis=PIModel(thresholds=[0.0, 20.0, 40.0], weights=[40.0, 8.0, 4.0]),
                       creep=creep_model(gain=1.0))
    played = VoltageHistory(model, DT_S, 0.0, settle_s=1.0)
    played.play(60.0 + 50.0 * np.sin(np.linspace(0.0, 40.0 * np.pi, 20_000)))
    played.ramp(0.0, 5000.0)
    rest = VoltageHistory(model, DT_S, 0.0, settle_s=600.0, peak_V=110.0)
    resumed = rest.copy()
    assert resumed.resume(played.creep_state(), played.last_V)
    table = np.linspace(30.0, 70.0, 300)
    for h in (played, resumed):
        h.hold(3.0)
    term = history_term_nm(resumed, rest, table)
    assert np.mean(term) > 1.0                                   # the plays left creep to see
    np.testing.assert_allclose(term, history_term_nm(played, rest, table), rtol=1e-9, atol=1e-9)
    assert not rest.copy().resume(played.creep_state()[:2], 0.0)  # another model's lags: not taken


def test_learning_starts_from_the_creep_a_recent_calibration_on_this_device_left(tmp_path):
    """The model's provenance names the device and keeps what its calibration left; a learn
    run on the same device within SETTLE_S starts its history there, the first play then
    carries a term, and nothing is taken from another device, an old calibration or an
    output that moved since."""
    import json
    import time

    from afmctl.control.learn_history import calibration_history
    model = creep_model(gain=1.0)
    charged = VoltageHistory(model, DT_S, 0.0, settle_s=1.0)
    charged.ramp_over(100.0, 0.1)
    charged.hold(20.0)
    charged.ramp(0.0, 5000.0)
    entry = {"ended_unix_s": time.time() - 2.0, "at_V": 0.0, "creep_state_nm": charged.creep_state()}
    scanner = tmp_path / "scanner.json"

    def reading(config: Config, path) -> Config:       # the configuration with scanner_model = path
        config = config.model_copy(deep=True)
        config.compensation.scanner_model = path
        return config

    def prior(device: dict, config: Config, **history) -> dict:
        scanner.write_text(json.dumps({"provenance": {"device": device, "history": {"x": {**entry, **history}}}}))
        return calibration_history(reading(config, scanner))

    here = {"driver": "gcs", "port": "socket://127.0.0.1:50000", "simulated": False}
    config = _timeline_config()
    assert prior({**here, "port": "socket://127.0.0.1:50001"}, config) == {}
    assert prior({**here, "simulated": True}, config) == {}
    assert calibration_history(config) == {} and calibration_history(reading(config, tmp_path / "none")) == {}
    for damaged in ("{not json", "[1, 2]", json.dumps({"provenance": {"device": "E-727", "history": {}}}),
                    json.dumps({"provenance": {"device": here, "history": ["x"]}})):
        scanner.write_text(damaged)
        assert calibration_history(reading(config, scanner)) == {}, damaged
    table = {"x": np.linspace(60.0, 70.0, 500)}

    def first_term(found: dict) -> tuple[dict, float]:
        timeline = PlayTimeline(config, {"x": model}, {"x": 0.0}, {"x": 70.0})
        taken = timeline.resume(found)
        t = timeline.t_last_s + 0.1
        times = {"approach": t, "settle": t + 0.012, "start": t + 0.212}
        return taken, float(np.mean(timeline.played(table, times, 500)["x"]))

    taken, term = first_term(prior(here, config))
    assert set(taken) == {"x"} and 1.5 < taken["x"] < 60.0 and term > 0.5
    assert first_term(prior(here, config, ended_unix_s=time.time() - 700.0)) == ({}, pytest.approx(0.0, abs=1e-9))
    assert first_term(prior(here, config, at_V=20.0))[0] == {}
    assert first_term(prior(here, config, creep_state_nm="x"))[0] == {}
