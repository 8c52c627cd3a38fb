"""A run log that cannot be written stops the run safely: the output ramps to the safe value
within the slew limit, the status says why, ``afmctl run`` exits 3, and every record
written before the error is kept and readable."""
from __future__ import annotations

import errno
import shutil
import threading
import time

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.config import load_config
from afmctl.control.controller import Controller, State
from afmctl.control.runlog import RunLogReader, RunLogWriter
from afmctl.simulation.link import RecordingAmplifier
from afmctl.testing import wait_until

RATE_HZ, SLEW_V_PER_S = 2000.0, 2000.0


def _cfg(runlog_dir) -> object:
    return load_config(text=f"""
[simulation]
enabled = true
[loop]
rate_Hz = {RATE_HZ}
[runlog]
dir = "{runlog_dir}"
flush_interval_s = 0.01
fsync = false
[safety]
slew_V_per_s = {SLEW_V_PER_S}
ramp_V_per_s = 1000
watchdog_s = 5
on_finish = "hold"
[trajectory]
kind = "queue"
""")


class DiskFull:
    """The run log's real file object, failing like a full disk from the next write on: the
    kernel takes part of the chunk, then ENOSPC."""

    def __init__(self, real) -> None:
        self.real = real

    def write(self, data) -> int:
        view = memoryview(data)
        if len(view) > 1:
            self.real.write(view[:len(view) // 2])   # a torn chunk on the disk
        raise OSError(errno.ENOSPC, "No space left on device")

    def __getattr__(self, name):
        return getattr(self.real, name)


class Statuses:
    def __init__(self) -> None:
        self.events: list[dict] = []

    def on_status(self, st: dict) -> None:
        self.events.append(st)


def _started(tmp_path, runlog_dir):
    """A controller at 100/50/20 V (held: queue mode, long watchdog) with its log going."""
    cfg = _cfg(runlog_dir)
    amp = RecordingAmplifier(check_step_V=SLEW_V_PER_S / RATE_HZ)
    ctl = Controller(cfg, amp)
    sink = Statuses()
    ctl.add_sink(sink)
    gain = cfg.scanner.axis_spec("x").nm_per_V
    ctl.submit_segment(np.tile([100.0 * gain, 50.0 * gain, 20.0 * gain], (4000, 1)), cfg.dt_s)
    ctl.start(cfg.trajectory, runlog_path=runlog_dir / "run.afmlog")
    wait_until(lambda: amp.outputs["x"] > 99.99)
    at_100 = ctl.stats()["samples"]     # records from here on were sent at 100 V
    wait_until(lambda: ctl.runlog.flushed > max(300, at_100 + 10))
    return ctl, amp, sink


def _check_stopped_safely(ctl, amp, sink, what: str) -> np.ndarray:
    assert ctl.wait(10)
    ctl.close()
    assert ctl.state is State.STOPPED
    assert amp.violations == []                         # every step within the slew limit
    assert amp.outputs == {"x": 0.0, "y": 0.0, "z": 0.0}   # ramped to the safe value despite on_finish = "hold"
    assert what in ctl.runlog_error and what in ctl.stats()["last_error"]
    st = [s for s in sink.events if s["event"] == "runlog-error"]
    assert st and what in st[0]["detail"] and st[0]["stats"]["runlog_error"] == ctl.runlog_error
    assert any(s["event"] == "safe-stop" for s in sink.events)
    return amp.as_array()


def _check_records_kept(path, flushed_before: int) -> RunLogReader:
    r = RunLogReader(path)
    sp = r.setpoints()
    assert len(sp) >= flushed_before
    np.testing.assert_array_equal(sp["seq"], np.arange(len(sp)))    # every record, no gap
    assert not r.torn and not r.complete                           # cut at a whole chunk; no end record
    assert r.events()[0]["event"] == "start"
    return r


def test_disk_full_stops_the_run_and_keeps_the_records(tmp_path):
    ctl, amp, sink = _started(tmp_path, tmp_path)
    w = ctl.runlog
    flushed = w.flushed
    w._f = DiskFull(w._f)
    _check_stopped_safely(ctl, amp, sink, "No space left on device")
    r = _check_records_kept(tmp_path / "run.afmlog", flushed)
    assert r.setpoints()["u_V"][-1, 0] == pytest.approx(100.0)      # written while still at 100 V


def test_vanished_directory_stops_the_run_and_copies_the_records_back(tmp_path):
    d = tmp_path / "runs" / "today"
    ctl, amp, sink = _started(tmp_path, d)
    flushed = ctl.runlog.flushed
    shutil.rmtree(tmp_path / "runs")
    _check_stopped_safely(ctl, amp, sink, "vanished")
    assert "copied back" in ctl.runlog_error
    _check_records_kept(d / "run.afmlog", flushed)


def test_writer_drops_records_after_an_error_and_never_writes_an_end_record(tmp_path):
    p = tmp_path / "w.afmlog"
    w = RunLogWriter(p, {"scanner": "s"}, flush_interval_s=0.01, fsync=False)
    header_bytes = p.stat().st_size
    w.write_event({"event": "start", "state": "running"})
    wait_until(lambda: p.stat().st_size > header_bytes)
    w._f = DiskFull(w._f)
    w.write_event({"event": "lost", "state": "running"})
    wait_until(lambda: w.error is not None)
    assert "write failed" in str(w.error) and str(p) in str(w.error)
    w.write_event({"event": "after", "state": "running"})
    w.close()
    r = RunLogReader(p)
    assert [e["event"] for e in r.events()] == ["start"] and not r.torn and not r.complete


def test_cleanly_closed_log_is_complete(tmp_path):
    p = tmp_path / "c.afmlog"
    with RunLogWriter(p, {}, fsync=False) as w:
        w.write_event({"event": "start", "state": "running"})
    r = RunLogReader(p)
    assert r.complete and r.closed and r.summary()["complete"]


CLI_CFG = """
[scanner]
name = "sim0"
[amplifier]
driver = "can"
port = "virtual:afmctl-runlog-err-{tag}"
[loop]
rate_Hz = 1000
[safety]
slew_V_per_s = 2000.0
ramp_V_per_s = 500.0
[trajectory]
kind = "raster"
x0_nm = 1000.0
y0_nm = 1000.0
width_nm = 4000.0
height_nm = 4000.0
lines = 200
line_rate_Hz = 2.0
[runlog]
dir = "{dir}"
flush_interval_s = 0.02
[simulation]
enabled = true
"""


def test_afmctl_run_exits_3_when_the_run_log_directory_vanishes(tmp_path, capsys):
    runs = tmp_path / "runs"
    cfg = tmp_path / "c.toml"
    cfg.write_text(CLI_CFG.format(tag=id(tmp_path), dir=runs))

    def remove_when_logging() -> None:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 30:
            logs = list(runs.glob("*.afmlog")) if runs.exists() else []
            if logs and logs[0].stat().st_size > 20000:
                shutil.rmtree(runs)
                return
            time.sleep(0.02)

    t = threading.Thread(target=remove_when_logging)
    t.start()
    rc = main(["run", "--config", str(cfg), "--json", "--quiet"])
    t.join()
    err = capsys.readouterr().err
    assert rc == 3, err
    # the provenance line that every run prints at its start, then the error as one line
    lines = [ln for ln in err.splitlines()    # what the run says at start, then the error
             if not ln.startswith(("afmctl: compensation ", "afmctl: warning: loop.rate_Hz"))]
    assert len(lines) == 1 and "vanished" in lines[0] and "safe value" in lines[0], err
    logs = list(runs.glob("*.afmlog"))
    assert len(logs) == 1
    assert main(["log", "show", str(logs[0])]) == 0
    out = capsys.readouterr().out
    assert "integrity INCOMPLETE" in out and "samples" in out
