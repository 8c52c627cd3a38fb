"""A stop ends the run from every phase of the setpoint loop, within the bound stated in
docs/CONTROLLER.md ("Stop bound"): one loop period + the finish ramp (distance to the safe
value / ``safety.ramp_V_per_s``; none in a fault, where nothing can be sent) + one driver call.
Each test drives the real controller (RecordingAmplifier, which checks every value it gets)
into one phase of afmctl.control.transitions, stops it there and checks the transition the
loop took and where it ended. Waits carry SLACK_S on top of the bound for a loaded 2-core
machine: they check that the run ends, not how fast (timing figures are benchmarks')."""
from __future__ import annotations

import math
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from afmctl.control.controller import Controller, State
from afmctl.control.transitions import Event, Phase
from afmctl.simulation.link import RecordingAmplifier
from afmctl.testing import make_config, wait_until

RATE_HZ = 1000.0
RAMP_V_PER_S = 200.0
SLEW_V_PER_S = 2000.0
SLACK_S = 2.0           # on top of the stated bound: a loaded machine, never a timing figure


pytestmark = pytest.mark.usefixtures("no_leaked_threads")   # tests/conftest.py


def cfg_for(tmp_path, **safety):
    return make_config(tmp_path, "", loop={"rate_Hz": RATE_HZ},
                       safety={"slew_V_per_s": SLEW_V_PER_S, "ramp_V_per_s": RAMP_V_PER_S, "watchdog_s": 0.05,
                               "reconnect_interval_s": 0.01, **safety})


def stop_bound_s(ctl: Controller, request: str = "stop") -> float:
    """The stated bound [s] until ``wait()`` returns: one period + the finish ramp from the
    present output + one driver call (RecordingAmplifier: immediate) + the dispatcher's last
    pass (``dispatch_interval_s``)."""
    s = ctl.safety
    dist = max(abs(v - safe) for v, safe in zip(s.last, s.safe))
    rate = s.slew_V_per_s if request == "estop" else min(ctl.config.safety.ramp_V_per_s, s.slew_V_per_s)
    return ctl.dt_s + dist / rate + ctl.dispatch_interval_s


class BlockingAmplifier(RecordingAmplifier):
    """get_voltages (``block_readback``) or reconnect (``block_reconnect``) blocks until
    :attr:`release` is set, as a serial driver's does up to its timeout."""

    def __init__(self, block_readback=False, block_reconnect=False, **kw):
        super().__init__(**kw)
        self.block_readback, self.block_reconnect = block_readback, block_reconnect
        self.release, self.blocked = threading.Event(), threading.Event()

    def get_voltages(self):
        if self.block_readback:
            self.blocked.set()
            self.release.wait(5.0)
        return super().get_voltages()

    def reconnect(self):
        if self.block_reconnect:
            self.blocked.set()
            self.release.wait(5.0)
        super().reconnect()


def _stop_in(ctl, amp, phase: Phase, request: str = "stop") -> None:
    """Wait for ``phase``, stop there; the run ends within the bound in STOPPED or FAULT and
    the loop's trail holds the transition the table gives."""
    wait_until(lambda: ctl._fsm is not None and ctl._fsm.phase is phase, 10.0, what=f"phase {phase.value}")
    bound = stop_bound_s(ctl, request)
    getattr(ctl, request)()
    ended = ctl.wait(bound + SLACK_S)
    amp_release = getattr(amp, "release", None)
    if amp_release is not None:
        amp_release.set()
    ctl.close()
    assert ended, f"{request} in {phase.value} did not end the run within {bound:.3f} + {SLACK_S} s"
    ev = Event.ESTOP if request == "estop" else Event.STOP
    taken = [t for t in ctl._fsm.trail if t[1] is ev]
    assert taken and taken[0][0] is phase, list(ctl._fsm.trail)
    assert taken[0][2] is ctl._fsm.table[(phase, ev)]
    assert ctl._fsm.phase in (Phase.STOPPED, Phase.FAULT)
    assert ctl.state.value == ctl._fsm.phase.value
    assert amp.violations == []


@pytest.mark.parametrize("req", ["stop", "estop"])
def test_stop_in_ramp_run_and_finish(tmp_path, req):
    g = 50.0      # nm/V of the default calibration
    for phase in (Phase.RAMP, Phase.RUN, Phase.FINISH):
        cfg = cfg_for(tmp_path)
        g = cfg.scanner.axis_spec("x").nm_per_V
        amp = RecordingAmplifier(check_step_V=SLEW_V_PER_S / RATE_HZ)
        ctl = Controller(cfg, amp)
        n = 200 if phase is Phase.FINISH else 20000     # FINISH: the trajectory's end starts the ramp to safe
        traj = np.column_stack([np.full(n, 60.0 * g), np.full(n, 10.0 * g), np.zeros(n)])
        ctl.start(traj)
        _stop_in(ctl, amp, phase, req)


def test_stop_in_settle(tmp_path):
    """The trajectory's last sample jumps further than the slew limit lets one tick go: the
    loop settles on it (SETTLE) at 20 V/s; a stop there ramps to the safe value."""
    cfg = cfg_for(tmp_path, slew_V_per_s=20.0)
    g = cfg.scanner.axis_spec("x").nm_per_V
    amp = RecordingAmplifier(check_step_V=20.0 / RATE_HZ)
    ctl = Controller(cfg, amp)
    traj = np.zeros((50, 3))
    traj[-1, 0] = 100.0 * g
    ctl.start(traj)
    _stop_in(ctl, amp, Phase.SETTLE)


def test_stop_in_hold(tmp_path):
    cfg = cfg_for(tmp_path)
    amp = RecordingAmplifier()
    ctl = Controller(cfg, amp)
    ctl.start(None)      # queue mode with nothing queued: the watchdog trips
    _stop_in(ctl, amp, Phase.HOLD)


@pytest.mark.parametrize("req", ["stop", "estop"])
def test_stop_in_retry_and_reconnect(tmp_path, req):
    """Link down, waiting between attempts (RETRY: 30 s interval), or an attempt blocked in
    the driver (RECONNECT): the request ends the run at the next tick (stop-in-fault)."""
    for phase in (Phase.RETRY, Phase.RECONNECT):
        cfg = cfg_for(tmp_path, reconnect_interval_s=30.0 if phase is Phase.RETRY else 0.01)
        amp = BlockingAmplifier(block_reconnect=True)
        amp.fail_after = 20
        ctl = Controller(cfg, amp)
        ctl.start(np.zeros((20000, 3)))
        _stop_in(ctl, amp, phase, req)
        assert ctl.state is State.STOPPED and len(amp.received) == 20


def test_stop_during_the_start_read_back(tmp_path):
    """The read-back blocks in the driver (SYNC): the stop is taken at the first tick after
    it, from RAMP (nothing has been sent)."""
    cfg = cfg_for(tmp_path)
    amp = BlockingAmplifier(block_readback=True)
    ctl = Controller(cfg, amp)
    ctl.start(np.zeros((20000, 3)))
    assert amp.blocked.wait(10)
    assert ctl._fsm.phase is Phase.SYNC
    ctl.stop()
    amp.block_readback = False
    amp.release.set()
    assert ctl.wait(stop_bound_s(ctl) + SLACK_S)
    ctl.close()
    assert ctl._fsm.phase is Phase.STOPPED and ctl.state is State.STOPPED
    assert [t[:2] for t in ctl._fsm.trail][:2] == [(Phase.SYNC, Event.READBACK_IN), (Phase.RAMP, Event.STOP)]


# ---------------------------------------------------------------- issue #22's example
ISSUE_22_EXAMPLE = dict(
    traj=[(359639.80, -428925.33, 0.0), (0, 0, 0), (0, 0, 0), (355369.60, 0, 0), (0, 0, 0), (0, 0, 0),
          (0, 766971.43, -18990.46)],
    start_V=-1.7e-186, moved_V=141.05, fail_at=140, bad_reconnects=0, action_at=150, action="stop",
    action_in_fault=False, lo=43.0336, span=110.511)


def _fuzz_inner():
    sys.path.insert(0, str(Path(__file__).parent))
    import test_safety
    return test_safety, test_safety.test_faults_reconnects_stops_and_readbacks_never_make_an_unsafe_step


def test_issue_22_example_ends_at_once_refusing_the_read_back(monkeypatch):
    """x limits 43.03..150 V, the amplifier at 0 V: the run is refused at the start (one line
    naming the axis and the limits, FAULT, nothing sent) and a stop() afterwards finds the run
    over within one second. Before, the controller resumed into a finished trajectory and held
    for ever (``ctl.wait(20)`` False)."""
    test_safety, fuzz = _fuzz_inner()
    made: list[Controller] = []
    real_init = Controller.__init__

    def recording_init(self, *a, **kw):
        real_init(self, *a, **kw)
        made.append(self)

    monkeypatch.setattr(Controller, "__init__", recording_init)
    fuzz.hypothesis.inner_test(**ISSUE_22_EXAMPLE)
    (ctl,) = made
    ctl.stop()
    assert ctl.wait(1.0)
    assert ctl.state is State.FAULT and ctl._fsm.phase is Phase.FAULT
    st = ctl.stats()
    assert st["last_error"] == ("axis x: read-back -1.7e-186 V is outside the limits [43.0336, 150] V; "
                                "not moving the output")
    assert list(ctl._fsm.trail) == [(Phase.SYNC, Event.READBACK_OUT, Phase.FAULT)]


def test_issue_22_example_inside_the_limits_resumes_into_settle_and_ends(monkeypatch):
    """The same run with the amplifier inside the limits at the start: the link goes after the
    trajectory's end (while settling on its last setpoint); after the reconnect the loop
    settles and finishes (it resumed into RUN before and held for ever)."""
    test_safety, fuzz = _fuzz_inner()
    made: list[Controller] = []
    real_init = Controller.__init__

    def recording_init(self, *a, **kw):
        real_init(self, *a, **kw)
        made.append(self)

    monkeypatch.setattr(Controller, "__init__", recording_init)
    fuzz.hypothesis.inner_test(**{**ISSUE_22_EXAMPLE, "start_V": 141.05})
    (ctl,) = made
    trail = [t[:2] for t in ctl._fsm.trail]
    assert (Phase.SETTLE, Event.FAULT) in trail and (Phase.RAMP, Event.TRAJECTORY_END) in trail
    assert ctl.state is State.STOPPED and ctl._fsm.phase is Phase.STOPPED
    assert ctl.stats()["reconnects"] == 1 and not math.isnan(ctl.safety.last[0])


def test_max_reconnects_ends_in_fault(tmp_path):
    cfg = cfg_for(tmp_path, max_reconnects=2, reconnect_interval_s=0.005)
    amp = RecordingAmplifier()
    amp.fail_after = 10
    ctl = Controller(cfg, amp)
    ctl.start(np.zeros((20000, 3)))
    assert ctl.wait(10.0)
    ctl.close()
    assert ctl.state is State.FAULT and ctl._fsm.phase is Phase.FAULT
    fired = [t[1] for t in ctl._fsm.trail]
    assert fired.count(Event.RECONNECT_FAILED) == 2 and fired[-1] is Event.RECONNECTS_EXHAUSTED
    time.sleep(0.01)


# ---------------------------------------------------------------- close() from every phase
def _running_in(tmp_path, phase: Phase):
    """A controller running and in ``phase`` (and its amplifier)."""
    slow_finish = phase is Phase.FINISH
    cfg = cfg_for(tmp_path, reconnect_interval_s=30.0 if phase is Phase.RETRY else 0.01,
                  ramp_V_per_s=5.0 if slow_finish else RAMP_V_PER_S)
    g = cfg.scanner.axis_spec("x").nm_per_V
    amp = BlockingAmplifier(block_reconnect=phase is Phase.RECONNECT,   # FINISH: no slow start ramp
                            initial_V={"x": 10.0 if slow_finish else 0.0, "y": 0.0, "z": 0.0})
    ctl = Controller(cfg, amp)
    if phase in (Phase.RETRY, Phase.RECONNECT):
        amp.fail_after = 20
    if phase is Phase.HOLD:
        ctl.start(None)
    else:
        n = 300 if slow_finish else 20000      # FINISH: 10 V to ramp down at 5 V/s after the end
        ctl.start(np.column_stack([np.full(n, 10.0 * g), np.zeros(n), np.zeros(n)]))
    wait_until(lambda: ctl._fsm is not None and ctl._fsm.phase is phase, 20.0, what=f"phase {phase.value}")
    return ctl, amp


@pytest.mark.parametrize("phase", [Phase.RAMP, Phase.RUN, Phase.HOLD, Phase.FINISH, Phase.RETRY, Phase.RECONNECT],
                         ids=lambda p: p.value)
def test_close_ends_every_thread_from_every_phase(tmp_path, phase):
    """close() without a stop first: the loop ends (a finish ramp slower than half the timeout
    is turned into an estop) and every thread of the controller is joined."""
    ctl, amp = _running_in(tmp_path, phase)
    if phase is Phase.RECONNECT:
        amp.release.set()           # the driver call returns (within its own timeout)
    assert ctl.close(timeout=1.0 if phase is Phase.FINISH else 10.0) == []
    assert not ctl.running and ctl._fsm.phase in (Phase.STOPPED, Phase.FAULT)
    assert amp.violations == []
    if phase is Phase.FINISH:       # escalated: the slow ramp was finished at the slew limit
        assert "estop" in [t[1].value for t in ctl._fsm.trail]


def test_close_reports_a_driver_call_that_does_not_return(tmp_path, caplog):
    """A reconnect blocked in the driver beyond close()'s timeout: the loop and dispatcher
    end, close() names the reconnect thread it could not join (and logs it); once the
    driver returns, the thread ends."""
    ctl, amp = _running_in(tmp_path, Phase.RECONNECT)
    left = ctl.close(timeout=0.3)
    assert left == ["afmctl-reconnect"]
    assert "afmctl-reconnect" in caplog.text and not ctl.running
    amp.release.set()
    wait_until(lambda: not ctl._rc_thread.is_alive(), 5.0)
