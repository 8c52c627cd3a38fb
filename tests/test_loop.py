"""The controller loop with an in-memory amplifier (RecordingAmplifier, a real Amplifier
implementation that checks every value): order, ramps, sinks, watchdog, faults, drift."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from afmctl.errors import AfmctlError
from afmctl.control.controller import Controller, State
from afmctl.control.pipeline import build_pipeline
from afmctl.control.runlog import RunLogReader
from afmctl.simulation.link import RecordingAmplifier
from afmctl.testing import make_config
from afmctl.testing import wait_until as wait_for



pytestmark = pytest.mark.usefixtures("no_leaked_threads")   # tests/conftest.py


def cfg_for(tmp_path, extra: str = "", rate: float = 2000.0, slew: float = 5000.0):
    return make_config(tmp_path, extra, loop={"rate_Hz": rate},
                       safety={"slew_V_per_s": slew, "ramp_V_per_s": 500, "watchdog_s": 0.03,
                               "reconnect_interval_s": 0.01})


class Sink:
    def __init__(self):
        self.batches, self.drift, self.status, self.threads = [], [], [], set()

    def on_setpoints(self, batch):
        self.threads.add(threading.current_thread().name)
        self.batches.append(batch.copy())

    def on_drift(self, est):
        self.drift.append(est)

    def on_status(self, st):
        self.threads.add(threading.current_thread().name)
        self.status.append(st)


def test_every_setpoint_in_order_and_logged(tmp_path):
    cfg = cfg_for(tmp_path)
    traj = np.column_stack([np.linspace(800, 4000, 300), np.linspace(400, 800, 300), np.full(300, 40.0)])
    amp = RecordingAmplifier(check_step_V=cfg.slew_V_per_s() * cfg.dt_s)
    sink = Sink()
    ctl = Controller(cfg, amp)
    ctl.add_sink(sink)
    ctl.start(traj, runlog_path=tmp_path / "r.afmlog")
    assert ctl.wait(10)
    ctl.close()
    assert ctl.state is State.STOPPED and amp.violations == []
    log = RunLogReader(tmp_path / "r.afmlog")
    sp = log.setpoints()
    ev = {e["event"]: e["seq"] for e in log.events()}
    # offline chain: exactly the voltages streamed between the start ramp and the end
    _, _, u_ref = build_pipeline(cfg).run(traj, cfg.compensation.temperature.T_C)
    ramp_end, end = ev["ramp-done"], ev["end"]
    sent = amp.as_array()
    assert end - ramp_end == len(traj)     # the ramp's last record is the first sample
    # exactly the offline chain, except samples that a late loop sent in quick succession
    # to catch up: those the safety layer slowed to the slew rate (counted, per axis)
    differs = np.any(np.abs(sent[ramp_end:end] - u_ref) > 1e-12, axis=1)
    assert int(differs.sum()) <= ctl.stats()["slew_limited"]
    np.testing.assert_allclose(sp["u_V"], sent)            # the log holds what was sent
    np.testing.assert_array_equal(sp["seq"], np.arange(len(sp)))
    np.testing.assert_allclose(sp["target_nm"][ramp_end:end], traj)
    # the start ramp began at the read-back (0 V) and the stop ramp ended at the safe value
    assert np.all(np.abs(sent[0]) <= cfg.safety.ramp_V_per_s * cfg.dt_s + 1e-12)
    np.testing.assert_allclose(sent[-1], 0.0)
    # sinks: same records, called off the loop thread
    got = np.concatenate(sink.batches)
    np.testing.assert_array_equal(got, sp)
    assert "afmctl-loop" not in sink.threads and "afmctl-dispatch" in sink.threads
    assert [s["state"] for s in sink.status][-1] == "stopped"
    st = ctl.stats()
    for key in ("lateness_p50_s", "lateness_p99_s", "lateness_max_s", "missed_deadlines", "samples", "errors"):
        assert key in st
    assert st["samples"] == len(sp) and st["errors"] == 0


def test_watchdog_holds_and_resumes_without_jump(tmp_path):
    cfg = cfg_for(tmp_path, '[trajectory]\nkind = "queue"\n')
    step = cfg.slew_V_per_s() * cfg.dt_s
    amp = RecordingAmplifier(check_step_V=step)
    ctl = Controller(cfg, amp)
    g = cfg.scanner.axis_spec("x").nm_per_V
    ctl.submit_segment(np.tile([10 * g, 5 * g, 0.0], (50, 1)), cfg.dt_s)
    ctl.start(cfg.trajectory)
    wait_for(lambda: ctl.state is State.HOLDING)
    n_hold = len(amp.received)
    time.sleep(0.05)
    assert len(amp.received) == n_hold           # held: nothing sent while stalled
    assert ctl.stats()["watchdog_trips"] == 1
    # a segment far away: resume ramps there within the slew limit
    ctl.submit_segment(np.tile([60 * g, 20 * g, 0.0], (20, 1)), 0.5e-3)
    wait_for(lambda: amp.outputs["x"] == pytest.approx(60.0))
    wait_for(lambda: ctl.state is State.HOLDING)   # stalls again after the segment
    ctl.stop()
    assert ctl.wait(10)
    ctl.close()
    assert amp.violations == []
    events = [e["event"] for e in RunLogReader(ctl.runlog_path).events()]
    assert events.count("watchdog") == 2 and "resume" in events


def test_safe_stall_action_ramps_to_safe_value(tmp_path):
    cfg = cfg_for(tmp_path, '[trajectory]\nkind = "queue"\n[safety.safe_V]\nx = 5.0\n')
    cfg.safety.on_stall = "safe"
    amp = RecordingAmplifier(check_step_V=cfg.slew_V_per_s() * cfg.dt_s)
    ctl = Controller(cfg, amp)
    g = cfg.scanner.axis_spec("x").nm_per_V
    ctl.submit_segment(np.tile([30 * g, 0.0, 0.0], (20, 1)), cfg.dt_s)
    ctl.start(None)
    wait_for(lambda: ctl.state is State.HOLDING)
    wait_for(lambda: amp.outputs["x"] == pytest.approx(5.0))
    ctl.estop()
    assert ctl.wait(5)
    ctl.close()
    assert amp.violations == []


def test_fault_holds_reconnects_and_resumes_from_readback(tmp_path):
    cfg = cfg_for(tmp_path)
    step = cfg.slew_V_per_s() * cfg.dt_s
    amp = RecordingAmplifier(check_step_V=step)
    g = cfg.scanner.axis_spec("x").nm_per_V
    n = 1500
    traj = np.column_stack([np.linspace(10 * g, 100 * g, n), np.full(n, 20 * g), np.zeros(n)])
    amp.fail_after = 200                   # the link vanishes mid-scan
    ctl = Controller(cfg, amp)
    ctl.start(traj)
    wait_for(lambda: ctl.state is State.FAULT)
    sent_before = len(amp.received)
    time.sleep(0.05)
    assert len(amp.received) == sent_before and ctl.state is State.FAULT
    assert ctl.stats()["errors"] >= 1
    # while away, the device output moved (e.g. front panel): resume must ramp from there
    amp.outputs["x"] = 30.0
    amp.fail = False
    wait_for(lambda: ctl.state is State.RUNNING)
    assert ctl.wait(10)
    ctl.close()
    assert amp.violations == []           # no step larger than the slew limit, from the read-back
    st = ctl.stats()
    assert st["faults"] == 1 and st["reconnects"] == 1
    events = [e["event"] for e in RunLogReader(ctl.runlog_path).events()]
    assert events.index("fault") < events.index("resume") < events.index("ramp-done", events.index("resume"))
    after = amp.as_array()[sent_before:]
    assert abs(after[0, 0] - 30.0) <= step + 1e-9


def test_gives_up_after_max_reconnects(tmp_path):
    cfg = cfg_for(tmp_path)
    cfg.safety.max_reconnects = 3
    amp = RecordingAmplifier()
    amp.fail_after = 10
    ctl = Controller(cfg, amp)
    ctl.start(np.zeros((500, 3)))
    assert ctl.wait(5)
    ctl.close()
    assert ctl.state is State.FAULT
    assert "give-up" in [e["event"] for e in RunLogReader(ctl.runlog_path).events()]


def test_unreadable_start_readback_is_a_fault_not_a_jump(tmp_path):
    cfg = cfg_for(tmp_path)
    cfg.safety.max_reconnects = 2
    amp = RecordingAmplifier(readback=lambda out: {**out, "y": "garbage"})
    ctl = Controller(cfg, amp)
    ctl.start(np.full((100, 3), 1000.0))
    assert ctl.wait(5)
    ctl.close()
    assert amp.received == [] and ctl.state is State.FAULT
    assert "not a voltage" in ctl.stats()["last_error"]


def test_drift_correction_and_temperature(tmp_path):
    cfg = cfg_for(tmp_path, "[compensation.drift]\nenabled = true\nparams = \"physical_tube\"\n")
    amp = RecordingAmplifier()
    ctl = Controller(cfg, amp)
    sink = Sink()
    ctl.add_sink(sink)
    with pytest.raises(AfmctlError, match="-50..150"):
        ctl.set_temperature(0.0, 400.0)
    ctl.start(np.full((600, 3), 2000.0))
    time.sleep(0.05)
    ctl.set_temperature(0.05, 24.0)
    assert ctl.wait(10)
    ctl.close()
    log = RunLogReader(ctl.runlog_path)
    sp, dr = log.setpoints(), log.drift()
    assert np.any(dr["T_C"] == 24.0) and dr["T_C"][0] == 22.0
    np.testing.assert_allclose(sp["corrected_nm"], sp["target_nm"] - dr["drift_nm"])
    assert np.abs(dr["drift_nm"]).max() > 0
    assert sink.drift and set(sink.drift[-1]) >= {"seq", "t_s", "T_C", "drift_nm"}


def test_segments_rejected_while_running_finite_trajectory(tmp_path):
    cfg = cfg_for(tmp_path)
    ctl = Controller(cfg, RecordingAmplifier())
    ctl.start(np.zeros((2000, 3)))
    with pytest.raises(AfmctlError, match="queue mode"):
        ctl.submit_segment(np.zeros((5, 3)), 1e-3)
    with pytest.raises(AfmctlError, match="stop it first"):
        ctl.start(np.zeros((5, 3)))
    ctl.stop()
    assert ctl.wait(5)
    ctl.close()
    with pytest.raises(AfmctlError, match="not finite"):
        ctl.submit_segment(np.array([[0, 0, np.nan]]), 1e-3)
    with pytest.raises(AfmctlError, match="dt_s"):
        ctl.submit_segment(np.zeros((5, 3)), -1)


def test_bad_trajectory_generator_ends_run_safely(tmp_path):
    cfg = cfg_for(tmp_path)

    def gen():
        yield np.full((50, 3), 500.0)
        yield np.array([[1.0, np.inf, 0.0]])

    amp = RecordingAmplifier(check_step_V=cfg.slew_V_per_s() * cfg.dt_s)
    ctl = Controller(cfg, amp)
    ctl.start(gen())
    assert ctl.wait(5)
    ctl.close()
    assert ctl.state is State.STOPPED and amp.violations == []
    assert "not finite" in ctl.stats()["last_error"]
    np.testing.assert_allclose(amp.as_array()[-1], 0.0)


def test_temperature_from_file(tmp_path):
    csv = tmp_path / "T.csv"
    csv.write_text("t,T\n0,22\n0.1,22\n0.2,26\n10,26\n")
    cfg = cfg_for(tmp_path, f'[compensation.temperature]\nsource = "file"\nfile = "{csv}"\n'
                            '[compensation.drift]\nenabled = true\nparams = "physical_tube"\n', rate=1000.0)
    ctl = Controller(cfg, RecordingAmplifier())
    ctl.start(np.full((400, 3), 1000.0))
    assert ctl.wait(10)
    ctl.close()
    dr = RunLogReader(ctl.runlog_path).drift()
    # the drift record of each tick carries the file's temperature at that time
    expect = np.interp(dr["t_s"], [0, 0.1, 0.2, 10], [22, 22, 26, 26])
    np.testing.assert_allclose(dr["T_C"], expect, atol=1e-9)


def test_single_axis_amplifier(tmp_path):
    cfg = cfg_for(tmp_path, '[scanner]\naxes = ["x"]\n[amplifier]\ndriver = "mdt694b"\n')
    amp = RecordingAmplifier(axes=("x",), check_step_V=cfg.slew_V_per_s() * cfg.dt_s)
    ctl = Controller(cfg, amp)
    ctl.start(np.column_stack([np.linspace(0, 3000, 200), np.full(200, 500.0), np.zeros(200)]))
    assert ctl.wait(10)
    ctl.close()
    assert amp.violations == [] and all(set(r) == {"x"} for r in amp.received)
    sp = RunLogReader(ctl.runlog_path).setpoints()
    assert np.all(sp["u_V"][:, 1:] == 0.0)            # undriven axes log 0 V
    assert sp["u_V"][:, 0].max() == pytest.approx(3000 / cfg.scanner.axis_spec("x").nm_per_V)


def test_restart_after_stop_and_after_giving_up(tmp_path):
    cfg = cfg_for(tmp_path)
    cfg.safety.max_reconnects = 1
    amp = RecordingAmplifier()
    ctl = Controller(cfg, amp)
    amp.fail_after = 5
    ctl.start(np.full((3000, 3), 800.0))
    assert ctl.wait(5) and ctl.state is State.FAULT
    ctl.close()
    amp.fail = False                      # the link is back: a new run may start
    ctl.start(np.full((50, 3), 800.0))
    assert ctl.wait(5)
    ctl.close()
    st = ctl.stats()
    assert ctl.state is State.STOPPED and st["samples"] > 50
    # the second run's statistics are its own (the first one's fault is in its own log)
    assert st["errors"] == st["faults"] == 0 and st["last_error"] is None


def test_lateness_histogram_percentiles():
    from afmctl.control.controller import _HBINS, _bin, _percentiles
    rng = np.random.default_rng(1)
    late = np.concatenate([rng.uniform(0, 50e-6, 990), rng.uniform(3e-3, 9e-3, 10)])
    h = np.zeros(_HBINS, np.int64)
    for v in late:
        h[_bin(float(v))] += 1
    p50, p99 = _percentiles(h, (0.5, 0.99))
    assert p50 == pytest.approx(np.percentile(late, 50), abs=0.5e-6)
    assert p99 == pytest.approx(np.sort(late)[989], abs=1e-6)  # 0.5 µs bins below 2 ms
    assert _bin(1.0) == _HBINS - 1 and _percentiles(np.zeros(_HBINS, np.int64), (0.5,)) == (0.0,)


class SlowReconnectAmplifier(RecordingAmplifier):
    """reconnect() blocks like a serial driver's (up to its reconnect_timeout_s)."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.release = threading.Event()
        self.in_reconnect = threading.Event()

    def reconnect(self):
        self.in_reconnect.set()
        self.release.wait(5.0)
        super().reconnect()


def test_estop_during_a_blocking_reconnect_is_honoured_at_once(tmp_path):
    cfg = cfg_for(tmp_path)
    amp = SlowReconnectAmplifier()
    amp.fail_after = 50
    ctl = Controller(cfg, amp)
    ctl.start(np.zeros((5000, 3)))
    try:
        assert amp.in_reconnect.wait(5)
        assert ctl.state is State.FAULT
        t0 = ctl.stats()["ticks"]
        time.sleep(0.05)
        assert ctl.stats()["ticks"] > t0          # the loop keeps ticking during the reconnect
        amp.fail = False
        n = len(amp.received)
        ctl.estop()
        assert ctl.wait(1.0)                       # not after the driver's reconnect timeout
        assert ctl.state is State.STOPPED
    finally:
        amp.release.set()
        ctl.close()
    assert len(amp.received) == n                  # nothing sent after the estop without a link
    events = [e["event"] for e in RunLogReader(ctl.runlog_path).events()]
    assert "estop" in events and "stop-in-fault" in events


def test_segments_with_bad_dt_or_positions_are_refused(tmp_path):
    from hypothesis import given, settings
    from hypothesis import strategies as st
    ctl = Controller(cfg_for(tmp_path), RecordingAmplifier())

    @settings(max_examples=60, deadline=None)
    @given(dt=st.floats(allow_nan=True, allow_infinity=True),
           v=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-1e3, 1e3)))
    def check(dt, v):
        seg = np.full((3, 3), v)
        try:
            n = ctl.submit_segment(seg, dt)
        except AfmctlError as err:
            assert "segment" in str(err)
            return
        assert 1e-6 <= dt <= 10.0 and abs(v) <= 1e7 and n >= 1
    check()
    ctl._deque.clear()


def test_segment_that_would_resample_to_too_many_samples_is_refused(tmp_path):
    from afmctl.control.controller import MAX_SEGMENT_SAMPLES
    ctl = Controller(cfg_for(tmp_path), RecordingAmplifier())
    with pytest.raises(AfmctlError, match="at most"):
        ctl.submit_segment(np.zeros((1000, 3)), 10.0)       # 10 000 s at 2 kHz
    assert len(ctl._deque) == 0
    n_in = 101
    dt_in = (MAX_SEGMENT_SAMPLES - 1) * ctl.dt_s / (n_in - 1)   # exactly the largest segment
    assert ctl.submit_segment(np.zeros((n_in, 3)), dt_in) == MAX_SEGMENT_SAMPLES
    ctl._deque.clear()


class _StallingAmplifier(RecordingAmplifier):
    """Stalls the loop thread once (like a hypervisor pause) when sample ``at`` is sent."""

    def __init__(self, at: int, stall_s: float, **kw) -> None:
        super().__init__(**kw)
        self.at, self.stall_s = at, stall_s

    def set_voltages(self, volts) -> None:
        if len(self.received) == self.at:
            time.sleep(self.stall_s)
        super().set_voltages(volts)


def test_last_setpoint_is_reached_after_a_stall_near_the_end(tmp_path):
    """After a late tick the overdue samples go out back to back, each slowed by the slew
    limit (per wall time), so the output lags the trajectory; the run must still reach the
    trajectory's last setpoint (at the slew limit) before it ramps to the safe value."""
    from afmctl.simulation.link import SendClock
    cfg = cfg_for(tmp_path)
    cfg.loop.resync_periods = 1000          # catch up sample by sample (no resync)
    n = 200
    clock = SendClock()                     # the amplifier checks slew per time between sends
    amp = _StallingAmplifier(at=n - 20, stall_s=0.05, check_slew_V_per_s=cfg.slew_V_per_s(),
                             clock=clock.stamp)
    ctl = Controller(cfg, amp)
    ctl.safety.clock = clock
    ctl.start(np.column_stack([np.linspace(0, 3000, n), np.zeros(n), np.zeros(n)]))
    assert ctl.wait(10)
    ctl.close()
    assert amp.violations == []
    x = np.array([r["x"] for r in amp.received])
    goal = 3000 / cfg.scanner.axis_spec("x").nm_per_V
    assert x.max() == pytest.approx(goal, abs=1e-9)
    assert ctl.stats()["lateness_max_s"] > 0.03          # the stall happened


def test_loop_phase_puts_every_deadline_at_its_share_of_the_period(tmp_path):
    """loop.phase 0.5 at 2 kHz: the run's first deadline (clock_bases) falls half a period
    after a whole number of periods on perf_counter."""
    cfg = make_config(tmp_path, loop={"rate_Hz": 2000.0, "phase": 0.5},
                      safety={"slew_V_per_s": 5000.0, "ramp_V_per_s": 500, "watchdog_s": 0.03})
    traj = np.column_stack([np.linspace(800, 1000, 100), np.full(100, 400.0), np.full(100, 40.0)])
    ctl = Controller(cfg, RecordingAmplifier())
    ctl.start(traj)
    assert ctl.wait(10)
    ctl.close()
    k = (ctl.clock_bases[0][1] - 0.5 * cfg.dt_s) / cfg.dt_s
    assert ctl.state is State.STOPPED and abs(k - round(k)) < 1e-6, k
