"""loop.cpu: the loop thread on a CPU of its own, the rest of afmctl on the others; the
dispatcher's quiet window in the loop period."""
from __future__ import annotations

import os

import pytest
from hypothesis import given
from hypothesis import strategies as st

from afmctl.config import load_config
from afmctl.control.cpu_pinning import plan
from afmctl.errors import AfmctlError
from afmctl.control.controller import Controller, quiet_window_wait_s
from afmctl.simulation.link import RecordingAmplifier
from afmctl.testing import make_config, wait_for

TWO = frozenset({0, 1})


def test_auto_pins_only_a_realtime_loop():
    p = plan("auto", TWO, realtime=False)
    assert p.loop_cpu is None and "realtime_priority" in p.why
    assert plan(1, TWO, realtime=False).loop_cpu == 1       # an explicit CPU: always


def test_auto_takes_the_highest_cpu_and_leaves_the_rest_to_the_others():
    p = plan("auto", frozenset({0, 1, 2, 3}))
    assert p.loop_cpu == 3 and p.others == frozenset({0, 1, 2}) and "CPU 3" in p.why
    assert plan(0, TWO).loop_cpu == 0 and plan(0, TWO).others == frozenset({1})


@pytest.mark.parametrize("setting, allowed, reason", [
    (None, TWO, "no CPU pinning"), ("none", TWO, "no CPU pinning"),
    ("auto", frozenset({5}), "one CPU available"), (7, TWO, "loop.cpu 7 is not one of"),
    ("auto", None, "not available on this OS")])
def test_no_pinning_says_why(setting, allowed, reason):
    p = plan(setting, allowed)
    assert p.loop_cpu is None and p.others is None and reason in p.why


@pytest.mark.parametrize("value", ["-1", "5000", '"fast"'])
def test_config_refuses_a_cpu_that_is_not_one(value):
    with pytest.raises(AfmctlError, match="loop.cpu") as err:
        load_config(text=f"[simulation]\nenabled = true\n[loop]\ncpu = {value}\n")
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("value, parsed", [('"auto"', "auto"), ('"none"', "none"), ("1", 1)])
def test_config_takes_auto_none_or_a_number(value, parsed):
    assert load_config(text=f"[simulation]\nenabled = true\n[loop]\ncpu = {value}\n").loop.cpu == parsed


@given(now=st.floats(0.0, 10.0), period=st.sampled_from([1e-3, 5e-4, 2e-3, 1e-2]),
       spin=st.sampled_from([0.0, 1e-4, 2e-4]))
def test_after_the_wait_a_helper_is_in_the_quiet_window(now, period, spin):
    deadline = 1.0
    wait = quiet_window_wait_s(now, deadline, period, spin)
    assert 0.0 <= wait < period
    if 0.75 * period - spin - 0.25 * period >= 1e-4:
        phase = (now + wait - deadline) % period
        assert 0.25 * period - 1e-9 <= phase <= 0.75 * period - spin + 1e-9


def test_no_window_when_the_loop_is_not_running_or_too_fast():
    assert quiet_window_wait_s(5.0, 0.0, 1e-3, 2e-4) == 0.0      # not running
    assert quiet_window_wait_s(5.00001, 5.0, 1e-4, 2e-4) == 0.0  # 10 kHz: no room


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs")
def test_the_loop_thread_runs_alone_on_its_cpu(tmp_path):
    cfg = make_config(tmp_path, trajectory={"kind": "queue"}, loop={"cpu": max(os.sched_getaffinity(0))})
    ctl = Controller(cfg, RecordingAmplifier())
    try:
        ctl.start(cfg.trajectory)
        loop_cpu = ctl.cpu_plan.loop_cpu
        assert loop_cpu == max(os.sched_getaffinity(0))
        assert wait_for(lambda: os.sched_getaffinity(ctl._thread.native_id) == {loop_cpu}, 5)
        assert wait_for(lambda: os.sched_getaffinity(ctl._dispatcher.native_id) == set(ctl.cpu_plan.others), 5)
    finally:
        ctl.stop()
        ctl.close()
