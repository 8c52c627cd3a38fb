"""GCS wave generator: the sans-I/O codec, the simulator's generator on its servo clock,
and our driver against the simulator over a real pty."""
from __future__ import annotations

import time

import numpy as np
import pytest

from afmctl.drivers import codec_gcs_wave as wcodec
from afmctl.drivers.errors import LimitError, ProtocolError
from afmctl.drivers.registry import open_amplifier
from afmctl.sim_backend.amplifiers.base import RecordingSink
from afmctl.sim_backend.amplifiers.gcs import SimGCS
from afmctl.sim_backend.amplifiers.gcs_wave import lin_segment
from afmctl.sim_backend.testing import serve_pty


# ----------------------------------------------------------------- codec (bytes only)
def test_wav_pnt_lines_start_then_append_at_their_index_and_stay_short():
    values = np.linspace(0.0, 119.99999, 1000)
    lines = wcodec.encode_wav_pnt(2, values, 0.0, 120.0, max_line=300)
    assert all(len(ln) <= 300 and ln.endswith(b"\n") for ln in lines)
    assert lines[0].startswith(b"WAV 2 X PNT 1 ") and all(ln.startswith(b"WAV 2 & PNT ") for ln in lines[1:])
    got, index = [], 1
    for ln in lines:
        tok = ln.split()
        assert int(tok[4]) == index and int(tok[5]) == len(tok) - 6
        got += [float(t) for t in tok[6:]]
        index += int(tok[5])
    assert len(got) == 1000 and max(got) <= 120.0
    assert np.max(np.abs(np.array(got) - values)) <= 0.5e-4 + 1e-12


def test_divider_for_exact_rates_and_the_nearest_ones_named():
    assert wcodec.divider_for(10_000, 20e-6) == 5
    assert wcodec.divider_for(50_000, 20e-6) == 1
    with pytest.raises(ValueError, match=r"3125 Hz or 2941.17647\d* Hz"):
        wcodec.divider_for(3000, 20e-6)
    with pytest.raises(ValueError, match="nearest: 50000 Hz"):
        wcodec.divider_for(60_000, 20e-6)


def test_running_mask_and_servo_time_replies():
    assert wcodec.parse_running(b"5\n") == 5 and wcodec.parse_running(b"0\n") == 0
    with pytest.raises(ProtocolError):
        wcodec.parse_running(b"zz\n")
    assert wcodec.parse_servo_cycle_s(b"1 0x0E000200=2e-05\n") == 2e-05
    with pytest.raises(ProtocolError, match="outside"):
        wcodec.parse_servo_cycle_s(b"1 0x0E000200=5\n")


# ----------------------------------------------------------------- simulator (sans-I/O)
def _sim(cycle_s: float = 20e-6):
    clock = [0.0]
    sink = RecordingSink()
    dev = SimGCS(sink, now=lambda: clock[0], servo_cycle_s=cycle_s)
    dev.feed(b"SVO 1 0 2 0 3 0\n")
    return dev, sink, clock


def test_sim_plays_point_k_at_t0_plus_k_divider_servo_cycles():
    dev, sink, clock = _sim()
    dev.feed(b"WAV 1 X PNT 1 4 1 2 3 4\nWSL 1 1\nWGC 1 2\nWTR 1 5 0\n")
    clock[0] = 1.0
    dev.feed(b"WGO 1 1\n")
    assert dev.feed(b"\x09") == b"1\n"
    clock[0] = 1.0 + 3 * 100e-6          # points 0..3 due (k * 5 * 20 us)
    dev.poll()
    assert [h[1]["x"] for h in sink.history[-4:]] == [1, 2, 3, 4]
    clock[0] = 2.0                       # the second cycle, then the generator stops
    assert dev.feed(b"WGO? 1\n") == b"1=0\n" and dev.feed(b"\x09") == b"0\n"
    times = [t for t, _ in sink.history[-8:]]
    assert times == [1.0 + k * 5 * 20e-6 for k in range(8)]
    assert [h[1]["x"] for h in sink.history[-8:]] == [1, 2, 3, 4] * 2
    assert dev.feed(b"ERR?\n") == b"0\n"


def test_sim_refuses_bad_wave_commands_with_gcs_errors():
    dev, _, _ = _sim()
    for cmd, code in [(b"WAV 1 X PNT 1 3 1 2\n", 1), (b"WAV 9 X PNT 1 1 1\n", 17), (b"WAV 1 & PNT 5 1 1\n", 17),
                      (b"WGO 1 1\n", 17), (b"WTR 1 0 0\n", 17), (b"WGO 1 7\n", 17), (b"WAV 1 X PNT 1 1 nan\n", 1),
                      (b"SPA? 1 0x1\n", 54)]:
        dev.feed(cmd)
        assert dev.feed(b"ERR?\n") == f"{code}\n".encode(), cmd
    dev.feed(b"WAV 1 X PNT 1 2 1 2\nWGC 1 0\nWGO 1 1\n")
    dev.feed(b"WAV 1 X PNT 1 1 5\n")      # a running generator's table cannot change
    assert dev.feed(b"ERR?\n") == b"17\n"


def test_lin_segment_rises_by_the_amplitude_with_smooth_ends():
    seg = lin_segment(20, 10.0, 2.0, 11, 4, 0)
    assert len(seg) == 20 and seg[:4] == [2.0] * 4 and seg[4] == 2.0 and seg[14] == 12.0 and seg[-1] == 12.0
    assert np.allclose(np.diff(seg[4:15]), 1.0)
    smooth = np.array(lin_segment(100, 1.0, 0.0, 100, 0, 20))
    d = np.diff(smooth)
    assert smooth[0] == 0.0 and smooth[-1] == pytest.approx(1.0) and np.all(d >= 0)
    assert d[0] < d[50] / 10 and d[-1] < d[50] / 10          # accelerates, decelerates
    assert np.allclose(d[25:70], d[50])                       # constant speed between


# ----------------------------------------------------------------- driver over a pty
def _ramp_to(amp, axis: str, v: float) -> None:
    for u in np.linspace(0, v, 21)[1:]:
        amp.set_voltages({axis: float(u)})


def test_driver_uploads_plays_on_the_device_clock_and_reads_back():
    with serve_pty("gcs") as server, open_amplifier("gcs", server.port, max_step_V=1.0) as amp:
        _ramp_to(amp, "x", 10.0)
        table = 10.0 + 5.0 * np.sin(np.linspace(0, 2 * np.pi, 501))[:-1]
        assert amp.upload_wave("x", table) == 500
        assert server.device.wave.tables[1] == pytest.approx(table, abs=0.5e-4)
        before = len(server.sink.history)
        st = amp.start_wave(rate_Hz=10_000, cycles=3)
        assert st.divider == 2 and st.rate_Hz == 10_000 and st.cycles == 3
        deadline = time.monotonic() + 5
        while amp.wave_status().running["x"]:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        played = server.sink.history[before:]
        t = np.array([h[0] for h in played])
        assert len(played) == 1499            # sample 0 (10 V) is the present output: no change to record
        assert np.allclose(np.diff(t), 100e-6, rtol=0, atol=1e-9)       # the servo clock, no jitter
        assert np.allclose([h[1]["x"] for h in played], np.tile(table, 3)[1:], atol=0.5e-4)
        assert amp.last_output["x"] == pytest.approx(table[-1], abs=1e-3)  # read back after the end


def test_driver_refuses_a_table_naming_the_sample_before_sending_anything():
    with serve_pty("gcs") as server, open_amplifier("gcs", server.port, max_step_V=1.0,
                                                   host_limits={"x": (0.0, 50.0)}) as amp:
        _ramp_to(amp, "x", 10.0)
        amp.flush()
        time.sleep(0.05)
        sent = server.bytes_received
        bad = [
            (np.r_[np.linspace(10, 49, 100), 51.0], r"sample 100 = 51 V is outside the limits \[0, 50\] V"),
            (np.r_[10.0, 10.5, 12.0], r"sample 2 = 12 V steps 1.5 V from sample 1"),
            (np.r_[12.0, 12.5], r"sample 0 = 12 V is 2 V from the present output 10 V"),
            (np.r_[10.0, np.nan], r"sample 1 = nan V"),
        ]
        for table, msg in bad:
            with pytest.raises(LimitError, match=msg):
                amp.upload_wave("x", table)
        time.sleep(0.05)
        assert server.bytes_received == sent and server.device.wave.tables[1] == []
        amp.upload_wave("x", np.linspace(10.0, 15.0, 11))
        with pytest.raises(LimitError, match="wrap from sample 10 = 15 V to sample 0 = 10 V"):
            amp.start_wave(rate_Hz=1000, cycles=2)
        with pytest.raises(LimitError, match="3000 Hz is not the servo rate 20000 Hz"):
            amp.start_wave(rate_Hz=3000)
        assert not server.device.wave.gens[1].mode


def test_stop_wave_stops_an_endless_wave_and_the_output_holds():
    with serve_pty("gcs") as server, open_amplifier("gcs", server.port, max_step_V=1.0) as amp:
        _ramp_to(amp, "x", 10.0)
        amp.upload_wave("x", np.r_[np.linspace(10, 14, 9), np.linspace(14, 10, 9)[1:-1]])
        assert amp.start_wave(divider=50, cycles=0).running["x"]
        time.sleep(0.1)
        st = amp.stop_wave()
        assert not st.running["x"] and not server.device.wave.gens[1].mode
        held = amp.get_voltages()["x"]
        time.sleep(0.05)
        assert amp.get_voltages()["x"] == held and 10.0 <= held <= 14.0
        amp.set_voltages({"x": held + 0.5})       # the slew reference is the read-back output
        with pytest.raises(LimitError, match="exceeds max_step_V"):
            amp.set_voltages({"x": held + 2.0})


# ----------------------------------------------------------------- afmctl amp --driver gcs wave
def _csv(path, header, rows) -> str:
    np.savetxt(path, np.asarray(rows), delimiter=",", header=header, comments="", fmt="%.6f")
    return str(path)


def test_amp_wave_cli_uploads_and_plays_on_the_servo_clock(tmp_path, capsys):
    from afmctl.cli import main
    n = 400
    x = 4.0 + 4.0 * np.sin(2 * np.pi * np.arange(n) / n) ** 2          # starts at 4 V, wraps smoothly
    path = _csv(tmp_path / "w.csv", "t,u", np.column_stack([np.arange(n) / 10_000, x]))
    with serve_pty("gcs") as server:
        base = ["amp", "--driver", "gcs", "--port", server.port, "--max-step", "5", "wave", "--file", path]
        assert main(base + ["--rate-Hz", "3000"]) == 2
        err = capsys.readouterr().err
        assert "--rate-Hz: 3000 Hz is not the servo rate 20000 Hz over a whole number" in err
        assert "3333.333333 Hz or 2857.142857 Hz" in err and "nothing was sent" in err
        assert server.device.wave.tables[1] == []
        assert main(base + ["--rate-Hz", "6666.666667"]) == 0           # 20 kHz / 3
        assert "at 6666.67 Hz" in capsys.readouterr().out and server.device.wave.gens[1].rate == 3
        before = len(server.sink.history)
        assert main(base + ["--rate-Hz", "10000", "--cycles", "2"]) == 0
        out = capsys.readouterr().out
        assert "played 400 points x 2 cycle(s) on x at 10000 Hz" in out and "every 2 tick(s) of 50 us" in out
        played = server.sink.history[before:]
        t = np.array([h[0] for h in played])
        assert np.allclose(np.diff(t) / 100e-6, np.round(np.diff(t) / 100e-6), atol=1e-6)   # on the 100 us grid
        assert t[-1] - t[0] <= (2 * n - 1) * 100e-6 + 1e-9
        assert max(h[1]["x"] for h in played) == pytest.approx(8.0, abs=1e-4)


def test_amp_wave_cli_refuses_a_row_over_the_step_limit_naming_it(tmp_path, capsys):
    from afmctl.cli import main
    path = _csv(tmp_path / "w.csv", "t,u", [(0.0, 1.0), (0.001, 2.0), (0.002, 9.0)])
    with serve_pty("gcs") as server:
        assert main(["amp", "--driver", "gcs", "--port", server.port, "--max-step", "5", "wave", "--file", path,
                     "--rate-Hz", "1000"]) == 2
        err = capsys.readouterr().err
        assert "row 4" in err and "exceeds --max-step 5 V" in err and "nothing was sent" in err
        assert server.device.wave.tables[1] == []


def test_set_voltages_is_refused_on_an_axis_whose_generator_runs():
    with serve_pty("gcs") as server, open_amplifier("gcs", server.port, max_step_V=1.0) as amp:
        _ramp_to(amp, "x", 10.0)
        amp.upload_wave("x", np.r_[np.linspace(10, 12, 5), np.linspace(12, 10, 5)[1:-1]])
        amp.start_wave(divider=100, cycles=0)
        with pytest.raises(LimitError, match="axis x: its wave generator runs"):
            amp.set_voltages({"x": 10.5})
        amp.set_voltages({"y": 0.5})                     # another axis is free
        amp.stop_wave()
        amp.set_voltages({"x": amp.last_output["x"]})


@pytest.mark.parametrize("query", ["wave_status", "get_voltages"])
def test_a_query_right_after_a_pipelined_error_check_reads_its_own_reply(query):
    """Every setpoint carries an ``ERR?`` (check_every=1) whose reply is still on its way
    (20 ms reply latency) when the next query is sent: the query must not take that ``0``
    for its own answer (``#9`` read it as "no generator runs", and the next ``VOL?`` got the
    ``#9`` reply)."""
    with serve_pty("gcs", latency_s=0.02) as srv, \
            open_amplifier("gcs", srv.port, check_every=1, timeout_s=1.0) as amp:
        amp.set_voltages({"x": 10.0, "y": 10.0, "z": 10.0})
        amp.flush()
        amp.upload_wave("x", np.full(4000, 10.0))
        amp.start_wave(divider=1, cycles=1, axes=["x"])      # plays 0.2 s
        amp.set_voltages({"y": 11.0})                        # pipelines an ERR?
        if query == "wave_status":
            assert amp.wave_status().running["x"] is True
        else:
            assert amp.get_voltages()["y"] == pytest.approx(11.0)
        assert amp.get_voltages()["x"] == pytest.approx(10.0)


def test_driver_refuses_a_table_longer_than_the_controller_holds():
    from afmctl.sim_backend.amplifiers.gcs_wave import MAX_POINTS
    with serve_pty("gcs") as server, open_amplifier("gcs", server.port) as amp:
        assert amp.wave_capacity("x") == MAX_POINTS
        with pytest.raises(LimitError, match=f"{MAX_POINTS + 1} points, the controller's table holds {MAX_POINTS}"):
            amp.upload_wave("x", np.zeros(MAX_POINTS + 1))
        assert server.device.wave.tables[1] == []


def test_generators_start_on_one_tick_and_an_output_offset_is_refused():
    """All axes start with one WGO (the same servo tick, whatever the link's speed), and a
    generator with an output offset (WOS, which the controller adds to every wave value and
    may have stored) is refused before anything starts; the driver does not change it."""
    sink = RecordingSink(max_history=100_000)
    with serve_pty("gcs", sink=sink, baud=115200) as server, open_amplifier("gcs", server.port) as amp:
        for a in "xyz":
            amp.upload_wave(a, np.zeros(200))
        server.device.wave_offset_V[2] = 5.0
        with pytest.raises(LimitError, match=r"generator 2 \(axis y\) adds an output offset WOS of 5 V"):
            amp.start_wave(divider=1, cycles=1)
        assert not any(g.mode for g in server.device.wave.gens.values())
        assert server.device.wave_offset_V[2] == 5.0
        server.device.wave_offset_V[2] = 0.0
        amp.start_wave(divider=1, cycles=1)
        t0 = {g: gen.t0_s for g, gen in server.device.wave.gens.items()}
        assert t0[1] == t0[2] == t0[3] > 0
