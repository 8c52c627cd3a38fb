"""The preview horizon (issues #11/#12 item 4): a pipeline whose inverse reads the target
L samples ahead (a chain with a dynamics stage) is fed the trajectory L samples ahead of
the output by the Controller; every axis lags by the same, reported latency."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from afmctl.compensators.chain import ChainModel
from afmctl.control.controller import Controller, State
from afmctl.control.pipeline import LinearAxis, build_pipeline
from afmctl.control.preview import DelayLine, Delayed, equalise_latency
from afmctl.control.runlog import RunLogReader
from afmctl.simulation.link import RecordingAmplifier
from afmctl.testing import assert_no_threads_left, make_config, wait_until

RATE_HZ = 2000.0


@pytest.fixture(autouse=True)
def no_leaked_threads():
    yield
    assert_no_threads_left("afmctl-")


def cfg_for(tmp_path, chain_file, **loop):
    return make_config(tmp_path, f'[compensation.x]\nmodel = "{chain_file}"\n',
                       loop={"rate_Hz": RATE_HZ, **loop},
                       safety={"slew_V_per_s": 1e5, "ramp_V_per_s": 2000, "watchdog_s": 0.05})


def smooth_x(n: int) -> np.ndarray:
    """x: a raised-cosine move 1000 → 3000 nm; y, z fixed [nm]."""
    s = 0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, n))
    return np.column_stack([1000.0 + 2000.0 * s, np.full(n, 500.0), np.full(n, 40.0)])


def test_controller_reads_ahead_by_the_pipelines_latency(tmp_path, chain_file):
    """The voltages sent are the pipeline's step() outputs for the trajectory read L samples
    ahead (the first sample fed L extra times, the last one L extra times after the end),
    and each is logged beside the target it aims at."""
    cfg = cfg_for(tmp_path, chain_file)
    traj = smooth_x(400)
    ref_pipe = build_pipeline(cfg)
    L = ref_pipe.latency_samples
    assert L > 0
    feed = np.concatenate([np.repeat(traj[:1], L, 0), traj, np.repeat(traj[-1:], L, 0)])
    _, _, u_ref = ref_pipe.run(feed, cfg.compensation.temperature.T_C)
    amp = RecordingAmplifier(check_step_V=cfg.slew_V_per_s() * cfg.dt_s)
    with Controller(cfg, amp) as ctl:
        assert ctl.latency_samples == L and ctl.latency_s == pytest.approx(L / RATE_HZ)
        ctl.start(traj, runlog_path=tmp_path / "r.afmlog")
        assert ctl.wait(20)
        st = ctl.stats()
    assert ctl.state is State.STOPPED and amp.violations == []
    assert st["latency_samples"] == L and st["latency_s"] == pytest.approx(L / RATE_HZ)
    log = RunLogReader(tmp_path / "r.afmlog")
    sp, ev = log.setpoints(), {e["event"]: e["seq"] for e in log.events()}
    ramp_end, end = ev["ramp-done"], ev["end"]
    assert end - ramp_end == len(traj) + L          # L outputs aim at the held start
    sent = amp.as_array()[ramp_end:end]
    differs = np.any(sent != u_ref[L:], axis=1)     # bit for bit, except slew-limited catch-ups
    assert int(differs.sum()) <= st["slew_limited"]
    np.testing.assert_array_equal(sp["target_nm"][ramp_end:end], feed[:len(traj) + L])
    np.testing.assert_array_equal(sp["target_nm"][end - len(traj):end], traj)


def test_status_carries_latency_and_queue_pause_drains_the_preview(tmp_path, chain_file):
    """Live segments (queue mode): when they pause, the last L outputs are still emitted (the
    target holds), so the output reaches the latest target; every status has latency_s."""
    cfg = cfg_for(tmp_path, chain_file)
    statuses = []

    class Sink:
        def on_status(self, s):
            statuses.append(s)

    amp = RecordingAmplifier()
    with Controller(cfg, amp) as ctl:
        ctl.add_sink(Sink())
        L = ctl.latency_samples
        ctl.start(None, runlog_path=tmp_path / "q.afmlog")
        seg = smooth_x(200)
        ctl.submit_segment(seg, cfg.dt_s)
        wait_until(lambda: ctl.state is State.HOLDING, 10)
        n_after_first = ctl.stats()["samples"]
        ctl.submit_segment(seg[::-1], cfg.dt_s)
        wait_until(lambda: ctl.stats()["samples"] >= n_after_first + len(seg) + L, 10)
        ctl.stop()
        assert ctl.wait(10)
    sp = RunLogReader(tmp_path / "q.afmlog").setpoints()
    tgt = sp["target_nm"]
    i_last = int(np.flatnonzero(np.all(tgt == seg[-1], axis=1))[0])   # the first segment's end reached
    assert i_last < n_after_first
    assert np.all(tgt[i_last:n_after_first] == seg[-1])
    assert np.any(np.all(tgt == seg[0], axis=1)[n_after_first:])       # the second segment's end too
    assert statuses and all(s["stats"]["latency_s"] == pytest.approx(L / RATE_HZ) for s in statuses)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(0, 7), x=st.lists(st.floats(-1e4, 1e4), min_size=0, max_size=40),
       cut=st.integers(0, 40))
def test_delay_line_block_equals_step(n, x, cut):
    a, b = DelayLine(n, 1.5), DelayLine(n, 1.5)
    xs = np.asarray(x, dtype=np.float64)
    ys = np.array([a.step(float(v)) for v in xs])
    yb = np.concatenate([b.block(xs[:cut]), b.block(xs[cut:])])
    np.testing.assert_array_equal(ys, yb)
    np.testing.assert_array_equal(ys, np.concatenate([np.full(min(n, len(xs)), 1.5), xs])[:len(xs)])


def test_equalise_latency_pads_shorter_axes(chain_file):
    op = ChainModel.model_validate(json.loads(chain_file.read_text())).inverse(1.0 / RATE_HZ)
    lin = LinearAxis(50.0)
    ops, L = equalise_latency([op, lin, lin])
    assert L == op.latency_samples > 0 and ops[0] is op
    assert isinstance(ops[1], Delayed) and ops[1].latency_samples == L
    r = np.linspace(0.0, 100.0, 3 * L)
    np.testing.assert_array_equal(ops[1].block(r)[L:], lin.block(r)[:-L])
    assert equalise_latency([lin, lin, lin]) == ([lin, lin, lin], 0)


def test_run_prints_the_preview_latency(tmp_path, chain_file):
    """``afmctl run`` says at start how far ahead it reads, and its summary has latency_s."""
    (tmp_path / "run.toml").write_text(f"""
[amplifier]
driver = "can"
port = "virtual:afmctl-preview-{os.getpid()}"
[loop]
rate_Hz = {RATE_HZ}
[safety]
slew_V_per_s = 100000
ramp_V_per_s = 2000
[compensation.x]
model = "{chain_file}"
[simulation]
enabled = true
[runlog]
dir = "{tmp_path}"
fsync = false
[trajectory]
kind = "raster"
x0_nm = 1000.0
y0_nm = 1000.0
width_nm = 2000.0
height_nm = 200.0
lines = 2
line_rate_Hz = 10.0
""")
    res = subprocess.run([sys.executable, "-m", "afmctl", "run", "--config", str(tmp_path / "run.toml"), "--json"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    L = build_pipeline(make_config(None, f'[compensation.x]\nmodel = "{chain_file}"\n',
                                   loop={"rate_Hz": RATE_HZ})).latency_samples
    assert summary["latency_samples"] == L and summary["latency_s"] == pytest.approx(L / RATE_HZ)
    assert f"reads the trajectory {L} samples" in res.stderr


def test_stream_output_queues_the_same_read_ahead_samples(tmp_path, chain_file):
    """output = "stream": the samples queued into the CAN amplifier's FIFO are the same
    read-ahead pipeline outputs, logged beside the targets they aim at, all played."""
    import uuid

    from afmctl.drivers.can_amp import CANAmplifier
    from afmctl.sim_backend.amplifiers.base import RecordingSink
    from afmctl.sim_backend.testing import serve_can
    channel = f"pstream-{uuid.uuid4().hex[:8]}"
    cfg = make_config(tmp_path, f'[compensation.x]\nmodel = "{chain_file}"\n', loop={"rate_Hz": RATE_HZ},
                      amplifier={"driver": "can", "port": f"virtual:{channel}", "output": "stream",
                                 "slew_V_per_s": 1e5, "low_water_s": 0.05, "high_water_s": 0.1},
                      safety={"slew_V_per_s": 1e5, "ramp_V_per_s": 2000, "watchdog_s": 0.05})
    traj = smooth_x(400)
    ref_pipe = build_pipeline(cfg)
    L = ref_pipe.latency_samples
    feed = np.concatenate([np.repeat(traj[:1], L, 0), traj, np.repeat(traj[-1:], L, 0)])
    _, _, u_ref = ref_pipe.run(feed, cfg.compensation.temperature.T_C)
    sink = RecordingSink(max_history=100_000)
    with serve_can(channel, sink, record_seq=True) as sim:
        amp = CANAmplifier.open(f"virtual:{channel}")
        amp.connect()
        try:
            with Controller(cfg, amp) as ctl:
                ctl.start(traj, runlog_path=tmp_path / "ps.afmlog")
                assert ctl.wait(20)
                st = ctl.stats()
        finally:
            amp.close()
    assert ctl.state is State.STOPPED and st["latency_samples"] == L and st["stream"]["underruns"] == 0
    log = RunLogReader(tmp_path / "ps.afmlog")
    sp, ev = log.setpoints(), {e["event"]: e["seq"] for e in log.events()}
    ramp_end, end = ev["ramp-done"], ev["end"]
    assert end - ramp_end == len(traj) + L
    np.testing.assert_array_equal(sp["u_V"][ramp_end:end], u_ref[L:])     # bit for bit (no limiting needed)
    np.testing.assert_array_equal(sp["target_nm"][end - len(traj):end], traj)
    assert len(sim.stream_log) == len(sp) == st["stream"]["queued"]
    np.testing.assert_allclose(np.array(sim.stream_log)[:, 0], sp["u_V"][:, 0], atol=0.00125 + 1e-9)
