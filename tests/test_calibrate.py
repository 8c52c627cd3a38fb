"""``afmctl calibrate`` (issue 38): the excitation cut into pieces a recorder holds and joined
with the holds between them (plain arrays); Ctrl-C on each device — the E-727 over TCP, the NV200 on a pty, the CAN amplifier on the
virtual bus — ends the command with the output at the safe value and nothing playing; a
``stop`` on zenoh does the same; a lost link exits 1 and keeps the partial recording; a device
whose recorder cannot hold the shortest piece is refused in one line before anything moves.
A whole calibration (a model with its provenance, the recording with the piezo voltage) is
the README's instrument tour (tests/test_doc_blocks.py). Excitations are short (the full-size figures
are benchmarks/calibrate_join.py)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from afmctl.control.calibrate_pieces import (CUT_IN_HOLD, NO_CUT, PieceRecord, cut_points, excitation_all,
                                             follow_table, join, plan_pieces, ramp_priorities)
from afmctl.data.excitation import ExcitationSpec, excitation
from afmctl.errors import AfmctlError

SHORT = dict(dwell_s=0.3, gap_s=0.1, periods=2, f_min_Hz=50.0, sweep_V_per_s=600.0)


def test_the_excitation_is_what_afmctl_excite_writes_and_its_multisine_is_never_cut_inside_a_period():
    spec = ExcitationSpec(u_min_V=0.0, u_max_V=120.0, rate_Hz=10_000.0, slew_V_per_s=1e4, **SHORT)
    exc = excitation_all(spec)
    np.testing.assert_array_equal(exc.u_V, excitation("all", spec))
    bounds = cut_points(exc.priority, 3 * exc.period)
    assert bounds[0][0] == 0 and bounds[-1][1] == len(exc.u_V)
    assert all(b0 == a1 for (_, b0), (a1, _) in zip(bounds[:-1], bounds[1:]))
    assert all(b - a <= 3 * exc.period for a, b in bounds)
    inside = np.flatnonzero(exc.priority == NO_CUT)
    assert len(inside) > 2 * exc.period
    assert not any(b - 1 in set(inside.tolist()) for _, b in bounds[:-1])   # every cut after a cuttable sample


def test_cuts_prefer_holds_and_a_device_too_small_for_one_period_is_refused_in_one_line():
    u = np.concatenate([np.linspace(0, 10, 50), np.full(20, 10.0), np.linspace(10, 0, 50)])
    prio = ramp_priorities(u)
    (a, b), _ = cut_points(prio, 80)[:2]
    assert prio[b - 1] == CUT_IN_HOLD and 50 <= b <= 70
    spec = ExcitationSpec(u_min_V=0.0, u_max_V=120.0, rate_Hz=10_000.0, **SHORT)
    exc = excitation_all(spec)
    with pytest.raises(AfmctlError) as err:
        plan_pieces(exc, "x", exc.period - 1, "nv200")
    assert "\n" not in str(err.value) and "nothing was moved" in str(err.value)


def test_join_puts_the_holds_back_at_the_held_voltage():
    dt = 1e-3
    p1 = PieceRecord(0, np.array([0.0, 1.0, 2.0]), np.array([0.0, 10.0, 20.0]), np.array([0.0, 1.0, 2.0]), 10.0)
    p2 = PieceRecord(3, np.array([2.0, 1.0]), np.array([25.0, 15.0]), np.array([2.0, 1.0]), 10.0 + 3 * dt + 4 * dt)
    j = join([p1, p2], dt)
    np.testing.assert_array_equal(j.u_V, [0, 1, 2, 2, 2, 2, 2, 2, 1])
    np.testing.assert_array_equal(j.measured, [1, 1, 1, 0, 0, 0, 0, 1, 1])
    np.testing.assert_allclose(j.y_nm[3:7], [21, 22, 23, 24])
    assert j.holds == [(3, 4)] and list(j.columns()) == ["t", "u", "y", "v", "measured"]
    assert j.held_share == pytest.approx(4 / 9)                   # what the summary reports
    assert len(join([p1, p2], dt, with_holds=False).u_V) == 5


def test_a_streamed_piece_keeps_the_holds_of_an_empty_fifo_and_ends_at_the_tables_last_row():
    table = np.array([1.0, 2.0, 2.0, 3.0, 4.0])
    played = np.array([1.0, 2.0, 2.0, 2.0, 2.0, 3.0, 3.0, 4.0, 4.0, 4.0])     # two underruns, then the FIFO ran dry
    assert follow_table(played, table, 0.01) == 8
    assert follow_table(table, table, 0.01) == 5
    with pytest.raises(ValueError, match="left the table at recorded sample 2"):
        follow_table(np.array([1.0, 2.0, 5.0]), table, 0.01)
    with pytest.raises(ValueError, match="ended after row 3 of 5"):
        follow_table(np.array([1.0, 2.0, 2.0, 2.0]), table, 0.01)


@pytest.mark.slow
def test_a_streamed_piece_is_read_back_while_it_plays_and_only_to_its_last_row():
    """On the CAN amplifier (CAN FD, the recorder read while it records): the points come
    back in chunks as the stream plays; once the FIFO has drained, the read-back ends at the
    table's last row (its rows plus the underruns, and a few points), not at the armed
    points the recorder keeps filling with the held output."""
    from afmctl.control.calibrate_run import STREAM_TAIL, LiveReadback
    from afmctl.drivers.registry import open_amplifier
    from afmctl.sim_backend.testing import serve_can
    n, armed = 3000, 4000
    table = 20.0 + 60.0 * np.sin(np.linspace(0.0, np.pi, n))
    channel = f"live-{uuid.uuid4().hex[:8]}"
    with serve_can(channel, _scanner()):
        with open_amplifier("can", f"virtual:{channel}", fd=True) as amp:
            amp.set_voltages({"x": float(table[0]), "y": 0.0, "z": 0.0})
            amp.start_stream(10_000, prefill=n)
            amp.configure_recorder(["x"], points=armed, signals=("y_nm", "u_V", "v_V"))
            live = LiveReadback(amp, armed, chunk=500)
            amp.queue([(float(v), 0.0, 0.0) for v in table])
            t_start = time.monotonic()
            amp.drain_stream()
            deadline = t_start + 30.0
            while amp.buffer_status().state != "idle" and time.monotonic() < deadline:
                live.step(t_start, 10_000.0)
                time.sleep(0.005)
            assert live.got > 0                                   # read while it played
            underruns = amp.latest_buffer_status().underruns
            live.points = min(live.points, n + underruns + STREAM_TAIL)
            rec = live.rest(10.0, lambda: False)
    assert len(rec) == n + underruns + STREAM_TAIL < armed
    assert follow_table(rec.u_V["x"], table, 0.0013) == n + underruns
    np.testing.assert_allclose(rec.t_s, np.arange(len(rec)) * 1e-4)


@pytest.mark.slow
def test_a_ring_takes_pieces_longer_than_the_recorder_only_on_a_can_fd_bus():
    """Classic frames bring a point back at 0.3–0.4× the play: pieces fit the recorder there
    (75 % of 8192); on CAN FD they span two rings."""
    from afmctl.control import calibrate_run as cr
    from afmctl.drivers.registry import open_amplifier
    from afmctl.sim_backend.testing import serve_can
    channel = f"rings-{uuid.uuid4().hex[:8]}"
    with serve_can(channel, _scanner()):
        rows = {}
        for fd in (False, True):
            with open_amplifier("can", f"virtual:{channel}", fd=fd) as amp:
                signals = cr.recorder_signals(amp, "x")
                rows[fd] = (cr.rings(amp), cr.device_capacity(amp, "x", signals))
    assert rows == {False: (False, 6144), True: (True, 12288)}


@pytest.mark.slow
def test_a_piece_longer_than_the_ring_is_read_in_step_and_played_again_when_the_read_back_fell_behind(
        tmp_path, caplog, monkeypatch):
    """The CAN amplifier's recorder is a ring of 8192 points read while it records: a piece
    of 12,000 rows is recorded whole. When its read-back did not keep in step (here: nothing
    read while it played), the amplifier refuses the overwritten points and the piece is
    played again in parts its recorder holds without going round the ring; the records are
    the table."""
    import logging
    from afmctl.config import load_config
    from afmctl.control import calibrate_run as cr
    from afmctl.drivers.registry import open_amplifier
    from afmctl.sim_backend.testing import serve_can
    n = 12_000
    u = 20.0 + 40.0 * np.sin(np.linspace(0.0, 2 * np.pi, n)) ** 2
    channel = f"ring-{uuid.uuid4().hex[:8]}"
    with serve_can(channel, _scanner()):
        config = load_config(_config(tmp_path, "can", f"virtual:{channel}",
                                     extra="[amplifier.options]\nfd = true\ntimeout_s = 2.0\n"))
        config.amplifier.settle_s = 0.1
        with open_amplifier("can", f"virtual:{channel}", fd=True) as amp:
            signals = cr.recorder_signals(amp, "x")
            assert cr.rings(amp) and cr.device_capacity(amp, "x", signals) >= n
            run = cr.CalibrationRun(config, amp)
            step = cr.LiveReadback.step
            calls = {"first": True}

            def lagging(self, t_start, rate_Hz):           # the first play reads nothing while it plays
                if not calls["first"]:
                    step(self, t_start, rate_Hz)
            monkeypatch.setattr(cr.LiveReadback, "step", lagging)
            original = run._piece

            def piece(*a, **k):
                try:
                    return original(*a, **k)
                finally:
                    calls["first"] = False
            monkeypatch.setattr(run, "_piece", piece)
            try:
                with caplog.at_level(logging.WARNING, logger="afmctl.control.calibrate_run"):
                    recs = run.play("excite x", "x", signals, [u], [0], lambda k: 0.0)
            finally:
                run.finish()
            most = cr.unringed_rows(amp, "x", signals)
    assert "fell behind the recorder" in caplog.text and "again in parts of at most" in caplog.text
    assert len(recs) == 2 and recs[0].start == 0 < n - most <= recs[1].start <= most       # two parts of the table
    whole = np.concatenate([r.u_V for r in recs])
    assert follow_table(whole, u, 0.0013) == len(whole) >= n
    assert all(np.ptp(r.y_nm) > 1000.0 for r in recs)


def _config(tmp_path, driver: str, port: str | None = None, *, simulated: bool = False, rate_Hz: int = 10000,
            extra: str = "") -> Path:
    """A calibration's run configuration: ``driver`` on ``port`` (or simulated in-process),
    output wave, the default simulated scanner at two simulation steps per table point."""
    from afmctl.sim_backend.scanner import default_scanner_config
    cfg = default_scanner_config()
    cfg.dt_s = 5e-5          # two simulation steps per table point: the simulator keeps up on a loaded machine
    (tmp_path / "scanner.json").write_text(cfg.model_dump_json())
    port_line = f'port = "{port}"' if port is not None else ""
    if "[amplifier.options]" not in extra:              # replies late on a loaded machine are not a lost link
        extra = "[amplifier.options]\ntimeout_s = 2.0\n" + extra
    sim = (f'[simulation]\nenabled = true\nbaud = 10000000\nscanner = "{tmp_path / "scanner.json"}"\n'
           if simulated else "")
    path = tmp_path / "cal.toml"
    path.write_text(f"""
[scanner]
name = "cal"
[amplifier]
driver = "{driver}"
{port_line}
output = "wave"
slew_V_per_s = 10000.0
[loop]
rate_Hz = {rate_Hz}
[safety]
slew_V_per_s = 10000.0
ramp_V_per_s = 2000.0
[trajectory]
line_rate_Hz = 20.0
[runlog]
dir = "{tmp_path / 'runs'}"
fsync = false
{sim}{extra}""")
    return path


def _scanner():
    from afmctl.sim_backend.scanner import Scanner, default_scanner_config
    cfg = default_scanner_config()
    cfg.dt_s = 5e-5
    return Scanner(cfg)


def _calibrate_cmd(config: Path, out: Path, *more: str) -> list[str]:
    return [sys.executable, "-m", "afmctl", "calibrate", "--config", str(config), "--out", str(out), "--axes", "x",
            "--kind", "pi", *[f"--{k.replace('_', '-')}={v}" for k, v in SHORT.items()], *more]


@pytest.fixture
def config_file(tmp_path):
    return _config(tmp_path, "gcs", simulated=True)


def _interrupt(proc: subprocess.Popen, playing, sig: int = signal.SIGINT) -> float:
    """Wait until ``playing()`` (the device plays a piece), send ``sig``; the seconds until
    the process ended."""
    from afmctl.testing import wait_until
    wait_until(lambda: playing() or proc.poll() is not None, timeout_s=240, interval_s=0.01)
    assert proc.poll() is None, proc.communicate()[1][-3000:]
    time.sleep(0.2)                                          # into the piece
    t0 = time.monotonic()
    proc.send_signal(sig)
    try:
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return time.monotonic() - t0


def _popen(cmd: list[str]) -> subprocess.Popen:
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_ctrl_c_on_the_e727_over_tcp_ends_within_2_s_at_the_safe_value_with_no_generator_playing(tmp_path):
    from afmctl.sim_backend.amplifiers import make_device
    from afmctl.sim_backend.amplifiers.tcp_server import TcpServer
    with TcpServer(make_device("gcs", _scanner())) as server:
        config = _config(tmp_path, "gcs", server.port)
        proc = _popen(_calibrate_cmd(config, tmp_path / "x.json"))
        took = _interrupt(proc, lambda: server.device.wave.running_mask() != 0)
        err = proc.stderr.read()
        assert proc.returncode == 130 and "Traceback" not in err, err[-3000:]
        print(f"Ctrl-C: ended {took:.2f} s after the signal")
        assert took < 2.0, f"Ctrl-C took {took:.2f} s"
        assert server.device.wave.running_mask() == 0            # no generator playing
        assert server.device.outputs["x"] == pytest.approx(0.0, abs=0.01)   # the safe value
    assert "ramped to the safe value" in err and not (tmp_path / "x.json").exists()


@pytest.mark.slow
def test_ctrl_c_on_the_nv200_ends_within_2_s_at_the_safe_value_with_no_generator_playing(tmp_path):
    from afmctl.sim_backend.testing import serve_pty
    with serve_pty("nv200", sink=_scanner(), sensor="strain gauge") as server:
        config = _config(tmp_path, "nv200", server.port)
        proc = _popen(_calibrate_cmd(config, tmp_path / "x.json"))
        took = _interrupt(proc, lambda: bool(server.device.wave.params["grun"]))
        err = proc.stderr.read()
        assert proc.returncode == 130 and "Traceback" not in err, err[-3000:]
        print(f"Ctrl-C: ended {took:.2f} s after the signal")
        assert took < 2.0, f"Ctrl-C took {took:.2f} s"
        assert not server.device.wave.params["grun"]             # the waveform generator stopped
        assert server.device.outputs["x"] == pytest.approx(0.0, abs=0.01)
    assert not (tmp_path / "x.json").exists()


@pytest.mark.slow
def test_ctrl_c_on_the_can_amplifier_ends_within_2_s_at_the_safe_value_with_no_stream_playing(tmp_path):
    """The virtual bus lives in one process: the command runs here (its main thread), the
    SIGINT comes from a timer once the amplifier's stream plays."""
    from afmctl.cli import main
    from afmctl.sim_backend.amplifiers.can_stream import StreamState
    from afmctl.sim_backend.testing import serve_can
    channel = f"cal-{uuid.uuid4().hex[:8]}"
    with serve_can(channel, _scanner()) as sim:
        config = _config(tmp_path, "can", f"virtual:{channel}", extra="[amplifier.options]\nfd = true\ntimeout_s = 2.0\n")
        sent: list[float] = []

        def interrupt() -> None:
            from afmctl.testing import wait_for
            if wait_for(lambda: sim.stream.state is StreamState.PLAYING, 240, 0.01):
                time.sleep(0.2)
                sent.append(time.monotonic())
                os.kill(os.getpid(), signal.SIGINT)
        timer = threading.Thread(target=interrupt, daemon=True)
        timer.start()
        code = main(_calibrate_cmd(config, tmp_path / "x.json")[3:])
        took = time.monotonic() - sent[0]
        timer.join(timeout=5)
        assert code == 130 and sent
        print(f"Ctrl-C: ended {took:.2f} s after the signal")
        assert took < 2.0, f"Ctrl-C took {took:.2f} s"
        assert sim.stream.state is StreamState.IDLE                # the FIFO flushed: nothing plays
        assert sim.outputs["x"] == pytest.approx(0.0, abs=0.01)
    assert not (tmp_path / "x.json").exists()


@pytest.mark.slow
def test_stop_on_zenoh_ends_the_calibration_at_the_safe_value(tmp_path):
    """``stop`` on the scanner's ``cmd`` key (docs/ZENOH.md) while the E-727 plays a piece,
    from a real zenoh session on loopback; ``status`` answers what it does, ``start`` is refused."""
    from afmctl.sim_backend.amplifiers import make_device
    from afmctl.sim_backend.amplifiers.tcp_server import TcpServer
    from afmctl.testing import wait_for
    from afmctl.zenoh_api.bridge import open_session
    from afmctl.zenoh_api.messages import CmdReply, CmdRequest, decode_json
    from afmctl.zenoh_api.settings import loopback_pair
    srv, cli = loopback_pair()
    with TcpServer(make_device("gcs", _scanner())) as server:
        config = _config(tmp_path, "gcs", server.port,
                         extra=f'[zenoh]\nenabled = true\nlisten = ["{srv.listen[0]}"]\n')
        proc = _popen(_calibrate_cmd(config, tmp_path / "x.json"))
        session = open_session(cli)
        try:
            def ask(cmd: str) -> CmdReply | None:
                for reply in session.get(srv.key("cal", "cmd"), payload=CmdRequest(cmd=cmd).to_json_bytes(),
                                         timeout=5.0):
                    if reply.ok is not None:
                        return decode_json(reply.ok.payload.to_bytes(), CmdReply)
                return None
            assert wait_for(lambda: server.device.wave.running_mask() != 0 or proc.poll() is not None, 240)
            status = ask("status")
            refused = ask("start")
            stopped = ask("stop")
            proc.wait(timeout=60)
        finally:
            session.close()
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        err = proc.stderr.read()
        assert status is not None and status.ok and status.result["state"] == "calibrating"
        assert status.result["what"] == "excite x" and status.result["pieces"] >= 2
        assert refused is not None and not refused.ok and "stop" in refused.error
        assert stopped is not None and stopped.ok and proc.returncode == 130, err[-3000:]
        assert server.device.wave.running_mask() == 0
        assert server.device.outputs["x"] == pytest.approx(0.0, abs=0.01)


@pytest.mark.slow
def test_a_lost_link_exits_1_and_keeps_the_partial_recording(tmp_path):
    """The E-727's TCP server goes away while the second piece plays: exit 1, one error
    line, the first piece kept as CSV (t,u,y,v), no model."""
    from afmctl.sim_backend.amplifiers import make_device
    from afmctl.sim_backend.amplifiers.tcp_server import TcpServer
    from afmctl.testing import wait_for
    server = TcpServer(make_device("gcs", _scanner())).start()
    try:
        config = _config(tmp_path, "gcs", server.port)
        proc = _popen(_calibrate_cmd(config, tmp_path / "x.json"))
        # the second piece plays once the generator has started twice
        starts = [0]

        def second_piece() -> bool:
            gen = server.device.wave.gens[1]
            if gen.mode and gen.t0_s != starts[-1]:
                starts.append(gen.t0_s)
            return len(starts) > 2
        assert wait_for(lambda: second_piece() or proc.poll() is not None, 240, 0.005)
    finally:
        server.stop()                                        # the link is lost
    out, err = proc.communicate(timeout=120)
    errors = [ln for ln in err.splitlines() if ln.startswith("afmctl:")]
    assert proc.returncode == 1 and "Traceback" not in err, err[-3000:]
    assert len(errors) == 1 and "recorded so far" in errors[0]
    partial = tmp_path / "x.x-excite-partial.csv"
    assert partial.exists() and partial.read_text().splitlines()[0] == "t,u,y,v"
    assert len(partial.read_text().splitlines()) > 1000 and not (tmp_path / "x.json").exists()


def test_a_recorder_too_small_for_the_shortest_piece_is_refused_before_anything_moves(config_file, tmp_path):
    # a 0.1 Hz multisine period is 100,000 points at 10 kHz: more than the E-727's 262,144
    # points hold per signal even in three tables
    res = subprocess.run([sys.executable, "-m", "afmctl", "calibrate", "--config", str(config_file),
                          "--out", str(tmp_path / "x.json"), "--axes", "x", "--f-min-Hz", "0.1"],
                         capture_output=True, text=True, timeout=300)
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("afmctl: error:")]
    assert res.returncode == 2 and len(errors) == 1 and "shortest piece" in errors[0], res.stderr[-2000:]
    assert not (tmp_path / "x.json").exists()


def test_the_model_keeps_what_the_calibrations_plays_left_in_its_creep_stage(config_file):
    """The lag states of the model's creep stage where the calibration's plays end (the
    excitation, the validation, the hold while the other axes play, the ramp to the safe
    value), for `afmctl learn` right after on the same device (tests/test_learning_history.py);
    a model without a creep stage keeps nothing."""
    from types import SimpleNamespace

    from afmctl.api.calibrate import Calibration
    from afmctl.compensators.chain import ChainModel
    from afmctl.compensators.creep import LinearCreepModel
    from afmctl.compensators.learning_history import VoltageHistory
    from afmctl.compensators.pi import PIModel
    pi = PIModel(thresholds=[0.0, 20.0, 40.0], weights=[40.0, 8.0, 4.0])
    chain = ChainModel(hysteresis=pi, creep=LinearCreepModel(time_constants_s=[0.1, 1.0, 10.0],
                                                             creep_weights=[0.01, 0.01, 0.01], gain_nm_per_V=1.0,
                                                             offset_nm=0.0, initial_V=0.0))
    rate_Hz = 10000.0
    exc, val = np.linspace(0.0, 100.0, 20_000), np.linspace(100.0, 0.0, 5_000)

    def result(model):
        return SimpleNamespace(identified=SimpleNamespace(model=model), recording=SimpleNamespace(u_V=exc),
                               validation_record=SimpleNamespace(u_V=val))

    cal = Calibration(config_file, axes=["x"], kind="pi+creep")
    cal.played_unix_s, cal.finished_unix_s = {"x": 1000.0}, 1003.0
    kept = cal._history("x", result(chain))
    assert cal._history("x", result(pi)) is None
    assert kept["ended_unix_s"] == 1003.0 and kept["at_V"] == 0.0
    h = VoltageHistory(chain, 1.0 / rate_Hz, 0.0, settle_s=1.0)
    h.play(exc)
    h.play(val)
    h.hold(3.0)                              # held at 0 V, the safe value: no ramp
    np.testing.assert_allclose(kept["creep_state_nm"], h.creep_state(), rtol=1e-12)
    assert max(kept["creep_state_nm"]) > 1.0
