"""Our drivers' recorder path (Amplifier.configure_recorder / read_recording) against the
simulated amplifiers driving the default simulated scanner with its position sensor, over
real ptys (GCS, NV200) and python-can's virtual bus (CAN); a device without a recorder
says so."""
from __future__ import annotations

import time

import numpy as np
import pytest

from afmctl.drivers.codec_gcs_rec import parse_data
from afmctl.drivers.errors import (AmplifierError, LimitError, ProtocolError, RecorderUnavailable,
                                   RecordingOverwritten)
from afmctl.drivers.recording import align_to_table, joined_recording
from afmctl.drivers.registry import open_amplifier
from afmctl.sim_backend.scanner import Scanner, default_scanner_config
from afmctl.sim_backend.testing import serve_pty


def _sine(n: int, lo: float, hi: float) -> np.ndarray:
    return lo + (hi - lo) * (0.5 - 0.5 * np.cos(2 * np.pi * np.arange(n) / n))


def _offline_reference(table_V: np.ndarray, samples_per_point: int, rest_s: float = 0.3) -> np.ndarray:
    """What the recorder should read: the same scanner at rest at table[0], then the table
    played point by point; reading k = the position after points 0..k-1 (noise-free sensor)."""
    cfg = default_scanner_config()
    for a in "xyz":
        cfg.axis(a).sensor = cfg.axis(a).sensor.model_copy(update={"noise_nm": 0.0, "resolution_nm": 0.0})
    ref = Scanner(cfg)
    ref.run(np.tile([table_V[0], 0.0, 0.0], (int(rest_s / 1e-5), 1)))
    cap = ref.capture_sensor(ref.time_s, samples_per_point * 1e-5, len(table_V))
    u = np.zeros((len(table_V) * samples_per_point, 3))
    u[:, 0] = np.repeat(table_V, samples_per_point)
    ref.run(u)
    return cap.y_nm[:, 0]


def test_gcs_driver_records_position_and_voltage_aligned_with_the_wave():
    scanner = Scanner(default_scanner_config())
    n, divider = 400, 2
    table = _sine(n, 20.0, 100.0)
    with serve_pty("gcs", sink=scanner) as server:
        with open_amplifier("gcs", server.port) as amp:
            assert amp.has_recorder and amp.recorder_clock_s() == pytest.approx(50e-6)
            amp.set_voltages({"x": float(table[0])})
            amp.upload_wave("x", table)
            setup = amp.configure_recorder(["x"], points=n, divider=divider)
            assert setup.period_s == pytest.approx(100e-6)
            with pytest.raises(LimitError, match="1..32768"):
                amp.configure_recorder(["x"], points=40000)
            amp.configure_recorder(["x"], points=n, divider=divider)
            amp.start_wave(divider=divider)
            rec = amp.read_recording(timeout_s=10)
    assert rec.source == "gcs DRR?" and len(rec) == n and rec.period_s == pytest.approx(100e-6)
    np.testing.assert_allclose(rec.t_s, np.arange(n) * 100e-6)
    np.testing.assert_allclose(rec.u_V["x"], table, atol=1e-4)       # point k = wave point k
    assert len(align_to_table(rec, {"x": table}, tol_V=1e-4)) == n
    # reading k is the position after wave points 0..k-1: the same scanner played offline
    # (its rest before the start lasts as long as the link took, so creep differs a little)
    want = _offline_reference(table, samples_per_point=10)
    err = rec.y_nm["x"] - want
    assert np.ptp(want) > 2000.0 and np.abs(err).max() < 0.002 * np.ptp(want)   # a point off would be ~50 nm


def test_gcs_recording_read_while_it_is_taken_equals_the_whole_read_after_it():
    """read_recorded (DRR? of the points DRL? says are recorded, while the wave plays): the
    parts joined are the recording read_recording reads once it is full."""
    from afmctl.sim_backend.amplifiers import make_device
    from afmctl.sim_backend.amplifiers.tcp_server import TcpServer
    n, divider, chunk = 4000, 2, 1000
    table = _sine(n, 20.0, 100.0)
    with TcpServer(make_device("gcs", Scanner(default_scanner_config()))) as server:   # the E-727's TCP port
        with open_amplifier("gcs", server.port, timeout_s=5.0) as amp:     # a loaded machine: a late reply
            assert amp.reads_while_recording
            amp.set_voltages({"x": float(table[0])})
            amp.upload_wave("x", table)
            amp.configure_recorder(["x"], points=n, divider=divider, signals=("y_nm", "u_V"))
            amp.start_wave(divider=divider)
            parts, got = [], 0
            while got < n:
                ready = min(amp.recorded_points(), n) - got
                if ready > 0:
                    parts.append(amp.read_recorded(got, min(ready, chunk)))
                    got += len(parts[-1])
                else:
                    time.sleep(0.01)
            whole = amp.read_recording(timeout_s=10)
            with pytest.raises(AmplifierError, match="outside the armed 4000"):
                amp.read_recorded(n - 10, 20)
    live = joined_recording(parts)
    assert len(parts) >= n // chunk and len(live) == n
    np.testing.assert_allclose(live.t_s, whole.t_s)
    np.testing.assert_array_equal(live.y_nm["x"], whole.y_nm["x"])
    np.testing.assert_array_equal(live.u_V["x"], whole.u_V["x"])


def test_gcs_array_lines_of_the_wrong_width_are_refused_even_when_the_count_adds_up():
    head = {"NDATA": "2", "DIM": "3", "SEPARATOR": "32"}
    assert parse_data(head, [b"1.5 2 3 ", b"4 5 -6.25"], 3).tolist() == [[1.5, 2, 3], [4, 5, -6.25]]
    with pytest.raises(ProtocolError, match="line 1: 2 finite values expected 3"):
        parse_data(head, [b"1 2 ", b"3 4 5 6"], 3)
    with pytest.raises(ProtocolError, match="line 2 is not numbers"):
        parse_data(head, [b"1 2 3 ", b"4 x 6"], 3)


def test_mdt693b_has_no_recorder_and_says_how_to_measure_instead():
    with serve_pty("mdt693b") as server:
        with open_amplifier("mdt693b", server.port) as amp:
            assert not amp.has_recorder
            with pytest.raises(RecorderUnavailable, match="no data recorder.*external sensor.*t,y"):
                amp.configure_recorder(points=10)
            with pytest.raises(RecorderUnavailable):
                amp.read_recording()


@pytest.mark.parametrize("sensor", ["strain gauge"])
def test_nv200_driver_records_position_and_voltage_started_by_the_waveform_generator(sensor):
    scanner = Scanner(default_scanner_config())
    n, divider = 200, 2
    table = _sine(n, 20.0, 100.0)
    with serve_pty("nv200", sink=scanner, sensor=sensor, posmax_um=12.0) as server:
        with open_amplifier("nv200", server.port) as amp:
            amp.set_voltages({"x": float(table[0])})
            amp.upload_wave("x", table)
            setup = amp.configure_recorder(points=n, divider=divider)
            assert setup.period_s == pytest.approx(100e-6) and setup.axes == ("x",)
            with pytest.raises(LimitError, match="1..6144"):
                amp.configure_recorder(points=7000)
            amp.configure_recorder(points=n, divider=divider)
            amp.start_wave(divider=divider)
            while amp.wave_status().running["x"]:      # hands back through the recorder: kept
                pass
            rec = amp.read_recording(timeout_s=10)
            assert amp.get_voltages()["x"] == pytest.approx(table[-1], abs=0.01)
    assert rec.source == "nv200 recoutf" and len(rec) == n
    np.testing.assert_allclose(rec.t_s, np.arange(n) * 100e-6)
    np.testing.assert_allclose(rec.u_V["x"], table, atol=0.1)    # the buffer holds % of the range
    assert len(align_to_table(rec, {"x": table}, tol_V=0.005)) == n
    want = _offline_reference(rec.u_V["x"], samples_per_point=10)
    err = rec.y_nm["x"] - want
    assert np.ptp(want) > 2000.0 and np.abs(err).max() < 0.002 * np.ptp(want)


def test_nv200_without_sensor_records_voltage_only_and_says_why():
    with serve_pty("nv200") as server:
        with open_amplifier("nv200", server.port) as amp:
            with pytest.raises(RecorderUnavailable, match="no position sensor.*u_V only"):
                amp.configure_recorder(points=10)
            assert amp.configure_recorder(points=10, signals=("u_V",)).signals == ("u_V",)


def test_can_driver_records_the_stream_from_its_first_played_sample():
    import uuid
    from afmctl.sim_backend.testing import serve_can
    scanner = Scanner(default_scanner_config())
    n = 400
    table = _sine(n, 20.0, 100.0)
    rows = [(float(v), 30.0, 0.0) for v in table]
    channel = f"rec-{uuid.uuid4().hex[:8]}"
    with serve_can(channel, scanner):
        with open_amplifier("can", f"virtual:{channel}") as amp:
            amp.set_voltages({"x": rows[0][0], "y": 30.0, "z": 0.0})
            with pytest.raises(LimitError, match="start_stream"):
                amp.configure_recorder(points=n)
            amp.start_stream(10_000, prefill=n)           # the clock starts once all are queued
            with pytest.raises(LimitError, match="1..65535"):
                amp.configure_recorder(points=70_000)
            assert amp.recorder_capacity() == 8192 and amp.recorder_max_points() == 65535   # a ring past 8192
            setup = amp.configure_recorder(["x", "y"], points=n)
            assert setup.period_s == pytest.approx(100e-6)
            amp.queue(rows)
            amp.drain_stream()
            rec = amp.read_recording(timeout_s=10)
    assert rec.source == "can REC_DATA" and len(rec) == n and set(rec.y_nm) == {"x", "y"}
    np.testing.assert_allclose(rec.u_V["x"], table, atol=0.0013)      # 2.5 mV frames
    np.testing.assert_allclose(rec.u_V["y"], 30.0)
    assert len(align_to_table(rec, {"x": table}, tol_V=0.00125 + 1e-9)) == n
    want = _offline_reference(rec.u_V["x"], samples_per_point=10)
    err = rec.y_nm["x"] - want                        # t0 lies between two 10 us samples: <= 1 sample off
    assert np.ptp(want) > 2000.0 and np.abs(err).max() < 0.002 * np.ptp(want)


def test_can_fd_read_back_equals_the_classic_one_and_reads_while_it_records():
    """On a CAN FD bus the recorder comes back in REC_DATA_FD frames of 8 points: the same
    points, position, output and piezo voltage, as REC_DATA + REC_DATA_V give; the points
    recorded so far are read while the stream still plays."""
    import uuid
    from afmctl.sim_backend.testing import serve_can
    n = 4000                                    # 0.4 s at 10 kHz, inside the 4096-sample FIFO
    table = _sine(n, 20.0, 100.0)
    channel = f"fd-{uuid.uuid4().hex[:8]}"
    with serve_can(channel, Scanner(default_scanner_config())):
        with open_amplifier("can", f"virtual:{channel}", fd=True) as amp:
            assert amp.reads_while_recording
            amp.set_voltages({"x": float(table[0]), "y": 30.0, "z": 0.0})
            amp.start_stream(10_000, prefill=n)           # the clock starts once all are queued
            setup = amp.configure_recorder(["x", "y"], points=n, signals=("y_nm", "u_V", "v_V"))
            amp.queue([(float(v), 30.0, 0.0) for v in table])
            deadline = time.monotonic() + 10.0
            while amp.recorded_points() < 200 and time.monotonic() < deadline:
                time.sleep(0.002)
            early = amp.read_recorded(0, 200)                     # 25 frames while 0.38 s still play
            assert amp.recorded_points() < n
            amp.drain_stream()
            fd = amp.read_recording(timeout_s=10)
            amp.stream_fd = False                                  # the same points, classic frames
            classic = amp.read_recording(timeout_s=10)
    assert setup.points == n and fd.source == "can REC_DATA_FD" and classic.source == "can REC_DATA"
    for a in ("x", "y"):
        np.testing.assert_array_equal(fd.y_nm[a], classic.y_nm[a])
        np.testing.assert_array_equal(fd.u_V[a], classic.u_V[a])
        np.testing.assert_array_equal(fd.v_V[a], classic.v_V[a])
        np.testing.assert_array_equal(early.y_nm[a], fd.y_nm[a][:200])
    np.testing.assert_allclose(fd.u_V["x"], table, atol=0.0013)
    assert np.ptp(fd.y_nm["x"]) > 2000.0 and np.ptp(fd.v_V["x"]) > 50.0
    np.testing.assert_allclose(early.t_s, fd.t_s[:200])


def test_can_recording_longer_than_the_recorder_is_a_ring_read_while_it_records():
    """20,000 points armed on the 8192-point recorder: read back while the stream plays,
    every point comes back (the output is the table); a point read after 8192 more were
    taken is refused by the amplifier as overwritten."""
    import uuid
    from afmctl.sim_backend.testing import serve_can
    n = 20_000                                              # 2 s at 10 kHz
    table = _sine(n, 20.0, 100.0)
    rows = [(float(v), 0.0, 0.0) for v in table]
    channel = f"ring-{uuid.uuid4().hex[:8]}"
    with serve_can(channel, Scanner(default_scanner_config())):
        with open_amplifier("can", f"virtual:{channel}", fd=True) as amp:
            amp.set_voltages({"x": rows[0][0], "y": 0.0, "z": 0.0})
            amp.start_stream(10_000, prefill=3000)
            amp.configure_recorder(["x"], points=n, signals=("y_nm", "u_V"))
            parts, got, queued = [], 0, 0
            deadline = time.monotonic() + 60.0
            while got < n and time.monotonic() < deadline:
                if queued < n and queued - amp.buffer_status().played_seq < 3000:
                    amp.queue(rows[queued:queued + 1000])      # the FIFO (4096) topped up as it plays
                    queued = min(n, queued + 1000)
                    continue
                ready = amp.recorded_points() - got
                if ready >= min(500, n - got):
                    parts.append(amp.read_recorded(got, min(ready, 500)))
                    got += len(parts[-1])
                else:
                    time.sleep(0.005)
            with pytest.raises(RecordingOverwritten):             # ERROR 6 detail 5
                amp.read_recorded(0, 10)
    rec = joined_recording(parts)
    assert len(rec) == n and rec.source == "can REC_DATA_FD"
    # every point is the output the amplifier gave: the table in order, held where the FIFO
    # ran dry (a host too loaded to top it up in time: the recorder records the hold)
    assert _table_rows_followed(rec.u_V["x"], table, 0.0013) > n // 2
    np.testing.assert_allclose(rec.t_s, np.arange(n) * 1e-4)
    assert np.ptp(rec.y_nm["x"]) > 2000.0


def _table_rows_followed(played: np.ndarray, table: np.ndarray, tol_V: float) -> int:
    """How many rows of ``table`` the recorded output ``played`` went through, in order,
    each sample a table row or a hold of the row before; fails on any other value."""
    i = 0
    for j, v in enumerate(np.asarray(played).tolist()):
        if i < len(table) and abs(v - table[i]) <= tol_V:
            i += 1
        else:
            assert i > 0 and abs(v - table[i - 1]) <= tol_V, f"recorded sample {j}: {v} V is not the table's output"
    return i


def test_nv200_recording_armed_but_never_started_is_dropped_when_the_output_is_read(caplog):
    import logging
    from afmctl.drivers.errors import AmplifierError
    with serve_pty("nv200", sensor="strain gauge") as server:
        with open_amplifier("nv200", server.port) as amp:
            amp.set_voltages({"x": 12.0})
            amp.configure_recorder(points=50)
            with caplog.at_level(logging.WARNING, logger="afmctl.drivers.nv200"):
                assert amp.get_voltages()["x"] == pytest.approx(12.0, abs=0.01)
            assert "never started" in caplog.text
            with pytest.raises(AmplifierError, match="no recording armed"):
                amp.read_recording(timeout_s=0.1)


# -- the simulated E-727's recorder, sans-I/O (a clock the test moves) --
def _gcs(clock):
    from afmctl.sim_backend.amplifiers.base import RecordingSink
    from afmctl.sim_backend.amplifiers.gcs import SimGCS
    return SimGCS(RecordingSink(), now=lambda: clock[0])


def test_sim_gcs_recorder_triggers_rate_and_gcs_array():
    clock = [0.0]
    dev = _gcs(clock)
    dev.feed(b"SVO 1 0 2 0 3 0\nDRC 1 1 7 2 2 7\nRTR 4\nDRT 0 1 0\n")
    assert dev.feed(b"DRL? 1 2\n") == b"1=0 \n2=0\n"            # not triggered yet
    clock[0] = 1e-3
    dev.feed(b"SVA 1 12.5\n")                                 # DRT 1: a position-changing command
    clock[0] = 1e-3 + 10 * 4 * 50e-6
    assert dev.feed(b"DRL? 1\n") == b"1=11\n"                  # t0 .. t0 + 10 x 200 us
    reply = dev.feed(b"DRR? 2 3 1 2\n").decode()
    head, data = reply.split("# END_HEADER \n")
    assert "# TYPE = 1 \n" in head and "# SEPARATOR = 32 \n" in head and "# NDATA = 3 \n" in head
    assert "# DIM = 2 \n" in head and "# SAMPLE_TIME = 0.0002 \n" in head and "# NAME1 = Voltage of output chan 2" in head
    assert data == "12.500000 0.000000 \n12.500000 0.000000 \n12.500000 0.000000\n"
    dev.feed(b"DRT 0 4 0\n")                                  # 4: at once
    assert dev.feed(b"DRL? 1\n") == b"1=1\n"
    dev.feed(b"DRT 0 2 0\n")                                  # 2: the next command, then back to 0
    clock[0] += 1.0
    dev.feed(b"VOL? 1\n")
    assert dev.feed(b"DRL? 1\n") == b"1=1\n" and dev.feed(b"DRT? 1\n") == b"1=0 0\n"
    clock[0] += 1.0
    dev.feed(b"WGR\n")                                        # restarts every table
    assert dev.feed(b"DRL? 1\n") == b"1=1\n" and dev.feed(b"ERR?\n") == b"0\n"
    assert dev.feed(b"TNR?\n") == b"8\n" and dev.feed(b"RTR?\n") == b"4\n"


@pytest.mark.parametrize("cmd, code", [(b"DRC 9 1 2\n", 17), (b"DRC 1 1 5\n", 17), (b"DRC 1 7 2\n", 17),
                                       (b"DRC 1 1\n", 1), (b"DRT 0 3 0\n", 17), (b"RTR 0\n", 17),
                                       (b"DRL? 9\n", 17), (b"DRR? 0 5 1\n", 17)])
def test_sim_gcs_recorder_refuses_bad_commands_with_gcs_errors(cmd, code):
    dev = _gcs([0.0])
    dev.feed(cmd)
    assert dev.feed(b"ERR?\n") == f"{code}\n".encode()


def test_sim_gcs_recorder_shares_its_points_among_the_tables_the_host_chooses():
    """``SPA 1 0x16000300 n`` (Data Recorder Chan Number): the 262,144 points in equal shares
    to n tables (TNR?, SPA?), 1 to 8; the other parameters stay protected (error 60)."""
    dev = _gcs([0.0])
    assert dev.feed(b"SPA 1 0x16000300 3\n") == b"" and dev.feed(b"ERR?\n") == b"0\n"
    assert dev.feed(b"TNR?\n") == b"3\n" and dev.feed(b"SPA? 1 0x16000300\n") == b"1 0x16000300=3\n"
    assert dev.recorder.max_points == 262_144 // 3
    dev.feed(b"DRC 4 1 2\n")                                  # table 4 is gone
    assert dev.feed(b"ERR?\n") == b"17\n"
    for cmd, code in [(b"SPA 1 0x16000300 9\n", 17), (b"SPA 1 0x16000300 0\n", 17),
                      (b"SPA 1 0x0E000200 1e-4\n", 60), (b"SPA 1 0x16000300\n", 1)]:
        dev.feed(cmd)
        assert dev.feed(b"ERR?\n") == f"{code}\n".encode(), cmd
    assert dev.feed(b"TNR?\n") == b"3\n"


def test_gcs_driver_regroups_the_recorder_and_keeps_its_tables_where_refused():
    with serve_pty("gcs") as server:
        with open_amplifier("gcs", server.port) as amp:
            signals = ("y_nm", "u_V", "v_V")
            assert amp.record_tables() == 8 and amp.recorder_capacity(["x"], signals) == 32768
            assert amp.set_record_tables(3) == 3 and amp.recorder_capacity(["x"], signals) == 262_144 // 3
            amp.configure_recorder(["x"], points=262_144 // 3, signals=signals)      # fits now
            server.device.record_tables_settable = False        # firmware that protects it: kept
            assert amp.set_record_tables(8) == 3
            server.device.record_tables_settable = True
            assert amp.set_record_tables(8) == 8 and amp.recorder_capacity(["x"], signals) == 32768
            with pytest.raises(LimitError, match="1 or more"):
                amp.set_record_tables(0)
    with serve_pty("nv200") as server:
        with open_amplifier("nv200", server.port) as amp:
            assert amp.record_tables() is None and amp.set_record_tables(2) is None


def test_sim_gcs_recorder_options_commanded_actual_and_error_from_the_sensor():
    """Option 1 (commanded position, the linear map of the output), 2 (the scanner's sensor)
    and 3 (their difference) on one recording; µm."""
    from afmctl.sim_backend.amplifiers.gcs import SimGCS
    clock = [0.0]
    scanner = Scanner(default_scanner_config())
    dev = SimGCS(scanner, now=lambda: clock[0])
    dev.feed(b"SVO 1 0\nSVA 1 60\nDRC 1 1 1 2 1 2 3 1 3\nDRT 0 1 0\n")
    clock[0] = 0.01
    dev.feed(b"SVA 1 61\n")                                   # triggers (DRT 1) and moves
    clock[0] = 0.02
    reply = dev.feed(b"DRR? 1 100 1 2 3\n").decode()
    data = np.array([[float(v) for v in ln.split()] for ln in reply.split("# END_HEADER \n")[1].splitlines()])
    assert data.shape == (100, 3)
    np.testing.assert_allclose(data[:, 0], 61 / 120 * 100, atol=1e-6)      # commanded: linear over VMI..VMA
    np.testing.assert_allclose(data[:, 2], data[:, 0] - data[:, 1], atol=2e-6)
    assert 2.0 < data[-1, 1] < 20.0 and data[-1, 1] > data[0, 1]           # the sensor [µm] sees the step


def test_sensor_config_from_a_scanner_config_table():
    from afmctl.sim_backend.config import ScannerConfig
    cfg = ScannerConfig.model_validate({"x": {"sensor": {"noise_nm": 1.0, "bandwidth_Hz": None, "delay_s": 2e-5}}})
    assert cfg.x.sensor.noise_nm == 1.0 and cfg.x.sensor.bandwidth_Hz is None and cfg.y.sensor.noise_nm == 0.2


def test_bad_recorder_requests_name_the_allowed_range_and_send_nothing():
    with serve_pty("gcs") as server:
        with open_amplifier("gcs", server.port) as amp:
            before = server.device.recorder.tables[1].option, server.device.commands
            for kwargs, match in [({"axes": ["w"], "points": 10}, "one or more of x, y, z"),
                                  ({"signals": ("pos",), "points": 10}, "one or more of y_nm, u_V"),
                                  ({"points": 0}, "1..32768"), ({"points": 10, "divider": 0}, "divider")]:
                with pytest.raises(LimitError, match=match):
                    amp.configure_recorder(**kwargs)
            assert server.device.recorder.tables[1].option == before[0]     # no DRC was sent
            with pytest.raises(Exception, match="no recording armed"):
                amp.read_recording(timeout_s=0.1)


def test_align_to_table_checks_length_and_trigger_and_cuts_a_cycle():
    from afmctl.drivers.recording import Recording, RecordingMismatch, align_to_table
    n = 50
    table = _sine(n, 10.0, 60.0)
    u = np.concatenate([table, table, table])
    y = np.arange(3 * n, dtype=float)
    rec = Recording(np.arange(3 * n) * 1e-4, {"x": y}, {"x": u}, 1e-4, "test")
    last = align_to_table(rec, {"x": table}, cycle=2)
    assert len(last) == n and last.y_nm["x"][0] == 2 * n and last.t_s[0] == 0.0
    with pytest.raises(RecordingMismatch, match="needs 200"):
        align_to_table(rec, {"x": table}, cycle=3)
    late = Recording(rec.t_s, {"x": y}, {"x": np.concatenate([table[-3:], u[:-3]])}, 1e-4, "late")
    with pytest.raises(RecordingMismatch, match="matches 3 point.s. later .a trigger offset.*not learned from"):
        align_to_table(late, {"x": table}, cycle=1)
