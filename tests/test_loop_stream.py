"""``[amplifier] output = "stream"``: the Controller as a producer for the buffered CAN
stream (issue #12 item 4). Real parts: our CAN driver and the simulated amplifier on
python-can's ``virtual`` bus; the Controller with its pipeline, safety layer and run log."""
from __future__ import annotations


import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from afmctl.errors import AfmctlError
from afmctl.control.controller import Controller, State
from afmctl.control.runlog import RunLogReader
from afmctl.testing import HostStalls, assert_no_threads_left, can_rig, make_config, wait_until

RATE_HZ = 1000.0
SLEW_V_PER_S = 2000.0     # 2 V per sample at 1 kHz
NM_PER_V = 50.0


@pytest.fixture(autouse=True)
def no_leaked_threads():
    yield
    assert_no_threads_left("afmctl-")


@pytest.fixture
def rig():
    with can_rig("lstream") as parts:
        yield parts


def cfg_for(tmp_path, channel, **amplifier):
    cal = {a: {"nm_per_V": NM_PER_V} for a in "xyz"}
    return make_config(tmp_path, "", loop={"rate_Hz": RATE_HZ},
                       scanner={"calibration": cal},
                       amplifier={"driver": "can", "port": f"virtual:{channel}", "output": "stream",
                                  "slew_V_per_s": SLEW_V_PER_S, "low_water_s": 0.1, "high_water_s": 0.2,
                                  **amplifier},
                       safety={"slew_V_per_s": SLEW_V_PER_S, "ramp_V_per_s": 1000.0, "watchdog_s": 0.2})


def scan_nm(n: int) -> np.ndarray:
    """x: 2 Hz sine 500..5500 nm (10..110 V, 628 V/s peak: inside the slew limit)."""
    t = np.arange(n) / RATE_HZ
    x = NM_PER_V * (60.0 + 50.0 * np.sin(2 * np.pi * 2.0 * t))
    return np.column_stack([x, np.full(n, 30.0 * NM_PER_V), np.full(n, 20.0 * NM_PER_V)])


def played(sim, sink):
    return [(t, v) for t, v in sink.history if t >= sim.stream.t0_s]


def test_host_stalls_do_not_reach_the_tip_through_the_controller(tmp_path, rig):
    """1 kHz, the producer stalled 20 ms once a second: zero underruns, every sample played
    exactly one period apart on the amplifier's clock, the run log holds every queued one."""
    channel, amp, sim, sink = rig
    cfg = cfg_for(tmp_path, channel)
    traj = scan_nm(3000)
    stall = HostStalls(stall_s=0.020, every_s=1.0)
    with Controller(cfg, amp) as ctl:
        ctl.stream_stall_hook = stall
        ctl.start(traj, runlog_path=tmp_path / "s.afmlog")
        assert ctl.wait(30)
        stats = ctl.stats()
    assert ctl.state is State.STOPPED, stats
    assert len(stall.times) >= 2
    assert stats["output"] == "stream" and stats["stream"]["underruns"] == 0 and sim.stream.underruns == 0
    assert stats["stream"]["lowest_level"] > 0
    sp = RunLogReader(tmp_path / "s.afmlog").setpoints()
    out = played(sim, sink)
    assert len(out) == len(sp) == stats["stream"]["queued"]      # every queued sample logged and played
    t0 = sim.stream.t0_s
    assert max(abs(t - (t0 + k / RATE_HZ)) for k, (t, _) in enumerate(out)) == 0.0   # zero jitter
    xs = np.array([v["x"] for _, v in out])
    np.testing.assert_allclose(xs, sp["u_V"][:, 0], atol=0.00125 + 1e-9)   # what was logged was played
    np.testing.assert_allclose(sp["t_s"], np.arange(len(sp)) / RATE_HZ)     # t_s: the amplifier's clock
    # the stream ends with the sample at which the finish ramp reaches the safe value (0 V)
    assert np.all(sp["u_V"][-1] == 0.0) and not np.all(sp["u_V"][-2] == 0.0)
    assert np.max(np.abs(np.diff(np.concatenate([[0.0], xs])))) <= SLEW_V_PER_S / RATE_HZ + 1e-9
    # the trajectory itself: linear calibration, so u = target / nm_per_V once the start ramp is done
    ev = {e["event"]: e["seq"] for e in RunLogReader(tmp_path / "s.afmlog").events()}
    seg = slice(ev["ramp-done"] + 1, ev["end"])
    np.testing.assert_allclose(sp["u_V"][seg, 0], sp["target_nm"][seg, 0] / NM_PER_V, atol=1e-9)


def test_estop_flushes_and_ramps_within_the_slew_limit_through_the_controller(tmp_path, rig):
    channel, amp, sim, sink = rig
    cfg = cfg_for(tmp_path, channel, low_water_s=0.03, high_water_s=0.06)
    n = 5000
    traj = scan_nm(n)
    traj[:, 0] = NM_PER_V * np.minimum(1.0 + np.arange(n) * 1.5, 110.0)   # climb to 110 V at 1.5 V/sample
    with Controller(cfg, amp) as ctl:
        ctl.start(traj, runlog_path=tmp_path / "e.afmlog")
        wait_until(lambda: sim.stream.played > 300, 10)
        ctl.estop()
        assert ctl.wait(20)
        stats = ctl.stats()
    assert stats["stream"]["estop_ramp_samples"] > 0
    events = [e["event"] for e in RunLogReader(tmp_path / "e.afmlog").events()]
    assert "estop" in events and "estop-flush" in events
    for a in "xyz":
        seq = np.array([0.0] + [v[a] for _, v in sink.history])
        assert np.max(np.abs(np.diff(seq))) <= SLEW_V_PER_S / RATE_HZ + 1e-9
    assert sink.last == {"x": 0.0, "y": 0.0, "z": 0.0}
    assert sim.stream.played < n


def test_stream_output_is_validated(tmp_path):
    with pytest.raises(AfmctlError, match="low_water_s 0.3 must be below high_water_s 0.2"):
        make_config(tmp_path, amplifier={"driver": "can", "output": "stream", "low_water_s": 0.3})
    with pytest.raises(AfmctlError, match="needs a link that buffers: driver 'can'"):
        make_config(tmp_path, amplifier={"driver": "mdt693b", "output": "stream"})
    with pytest.raises(AfmctlError, match="amplifier.output"):
        make_config(tmp_path, amplifier={"output": "tape"})


_odd = st.sampled_from([float("nan"), float("inf"), -float("inf"), 1e9, -1e9])


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.lists(st.tuples(*(st.one_of(st.floats(-2e4, 2e4), _odd),) * 3), min_size=1, max_size=60),
       nm_per_V=st.floats(1.0, 200.0), offset_V=st.floats(-300.0, 300.0))
def test_no_trajectory_or_model_makes_the_queued_stream_exceed_limits_or_slew(tmp_path, rig, rows, nm_per_V,
                                                                              offset_V):
    """Any target (NaN, inf and huge included: the run then ends safely) through any linear
    calibration: every played sample inside 0..120 V and within the slew limit of the one
    before, from the read-back on."""
    channel, amp, sim, sink = rig
    sink.history.clear()
    cal = {a: {"nm_per_V": nm_per_V, "offset_V": offset_V} for a in "xyz"}
    cfg = make_config(None, "", loop={"rate_Hz": RATE_HZ}, scanner={"calibration": cal},
                      amplifier={"driver": "can", "port": f"virtual:{channel}", "output": "stream",
                                 "slew_V_per_s": SLEW_V_PER_S, "low_water_s": 0.01, "high_water_s": 0.02,
                                 "limits_V": {a: {"min_V": 0.0, "max_V": 120.0} for a in "xyz"}},
                      safety={"slew_V_per_s": SLEW_V_PER_S, "ramp_V_per_s": 1000.0})
    traj = np.array(rows, dtype=float)
    prev = [v for v in amp.get_voltages().values()]
    with Controller(cfg, amp) as ctl:
        ctl.start(traj)
        assert ctl.wait(30)
    assert ctl.state is State.STOPPED
    for _, v in sink.history:
        row = [v["x"], v["y"], v["z"]]
        assert all(0.0 <= u <= 120.0 for u in row)
        assert all(abs(u - p) <= SLEW_V_PER_S / RATE_HZ + 1e-9 for u, p in zip(row, prev))
        prev = row


def _run_cli(tmp_path, output: str):
    import json
    import os
    import subprocess
    import sys
    (tmp_path / "run.toml").write_text(f"""
[amplifier]
driver = "can"
port = "virtual:afmctl-lstream-cli-{os.getpid()}-{output}"
slew_V_per_s = 5000
output = "{output}"
low_water_s = 0.05
high_water_s = 0.1
[loop]
rate_Hz = 1000
[simulation]
enabled = true
[runlog]
dir = "{tmp_path}"
fsync = false
[trajectory]
kind = "raster"
lines = 2
line_rate_Hz = 5.0
""")
    res = subprocess.run([sys.executable, "-m", "afmctl", "run", "--config", str(tmp_path / "run.toml"), "--json"],
                         capture_output=True, text=True, timeout=120)
    return res, (json.loads(res.stdout) if res.returncode == 0 else None)


def test_afmctl_run_streams_and_reports_the_fifo(tmp_path):
    res, summary = _run_cli(tmp_path, "stream")
    assert res.returncode == 0, res.stderr
    assert summary["output"] == "stream" and summary["stream"]["underruns"] == 0
    assert summary["stream"]["queued"] == summary["samples"] > 0


def test_afmctl_run_plays_a_wave_through_the_fifo(tmp_path):
    res, summary = _run_cli(tmp_path, "wave")
    assert res.returncode == 0, res.stderr
    assert summary["output"] == "wave" and summary["stream"]["underruns"] == 0
    assert summary["stream"]["queued"] > 0
