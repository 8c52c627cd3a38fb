"""The safety layer: no request, trajectory, configuration or device reply puts a value
outside the limits or a step larger than the slew limit on the wire.

The amplifier here is :class:`afmctl.simulation.link.RecordingAmplifier`, a real implementation of
the Amplifier ABC that checks every value it receives (and a real-backend run is in
tests/test_hil.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from afmctl.errors import AfmctlError
from afmctl.control.controller import Controller, State
from afmctl.control.safety import ReadbackError, SafetyLayer, Watchdog
from afmctl.simulation.link import RecordingAmplifier
from afmctl.drivers.errors import AmplifierConnectionError

floats_any = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                       st.floats(min_value=-1e4, max_value=1e4))


def _layer(lo=0.0, hi=150.0, slew=1000.0, dt=1e-3, dev=(0.0, 150.0), initial=0.0):
    amp = RecordingAmplifier(limits_V={a: dev for a in "xyz"},
                             check_limits_V={a: (max(lo, dev[0]), min(hi, dev[1])) for a in "xyz"},
                             check_step_V=slew * dt, initial_V={a: initial for a in "xyz"})
    return amp, SafetyLayer(amp, ("x", "y", "z"), {a: (lo, hi) for a in "xyz"}, slew, dt)


@settings(max_examples=200, deadline=None)
@given(reqs=st.lists(st.tuples(floats_any, floats_any, floats_any), min_size=1, max_size=60),
       lo=st.floats(-200, 100), span=st.floats(0.5, 300), slew=st.floats(1.0, 1e5),
       dt=st.floats(1e-5, 1e-2), dev_lo=st.floats(-50, 50), dev_span=st.floats(10, 300))
def test_send_never_violates_limits_or_slew(reqs, lo, span, slew, dt, dev_lo, dev_span):
    hi = lo + span
    dev = (dev_lo, dev_lo + dev_span)
    if max(lo, dev[0]) >= min(hi, dev[1]):
        with pytest.raises(AfmctlError, match="leave no range"):
            _layer(lo, hi, slew, dt, dev)
        return
    start = min(max(0.0, max(lo, dev[0])), min(hi, dev[1]))
    amp, layer = _layer(lo, hi, slew, dt, dev, initial=start)
    layer.sync_from_device()
    for r in reqs:
        layer.send(r)
    for _ in range(5):
        layer.ramp_step([math.nan, 1e9, -1e9], 1e12)
    assert amp.violations == []
    assert len(amp.received) == len(reqs) + 5


@settings(max_examples=100, deadline=None)
@given(reply=st.one_of(st.none(), st.text(max_size=5), st.floats(allow_nan=True, allow_infinity=True),
                       st.integers(-10**6, 10**6), st.just("75.0")))
def test_any_readback_reply_is_safe(reply):
    """Whatever the device reports as its output, the next value sent is within the limits
    and within one slew step of the true output — or the layer refuses to move."""
    true_V = 40.0
    amp = RecordingAmplifier(check_step_V=1.0, initial_V={a: true_V for a in "xyz"},
                             readback=lambda out: {**out, "x": reply})
    layer = SafetyLayer(amp, ("x", "y", "z"), {}, 1000.0, 1e-3)
    try:
        layer.sync_from_device()
    except ReadbackError as err:
        assert "axis x" in str(err)
        assert amp.received == []
        return
    # accepted: only a reply that is a number within one step of the limits
    v = float(reply)
    assert -1.0 <= v <= 151.0
    layer.send([v, true_V, true_V])
    assert all(0 <= r["x"] <= 150 for r in amp.received)


def test_readback_near_limit_is_clamped_and_reported():
    amp = RecordingAmplifier(initial_V={"x": 150.5, "y": 0.0, "z": 0.0})
    layer = SafetyLayer(amp, ("x", "y", "z"), {}, 1000.0, 1e-3)  # step 1 V
    warnings = layer.sync_from_device()
    assert layer.last[0] == 150.5 and "150.5" in warnings[0]   # the true output is the reference
    layer.send([math.nan, 0.0, 0.0])       # even "hold" moves it inside, within one step
    assert amp.received[-1]["x"] == 150.0
    assert amp.violations == []


def test_limits_intersect_config_and_device():
    amp = RecordingAmplifier(limits_V={a: (-10.0, 120.0) for a in "xyz"})
    layer = SafetyLayer(amp, ("x", "y"), {"x": (0.0, 150.0), "y": (5.0, 100.0)}, 1e6, 1e-3)
    assert (layer.lo, layer.hi) == ([0.0, 5.0], [120.0, 100.0])
    with pytest.raises(AfmctlError, match="not driven"):
        SafetyLayer(RecordingAmplifier(axes=("x",)), ("x", "y"), {}, 1.0, 1e-3)


def test_nonfinite_request_holds_last_value():
    amp, layer = _layer()
    layer.send([1.0, 1.0, 1.0])
    layer.send([math.nan, math.inf, -math.inf])
    assert amp.received[-1] == {"x": 1.0, "y": 1.0, "z": 1.0}
    assert layer.nonfinite == 3


def test_watchdog():
    t = [0.0]
    wd = Watchdog(0.1, clock=lambda: t[0])
    t[0] = 0.05
    assert not wd.expired()
    t[0] = 0.2
    assert wd.expired()
    wd.feed()
    assert not wd.expired()


# ----------------------------------------------------------------------------- whole loop
def _cfg(extra: str = "", rate: float = 5000.0, slew: float = 2000.0):
    from afmctl.testing import make_config
    return make_config(None, extra, loop={"rate_Hz": rate},
                       safety={"slew_V_per_s": slew, "ramp_V_per_s": 1000, "watchdog_s": 0.05})


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(traj=st.lists(st.tuples(st.floats(-1e6, 1e6), st.floats(-1e6, 1e6), st.floats(-1e6, 1e6)),
                     min_size=1, max_size=80),
       gain=st.floats(0.5, 500.0), lo=st.floats(-20, 60), span=st.floats(1.0, 150.0))
def test_controller_fuzz_never_emits_unsafe_voltage(traj, gain, lo, span):
    """Random trajectories, calibrations and limits through the whole controller."""
    hi = lo + span
    if min(hi, 150.0) <= max(lo, 0.0):   # no range left with the amplifier's 0..150 V
        with pytest.raises(AfmctlError, match="leave no voltage range"):
            _cfg(f"[safety.limits_V.x]\nmin_V = {lo}\nmax_V = {hi}\n")
        return
    cfg = _cfg(f"""
[safety.limits_V.x]
min_V = {lo}
max_V = {hi}
[scanner.calibration.x]
nm_per_V = {gain}
[scanner.calibration.y]
nm_per_V = {gain}
offset_V = -30
""")
    dt = cfg.dt_s
    slew_step = cfg.slew_V_per_s() * dt
    amp = RecordingAmplifier(limits_V={a: (-20.0, 150.0) for a in "xyz"},
                             check_limits_V={"x": (max(lo, 0.0), min(hi, 150.0)), "y": (0.0, 150.0),
                                             "z": (0.0, 150.0)},
                             check_step_V=slew_step,
                             initial_V={"x": min(max(0.0, lo), hi), "y": 0.0, "z": 0.0})
    cfg.safety.limits_V.update({})
    ctl = Controller(cfg, amp)
    # y, z default limits 0..150 (amplifier section)
    ctl.start(np.array(traj))
    assert ctl.wait(20)
    ctl.close()
    assert amp.violations == []
    assert ctl.state is State.STOPPED


def test_estop_ramps_down_within_slew_limit():
    cfg = _cfg("[trajectory]\nkind = \"queue\"\n", rate=2000.0, slew=500.0)
    amp = RecordingAmplifier(check_step_V=500.0 / 2000.0)
    ctl = Controller(cfg, amp)
    gain = cfg.scanner.axis_spec("x").nm_per_V
    seg = np.tile([100.0 * gain, 50.0 * gain, 20.0 * gain], (400, 1))
    ctl.submit_segment(seg, cfg.dt_s)
    ctl.start(cfg.trajectory)
    import time
    t0 = time.monotonic()
    while amp.outputs["x"] < 99.99 and time.monotonic() - t0 < 5:
        time.sleep(0.01)
    assert amp.outputs["x"] == pytest.approx(100.0)
    n0 = len(amp.received)
    limited0 = ctl.safety.slew_limited
    ctl.estop()
    assert ctl.wait(10)
    ctl.close()
    down = amp.as_array()[n0:]
    assert amp.violations == []
    assert np.allclose(down[-1], 0.0)
    # at the slew limit: 100 V at 0.25 V/sample takes 400 samples; a sample sent less than
    # a period after the previous one (jitter, catching up) moves less and costs at most
    # one more sample
    assert 395 <= len(down) <= 405 + (ctl.safety.slew_limited - limited0)
    assert ctl.state is State.STOPPED


# ----------------------------------------------------------------------------- slew in V/s of wall time
@settings(max_examples=150, deadline=None)
@given(steps=st.lists(st.tuples(floats_any, st.one_of(st.just(0.0), st.floats(0.0, 2e-3),
                                                       st.floats(1e-3, 1e3), st.floats(-1e-3, 0.0))),
                      min_size=1, max_size=60),
       slew=st.floats(1.0, 1e5), dt=st.floats(1e-5, 1e-2))
def test_slew_limit_holds_per_wall_time_between_sends(steps, slew, dt):
    """Sends that come faster than the sample period (a late loop catching up) get smaller
    steps: |Δu| ≤ slew · Δt of wall time, and never more than slew · dt per send."""
    t = [0.0]
    from afmctl.simulation.link import SendClock
    clock = SendClock(lambda: t[0])
    amp = RecordingAmplifier(check_step_V=slew * dt, check_slew_V_per_s=slew, clock=clock.stamp)
    layer = SafetyLayer(amp, ("x", "y", "z"), {}, slew, dt, clock=clock)
    layer.sync_from_device()
    for req, adv in steps:
        t[0] += adv
        layer.send([req, 150.0 - (req if math.isfinite(req) else 0.0), 75.0])
    for _ in range(3):
        t[0] += 1e-7
        layer.ramp_step([150.0, 0.0, 0.0], 1e12)
    assert amp.violations == []


def test_burst_of_sends_is_slowed_to_the_slew_rate():
    t = [0.0]
    from afmctl.simulation.link import SendClock
    clock = SendClock(lambda: t[0])
    amp = RecordingAmplifier(check_slew_V_per_s=1000.0, clock=clock.stamp)
    layer = SafetyLayer(amp, ("x",), {}, 1000.0, 1e-3, clock=clock)   # 1 V per 1 ms sample
    layer.sync_from_device()
    for _ in range(10):            # ten samples sent within 10 µs
        t[0] += 1e-6
        layer.send([150.0, 0.0, 0.0])
    assert amp.outputs["x"] == pytest.approx(1.0 + 9 * 1e-3)   # full step first, then 1 mV per µs
    t[0] += 1.0                    # held for a second: still only one step
    layer.send([150.0, 0.0, 0.0])
    assert amp.outputs["x"] == pytest.approx(2.009)
    assert amp.violations == []


class StallingAmplifier(RecordingAmplifier):
    """Blocks once in set_voltages (a stalled link / a descheduled loop)."""

    def __init__(self, stall_at: int, stall_s: float, **kw):
        super().__init__(**kw)
        self.stall_at, self.stall_s = stall_at, stall_s

    def set_voltages(self, volts):
        super().set_voltages(volts)
        if len(self.received) == self.stall_at:
            import time
            time.sleep(self.stall_s)


def test_loop_catching_up_after_a_stall_keeps_the_slew_rate():
    """After a stall the loop sends the overdue samples back to back; at the amplifier
    that must not be faster than slew_V_per_s (it was: 1 V steps microseconds apart)."""
    from afmctl.simulation.link import SendClock
    cfg = _cfg(rate=1000.0, slew=1000.0)
    cfg.loop.resync_periods = 1000
    clock = SendClock()
    amp = StallingAmplifier(stall_at=100, stall_s=0.04, check_slew_V_per_s=1000.0, clock=clock.stamp,
                            check_step_V=1.0)
    ctl = Controller(cfg, amp)
    ctl.safety.clock = clock
    gain = cfg.scanner.axis_spec("x").nm_per_V
    ramp = np.zeros((300, 3))
    ramp[:, 0] = np.minimum(np.arange(300) * 0.9, 140.0) * gain     # 0.9 V per 1 ms sample
    ctl.start(ramp)
    assert ctl.wait(20)
    ctl.close()
    assert ctl.stats()["lateness_max_s"] > 0.02      # the stall happened and was caught up
    assert amp.violations == []


class FuzzAmplifier(RecordingAmplifier):
    """Fails at send ``fail_at``; the first ``bad_reconnects`` reconnects fail, then the
    output reads back as ``moved_V`` on x (moved while away); at send ``action_at`` it asks
    the controller to stop or estop (from the loop thread: only a flag is set)."""

    def __init__(self, *, fail_at, bad_reconnects, moved_V, action_at, action, action_in_fault=False, **kw):
        super().__init__(**kw)
        self.fail_after = fail_at
        self.bad_reconnects, self.moved_V = bad_reconnects, moved_V
        self.action_at, self.action = action_at, action
        self.action_in_fault = action_in_fault
        self.sent_at_action = None
        self.ctl = None

    def set_voltages(self, volts):
        super().set_voltages(volts)
        if self.ctl is not None and len(self.received) == self.action_at:
            getattr(self.ctl, self.action)()

    def reconnect(self):
        if self.ctl is not None and self.action_in_fault:
            self.action_in_fault = False
            self.sent_at_action = len(self.received)
            getattr(self.ctl, self.action)()      # stop / estop while the link is away
        if self.bad_reconnects > 0:
            self.bad_reconnects -= 1
            raise AmplifierConnectionError("still away (fuzz)")
        self.fail = False
        self.outputs["x"] = self.moved_V
        super().reconnect()


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(traj=st.lists(st.tuples(st.floats(-1e6, 1e6), st.floats(-1e6, 1e6), st.floats(-1e6, 1e6)),
                     min_size=1, max_size=120),
       start_V=st.floats(-5.0, 160.0), moved_V=st.one_of(st.floats(-5.0, 160.0), st.just(math.nan)),
       fail_at=st.one_of(st.none(), st.integers(0, 150)), bad_reconnects=st.integers(0, 2),
       action_at=st.integers(1, 300), action=st.sampled_from(["stop", "estop"]),
       action_in_fault=st.booleans(), lo=st.floats(0.0, 60.0), span=st.floats(5.0, 150.0))
def test_faults_reconnects_stops_and_readbacks_never_make_an_unsafe_step(
        traj, start_V, moved_V, fail_at, bad_reconnects, action_at, action, action_in_fault, lo, span):
    """The whole controller under faults at any sample, read-backs inside/outside the
    limits (also after a reconnect), stop/estop at any time (also during a ramp or a
    fault): every value the amplifier receives is inside the limits and, against the
    wall time between sends, within the slew limit."""
    from afmctl.simulation.link import SendClock
    hi = min(lo + span, 150.0)
    cfg = _cfg(f"""
[safety]
reconnect_interval_s = 0.002
max_reconnects = 3
[safety.limits_V.x]
min_V = {lo}
max_V = {hi}
""", rate=5000.0, slew=2000.0)
    clock = SendClock()
    amp = FuzzAmplifier(fail_at=fail_at, bad_reconnects=bad_reconnects, moved_V=moved_V, action_at=action_at,
                        action=action, action_in_fault=action_in_fault,
                        check_limits_V={"x": (lo, hi), "y": (0.0, 150.0), "z": (0.0, 150.0)},
                        check_step_V=cfg.slew_V_per_s() * cfg.dt_s, check_slew_V_per_s=cfg.slew_V_per_s(),
                        clock=clock.stamp, initial_V={"x": start_V, "y": 0.0, "z": 0.0})
    ctl = Controller(cfg, amp)
    ctl.safety.clock = clock
    amp.ctl = ctl
    ctl.start(np.array(traj))
    assert ctl.wait(20)
    ctl.close()
    assert amp.violations == []
    assert ctl.state in (State.STOPPED, State.FAULT)
    if amp.sent_at_action is not None:     # stopped during a fault: nothing sent after it
        assert len(amp.received) == amp.sent_at_action and ctl.state is State.STOPPED


class StepCheckingAmplifier(RecordingAmplifier):
    """Like the serial/CAN drivers with ``max_step_V``: refuses (LimitError) a step larger
    than that from its last output, which it keeps at the device's resolution."""

    def __init__(self, max_step_V, resolution_V=0.0025, refuse_at=None, **kw):
        super().__init__(**kw)
        self.max_step_V, self.resolution_V, self.refuse_at = max_step_V, resolution_V, refuse_at

    def set_voltages(self, volts):
        from afmctl.drivers.errors import LimitError
        if self.refuse_at is not None and len(self.received) >= self.refuse_at:
            raise LimitError("axis x: 200 V is outside the device limits (test)")
        for a, v in volts.items():
            if abs(v - self.outputs[a]) > self.max_step_V:
                raise LimitError(f"axis {a}: step {self.outputs[a]} -> {v} exceeds max_step_V")
        super().set_voltages({a: round(v / self.resolution_V) * self.resolution_V for a, v in volts.items()})


def test_driver_step_limit_is_respected_so_the_driver_never_refuses():
    """A driver with its own max_step_V (amplifier.options) below slew · dt refused steps
    the safety layer allowed, and the run went fault → reconnect → fault for ever."""
    cfg = _cfg(rate=1000.0, slew=5000.0)
    amp = StepCheckingAmplifier(max_step_V=0.5)
    ctl = Controller(cfg, amp)
    assert ctl.safety.max_step_V < 0.5
    gain = cfg.scanner.axis_spec("x").nm_per_V
    traj = np.column_stack([np.linspace(0, 100 * gain, 300), np.zeros(300), np.zeros(300)])
    ctl.start(traj)
    assert ctl.wait(20)
    ctl.close()
    st = ctl.stats()
    assert st["faults"] == 0 and st["errors"] == 0 and ctl.state is State.STOPPED
    assert amp.outputs["x"] == pytest.approx(0.0)   # ramped back to the safe value


def test_a_refused_setpoint_ends_the_run_without_reconnecting():
    cfg = _cfg(rate=2000.0)
    amp = StepCheckingAmplifier(max_step_V=100.0, refuse_at=50)
    ctl = Controller(cfg, amp)
    ctl.start(np.zeros((2000, 3)))
    assert ctl.wait(5)
    ctl.close()
    assert ctl.state is State.FAULT and amp.reconnects == 0
    st = ctl.stats()
    assert st["errors"] == 1 and st["reconnects"] == 0 and "outside the device limits" in st["last_error"]
    assert len(amp.received) == 50
