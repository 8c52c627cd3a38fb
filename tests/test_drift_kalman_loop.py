"""The Kalman drift correction in the real-time controller (compensation.drift.kalman):
without measurements the estimate is the model's and its uncertainty grows; a measurement
pulls the estimate toward model + bias and shrinks it; offline == per-sample; bad
measurements are refused; the voltages stay within the limits."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmctl.config import load_config
from afmctl.errors import AfmctlError
from afmctl.control.controller import Controller, State
from afmctl.control.pipeline import build_pipeline
from afmctl.control.runlog import RunLogReader
from afmctl.simulation.link import RecordingAmplifier
from afmctl.testing import assert_no_threads_left, bridge_on_free_port, make_config
from afmctl.testing import wait_until as wait_for


@pytest.fixture(autouse=True)
def no_leaked_threads():
    yield
    assert_no_threads_left("afmctl-")


def cfg_for(tmp_path, kalman: bool = True, extra: str = ""):
    return make_config(tmp_path, extra, loop={"rate_Hz": 1000},
                       safety={"slew_V_per_s": 5000, "ramp_V_per_s": 500, "watchdog_s": 0.5},
                       compensation={"drift": {"enabled": True, "params": "physical_tube", "kalman": kalman,
                                               "kalman_bias_std0_nm": 5.0, "kalman_q_bias_nm2_per_s": 10.0}})


class DriftSink:
    def __init__(self):
        self.drift = []

    def on_drift(self, est):
        self.drift.append(est)


def test_config_off_by_default_and_checked():
    sim = "[simulation]\nenabled = true\n"
    cfg = load_config(text=sim + "[compensation.drift]\nenabled = true\n")
    assert cfg.compensation.drift.kalman is False
    assert build_pipeline(cfg).kalman is None
    with pytest.raises(Exception, match="kalman_q_bias_nm2_per_s"):
        load_config(text=sim + "[compensation.drift]\nenabled = true\nkalman = true\nkalman_q_bias_nm2_per_s = -1\n")
    with pytest.raises(Exception, match="drift.enabled"):
        load_config(text=sim + "[compensation.drift]\nkalman = true\n")


def test_loop_estimate_model_then_measurement(tmp_path):
    """(a) no measurement: estimate == model, std grows; (b) a measured offset moves the
    estimate toward model + offset and shrinks std; (e) voltages within the limits."""
    cfg = cfg_for(tmp_path)
    amp = RecordingAmplifier(check_step_V=cfg.slew_V_per_s() * cfg.dt_s)
    ctl = Controller(cfg, amp)
    sink = DriftSink()
    ctl.add_sink(sink)
    with pytest.raises(AfmctlError, match="idle"):
        ctl.submit_drift_measurement([1.0, 2.0, 3.0], 1.0)
    ctl.start(None)                        # queue mode: runs until stopped
    # target 0 nm: no start ramp, so every logged record is one step of the chain and the
    # model can be replayed offline from the log
    ctl.submit_segment(np.zeros((1500, 3)), cfg.dt_s)
    wait_for(lambda: ctl.stats()["samples"] > 20)
    ctl.set_temperature(0.0, 42.0)         # a 20 °C step from the configured 22 °C
    wait_for(lambda: ctl.stats()["samples"] > 400 and len(sink.drift) > 2)
    s1 = sink.drift[-1]
    offset = np.array([40.0, -25.0, math.nan])
    seq0 = ctl.stats()["samples"]
    ctl.submit_drift_measurement(np.array(s1["drift_nm"]) + offset, 0.5, t_s=None)
    wait_for(lambda: sink.drift[-1]["seq"] > seq0 + 50)
    n_run = ctl.stats()["samples"]         # records before the stop (then: finish ramp)
    ctl.stop()
    assert ctl.wait(10)
    ctl.close()
    assert ctl.state is State.STOPPED and amp.violations == []

    # the model alone, replayed offline on the logged temperatures and voltages
    log = RunLogReader(ctl.runlog_path)
    sp, dr = log.setpoints()[:n_run], log.drift()[:n_run]
    from afmctl.control.pipeline import load_drift_params
    model = load_drift_params("physical_tube").predictor(cfg.dt_s)
    u_prev = np.zeros(3)
    m = np.zeros((len(dr), 3))
    for i in range(len(dr)):
        m[i] = model.step(float(dr["T_C"][i]), u_prev)
        u_prev = sp["u_V"][i]
    bias = dr["drift_nm"] - m
    assert np.abs(m).max() > 0.5                           # the step does drive the model
    k = int(np.argmax(np.abs(bias[:, 0]) > 1e-9))           # first sample after the update
    assert k > 100
    np.testing.assert_allclose(dr["drift_nm"][:k], m[:k], rtol=0, atol=1e-9)   # (a)
    # (b) x and y pulled most of the way to the measured offset, z (NaN) untouched
    assert bias[k, 0] == pytest.approx(40.0, abs=8.0) and bias[k, 1] == pytest.approx(-25.0, abs=5.0)
    np.testing.assert_allclose(bias[:, 2], 0.0, atol=1e-9)
    np.testing.assert_allclose(sp["corrected_nm"], sp["target_nm"] - dr["drift_nm"])

    stds = [np.array(d["std_nm"]) for d in sink.drift if d["std_nm"] is not None]
    seqs = [d["seq"] for d in sink.drift if d["std_nm"] is not None]
    assert len(stds) == len(sink.drift)
    before = [s for s, q in zip(stds, seqs) if q < k]
    after = [s for s, q in zip(stds, seqs) if q >= k]
    assert before[-1][0] > before[0][0] > 5.0              # (a) std grows from its prior 5 nm
    assert after[0][0] < 1.0 < before[-1][0]               # (b) shrinks at the update ...
    assert after[0][2] == pytest.approx(before[-1][2], rel=0.2)   # ... only on measured axes
    # (e) every sent voltage inside the configured limits
    assert_within_limits(cfg, sp["u_V"])


def assert_within_limits(cfg, u):
    for i, axis in enumerate(cfg.scanner.axes):
        lo, hi = cfg.limits(axis)
        assert np.all(u[:, i] >= lo - 1e-9) and np.all(u[:, i] <= hi + 1e-9)


def test_huge_measured_drift_cannot_push_voltages_out(tmp_path):
    """(e) a measurement claiming 1e5 nm of drift drives the corrected target far out of
    range; the safety layer still keeps every voltage inside the limits and the slew."""
    cfg = cfg_for(tmp_path)
    amp = RecordingAmplifier(check_step_V=cfg.slew_V_per_s() * cfg.dt_s)
    ctl = Controller(cfg, amp)
    ctl.start(None)
    ctl.submit_segment(np.full((600, 3), 3000.0), cfg.dt_s)
    wait_for(lambda: ctl.stats()["samples"] > 100)
    ctl.submit_drift_measurement([1e5, -1e5, 1e5], 0.01)
    wait_for(lambda: ctl.stats()["samples"] > 400)
    ctl.stop()
    assert ctl.wait(10)
    ctl.close()
    sp, dr = RunLogReader(ctl.runlog_path).setpoints(), RunLogReader(ctl.runlog_path).drift()
    assert np.abs(dr["drift_nm"]).max() > 5e4          # the estimate did take the measurement
    assert np.all(np.isfinite(dr["std_nm"])) and dr["std_nm"][-1, 0] < dr["std_nm"][50, 0]  # logged
    assert amp.violations == []
    assert_within_limits(cfg, sp["u_V"])


def test_filter_off_std_is_none(tmp_path):
    cfg = cfg_for(tmp_path, kalman=False)
    ctl = Controller(cfg, RecordingAmplifier())
    sink = DriftSink()
    ctl.add_sink(sink)
    ctl.start(np.full((100, 3), 1000.0))
    with pytest.raises(AfmctlError, match="Kalman filter is off"):
        ctl.submit_drift_measurement([1.0, 1.0, 1.0], 1.0)
    assert ctl.wait(10)
    ctl.close()
    assert sink.drift and all(d["std_nm"] is None for d in sink.drift)
    assert np.all(np.isnan(RunLogReader(ctl.runlog_path).drift()["std_nm"]))


@pytest.mark.parametrize("meas, std, t_s, field", [
    ([1.0, 2.0], 1.0, None, "measured_drift_nm"),
    ([1.0, math.inf, 2.0], 1.0, None, "measured_drift_nm"),
    ([math.nan] * 3, 1.0, None, "measured_drift_nm"),
    (["a", 1.0, 2.0], 1.0, None, "measured_drift_nm"),
    ([1.0, 2.0, 3e9], 1.0, None, "measured_drift_nm"),
    ([1.0, 2.0, 3.0], 0.0, None, "std_nm"),
    ([1.0, 2.0, 3.0], math.nan, None, "std_nm"),
    ([1.0, 2.0, 3.0], "1", None, "std_nm"),
    ([1.0, 2.0, 3.0], 1.0, -1.0, "t_s"),
    ([1.0, 2.0, 3.0], 1.0, math.inf, "t_s"),
])
def test_bad_measurements_rejected(tmp_path, meas, std, t_s, field):
    """(d) refused with an error naming the field and its range, before reaching the loop."""
    cfg = cfg_for(tmp_path)
    ctl = Controller(cfg, RecordingAmplifier())
    ctl.start(None)
    try:
        with pytest.raises(AfmctlError, match=rf"drift-measurement: {field} .*(range|values)"):
            ctl.submit_drift_measurement(meas, std, t_s)
        assert len(ctl._drift_meas) == 0
    finally:
        ctl.stop()
        ctl.wait(5)
        ctl.close()


def _pipe(tmp_path):
    return build_pipeline(cfg_for(tmp_path))


@settings(max_examples=15, deadline=None)
@given(st.integers(1, 150), st.floats(-50, 50), st.floats(0.1, 5.0))
def test_block_equals_step_with_filter(tmp_path_factory, i_meas, offset, std):
    """(c) the offline path (run) == per-sample step, measurements included."""
    tmp = tmp_path_factory.mktemp("k")
    n = 200
    t = np.arange(n)
    targets = np.column_stack([1000 + 500 * np.sin(t / 30), 800 + 0 * t, 50 + 0.1 * t])
    T = 22.0 + np.where(t > 20, 2.0, 0.0)
    meas = {i_meas: ([offset, math.nan, -offset], std)}
    a = _pipe(tmp)
    a.reset()
    d, c, u = a.run(targets, T, meas)
    b = _pipe(tmp)
    b.reset()
    prev = (0.0, 0.0, 0.0)
    for i in range(n):
        if i in meas:
            b.update_drift(*meas[i])
        out = b.step(*targets[i], float(T[i]), prev)
        assert out[0:3] == tuple(d[i]) and out[3:6] == tuple(c[i]) and out[6:9] == tuple(u[i])
        prev = out[6:9]
    assert b.drift_std_nm() == a.drift_std_nm()
    # before the measurement the estimate is the model's (filter-off pipeline)
    off = build_pipeline(cfg_for(tmp, kalman=False))
    off.reset()
    d0, _, _ = off.run(targets, T)
    np.testing.assert_array_equal(d[:i_meas], d0[:i_meas])
    assert abs(d[-1, 0] - d[i_meas - 1, 0]) > 0   # the measurement did change the estimate


def test_drift_measurement_over_zenoh_cmd(tmp_path):
    """The ``drift-measurement`` command on the ``cmd`` queryable (real sessions on
    loopback): accepted → the published drift carries the filter's std and moves by the
    measured offset; bad args → an error reply naming the field."""
    import zenoh
    import json

    from afmctl.zenoh_api.messages import CmdRequest

    cfg = cfg_for(tmp_path, extra='[scanner]\nname = "s1"\n')
    ctl = Controller(cfg, RecordingAmplifier())
    bridge, cli = bridge_on_free_port(ctl, "s1", status_period_s=0.2)
    session = zenoh.open(cli.to_zenoh_config())
    drift: list[dict] = []
    sub = session.declare_subscriber("afm/s1/drift", lambda s: drift.append(json.loads(s.payload.to_bytes())))

    def cmd(name, seq, **args):
        replies = session.get("afm/s1/cmd", payload=CmdRequest(cmd=name, seq=seq, args=args).to_json_bytes(),
                              timeout=3.0)
        out = [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
        assert len(out) == 1, out
        return out[0]

    try:
        assert cmd("start", 0)["ok"]
        ctl.submit_segment(np.zeros((1500, 3)), cfg.dt_s)
        wait_for(lambda: len(drift) > 3 and drift[-1]["std_nm"] is not None)
        before = drift[-1]
        bad = cmd("drift-measurement", 1, measured_drift_nm=[1.0, None], std_nm=1.0)
        assert bad["ok"] is False and "measured_drift_nm" in bad["error"]
        bad = cmd("drift-measurement", 2, measured_drift_nm=[1.0, 2.0, 3.0], std_nm=0.0)
        assert bad["ok"] is False and "std_nm" in bad["error"] and "0.000001" in bad["error"]
        target = [before["drift_nm"][0] + 30.0, None, None]
        ok = cmd("drift-measurement", 3, measured_drift_nm=target, std_nm=0.5)
        assert ok["ok"], ok
        wait_for(lambda: drift[-1]["std_nm"][0] < 1.0)
        after = drift[-1]
        assert after["drift_nm"][0] - before["drift_nm"][0] == pytest.approx(30.0, abs=6.0)
        assert after["std_nm"][1] > before["std_nm"][1] > 1.0          # y not measured: still growing
    finally:
        sub.undeclare()
        session.close()
        ctl.stop()
        ctl.wait(5)
        ctl.close()
        bridge.close()
