"""Run log: round trip, torn/corrupt tails, kill -9 during a run, `afmctl log show`."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmctl.cli import main
from afmctl.errors import AfmctlError
from afmctl.control.runlog import (DRIFT_DTYPE, KIND_EVENTS, KIND_SETPOINTS, SETPOINT_DTYPE, RunLogReader, RunLogWriter,
                           encode_chunk, encode_header)


def _sp(start: int, n: int) -> np.ndarray:
    a = np.zeros(n, SETPOINT_DTYPE)
    a["seq"] = np.arange(start, start + n)
    a["t_s"] = a["seq"] * 1e-3
    a["target_nm"] = np.arange(start, start + n)[:, None] * [1.0, 2.0, 3.0]
    a["corrected_nm"] = a["target_nm"] - 0.5
    a["u_V"] = a["target_nm"] / 66.7
    return a


def test_round_trip(tmp_path):
    path = tmp_path / "a.afmlog"
    with RunLogWriter(path, {"scanner": "s1"}, flush_interval_s=0.01, fsync=False) as w:
        w.write_event({"event": "start", "state": "running"})
        for k in range(5):
            w.write_setpoints(_sp(100 * k, 100))
            d = np.zeros(100, DRIFT_DTYPE)
            d["seq"] = np.arange(100 * k, 100 * k + 100)
            d["T_C"] = 22.5
            w.write_drift(d)
        w.write_event({"event": "stopped", "state": "stopped"})
    r = RunLogReader(path)
    assert not r.torn
    assert r.meta()["scanner"] == "s1"
    np.testing.assert_array_equal(r.setpoints(), _sp(0, 500))
    assert len(r.drift()) == 500 and np.all(r.drift()["T_C"] == 22.5)
    assert [e["event"] for e in r.events()] == ["start", "stopped"]
    s = r.summary()
    assert s["samples"] == 500 and s["seq_gaps"] == 0 and s["states"] == ["running", "stopped"]


def _log_bytes(n_chunks: int = 4, per: int = 50) -> tuple[bytes, set[int]]:
    """A log of setpoint and event chunks, and the offsets where whole chunks end."""
    out = encode_header({"scanner": "t"})
    ends = {len(out)}
    for k in range(n_chunks):
        out += encode_chunk(KIND_SETPOINTS, _sp(per * k, per).tobytes(), per)
        ends.add(len(out))
        out += encode_chunk(KIND_EVENTS, b'[{"event": "e%d"}]' % k, 1)
        ends.add(len(out))
    return out, ends


@settings(max_examples=150, deadline=None)
@given(cut=st.integers(0, 10**6), flip=st.booleans())
def test_reader_stops_at_first_torn_or_corrupt_chunk(tmp_path_factory, cut, flip):
    data, ends = _log_bytes()
    path = tmp_path_factory.mktemp("torn") / "t.afmlog"
    pos = cut % (len(data) + 1)
    if flip and pos < len(data):
        damaged = bytearray(data)
        damaged[pos] ^= 0xFF
        path.write_bytes(bytes(damaged))
    else:
        path.write_bytes(data[:pos])
    try:
        r = RunLogReader(path)
    except AfmctlError as err:  # the header itself is damaged or cut
        assert "header" in str(err) or "not an afmctl run log" in str(err)
        return
    got = r.setpoints()
    # a prefix of whole chunks, contiguous from seq 0, never a damaged record
    assert len(got) % 50 == 0
    np.testing.assert_array_equal(got, _sp(0, len(got)))
    if flip and pos < len(data):
        assert r.torn and r.valid_bytes <= pos          # stopped at the damaged chunk
    elif pos in ends:
        assert not r.torn and r.valid_bytes == pos       # cut between whole chunks
    else:
        assert r.torn and r.valid_bytes == max(e for e in ends if e <= pos)
    if pos == len(data):
        assert len(got) == 200 and len(r.events()) == 4


def test_not_a_runlog(tmp_path):
    p = tmp_path / "x.afmlog"
    p.write_bytes(b"hello")
    with pytest.raises(AfmctlError, match="not an afmctl run log"):
        RunLogReader(p)


KILL_CHILD = textwrap.dedent("""
    import sys, time
    import numpy as np
    from afmctl.config import load_config
    from afmctl.control.controller import Controller
    from afmctl.simulation.link import RecordingAmplifier
    cfg = load_config(text='''
    [simulation]
    enabled = true
    [loop]
    rate_Hz = 2000
    [runlog]
    flush_interval_s = 0.02
    fsync = false
    [trajectory]
    kind = "spiral"
    radius_nm = 3000
    speed_nm_per_s = 500
    ''')
    ctl = Controller(cfg, RecordingAmplifier())
    ctl.start(cfg.trajectory, runlog_path=sys.argv[1])
    while True:
        time.sleep(0.01)
        print(ctl.runlog.flushed, flush=True)
""")


def _kill_9_after_flushes(log_path, n_flushed: int) -> int:
    """Run KILL_CHILD writing ``log_path``, SIGKILL it once it reports ``n_flushed`` flushed
    setpoint records (or 30 s passed); return the last count it reported."""
    proc = subprocess.Popen([sys.executable, "-c", KILL_CHILD, str(log_path)], stdout=subprocess.PIPE, text=True)
    try:
        flushed = 0
        t0 = time.monotonic()
        while flushed < n_flushed and time.monotonic() - t0 < 30:
            line = proc.stdout.readline()
            if not line:
                break
            flushed = int(line)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
    assert flushed >= n_flushed, "child did not get going"
    return flushed


def test_kill_9_keeps_every_flushed_record(tmp_path):
    log_path = tmp_path / "killed.afmlog"
    flushed = _kill_9_after_flushes(log_path, 400)
    r = RunLogReader(log_path)
    sp = r.setpoints()
    assert len(sp) >= flushed
    np.testing.assert_array_equal(sp["seq"], np.arange(len(sp)))
    assert len(r.drift()) >= flushed
    assert r.events()[0]["event"] == "start"


def test_log_show_cli(tmp_path, capsys):
    path = tmp_path / "run.afmlog"
    with RunLogWriter(path, {"scanner": "s9", "rate_Hz": 1000}, fsync=False) as w:
        w.write_event({"seq": 0, "t_s": 0.0, "state": "running", "event": "start"})
        w.write_setpoints(_sp(0, 20))
        d = np.zeros(20, DRIFT_DTYPE)
        d["seq"] = np.arange(20)
        w.write_drift(d)
    csv = tmp_path / "out.csv"
    assert main(["log", "show", str(path), "--csv", str(csv), "--events"]) == 0
    out = capsys.readouterr().out
    assert "samples   20" in out and "s9" in out and "start" in out
    lines = csv.read_text().splitlines()
    assert lines[0].startswith("seq,t,x_target") and len(lines) == 21
    assert main(["log", "show", str(tmp_path / "missing")]) == 2
    assert "no run log" in capsys.readouterr().err


def test_well_formed_chunks_with_wrong_content_read_as_torn_prefix(tmp_path, capsys):
    """Chunks whose CRC is right but whose content no writer writes (events that are not a
    list of objects, a header that is not an object) stop the reader / give one-line errors."""
    import struct
    import zlib

    from afmctl.control.runlog import encode_chunk, encode_header
    good = encode_header({"scanner": "s"}) + encode_chunk(3, b'[{"event": "start", "state": "running"}]', 1)
    for bad in (b'{"event": "x"}', b"[1, 2, 3]", b'["a"]', b"[]"):
        p = tmp_path / "e.afmlog"
        p.write_bytes(good + encode_chunk(3, bad, 3) + encode_chunk(3, b'[{"event": "late"}]', 1))
        r = RunLogReader(p)
        assert r.torn and [e["event"] for e in r.events()] == ["start"]
        assert main(["log", "show", str(p), "--events"]) == 0
    body = b"[1, 2]"
    p = tmp_path / "h.afmlog"
    p.write_bytes(b"AFMLOG01" + struct.pack("<II", len(body), zlib.crc32(body)) + body)
    assert main(["log", "show", str(p)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "header must be a JSON object" in err


def test_killed_run_log_is_not_reported_complete(tmp_path, capsys):
    """kill -9 leaves whole chunks (not torn) but no end record: `afmctl log show` must not
    call that log complete."""
    log_path = tmp_path / "killed.afmlog"
    _kill_9_after_flushes(log_path, 200)
    r = RunLogReader(log_path)
    assert not r.closed and not r.complete and not r.summary()["complete"]
    assert main(["log", "show", str(log_path)]) == 0
    out = capsys.readouterr().out
    assert "integrity INCOMPLETE" in out and "integrity complete" not in out
