"""``afmctl amp`` against simulated amplifiers (real ptys, real CAN virtual bus)."""
from __future__ import annotations

import uuid

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.sim_backend.testing import serve_can, serve_pty


@pytest.fixture
def mdt():
    with serve_pty("mdt693b") as server:
        yield server


def write_csv(path, header, rows):
    path.write_text(header + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in rows) + "\n")
    return str(path)


def test_info_get_set(mdt, capsys):
    base = ["amp", "--driver", "mdt693b", "--port", mdt.port, "--timeout", "0.3"]
    assert main(base + ["info"]) == 0
    out = capsys.readouterr().out
    assert "driver: mdt693b" in out and "limits_V" in out and "Model MDT693B" in out
    assert main(base + ["set", "x=10", "z=20.5"]) == 0
    assert "x=10.0000 V" in capsys.readouterr().out
    assert mdt.device.outputs == {"x": 10.0, "y": 0.0, "z": 20.5}
    assert main(base + ["get"]) == 0
    assert "z=20.5000 V" in capsys.readouterr().out


def test_set_outside_limits_is_refused_with_exit_2(mdt, capsys):
    base = ["amp", "--driver", "mdt693b", "--port", mdt.port, "--timeout", "0.3"]
    assert main(base + ["--limit", "0:100", "--limit", "y=0:50", "set", "y=60"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("afmctl: error:") and "[0, 50]" in err
    assert main(base + ["set", "x=151"]) == 2
    assert mdt.sink.count == 0  # nothing was sent


def test_stream_three_axes_in_order_and_reports_the_rate(mdt, tmp_path, capsys):
    n = 300
    u = np.column_stack([np.linspace(0, 30, n), np.linspace(5, 6, n), np.full(n, 7.0)])
    path = write_csv(tmp_path / "v.csv", "t,ux,uy,uz", np.column_stack([np.arange(n) * 1e-3, u]))
    assert main(["amp", "--driver", "mdt693b", "--port", mdt.port, "stream", "--file", path]) == 0
    out = capsys.readouterr().out
    assert f"sent {n} setpoints" in out and "setpoints/s" in out
    xs = [v["x"] for _, v in mdt.sink.history]
    assert xs == sorted(xs) and xs[-1] == 30.0  # every row, in order
    assert len(mdt.sink.history) == n


def test_stream_single_axis_at_a_rate(mdt, tmp_path, capsys):
    n = 40
    path = write_csv(tmp_path / "v.csv", "t,u", np.column_stack([np.arange(n) * 1e-2, np.linspace(1, 2, n)]))
    assert main(["amp", "--driver", "mdt693b", "--port", mdt.port, "stream", "--file", path,
                 "--axis", "y", "--rate", "200"]) == 0
    out = capsys.readouterr().out
    rate = float(out.split("s: ")[1].split(" setpoints/s")[0])
    assert rate <= 205          # the pacing holds: never faster than --rate (+ the first row's head start)
    assert rate > 40            # and not stalled (generous: the machine may be busy)
    assert mdt.device.outputs["y"] == 2.0


def test_stream_with_a_value_outside_the_limits_sends_nothing(mdt, tmp_path, capsys):
    vals = np.array([1.0, 2.0, 151.0, 3.0])
    path = write_csv(tmp_path / "v.csv", "t,u", np.column_stack([np.arange(4.0), vals]))
    assert main(["amp", "--driver", "mdt693b", "--port", mdt.port, "stream", "--file", path]) == 2
    err = capsys.readouterr().err
    assert "row 4" in err and "column u" in err and "nothing was sent" in err
    assert mdt.sink.count == 0


def test_bad_files_and_arguments_are_one_line_errors(mdt, tmp_path, capsys):
    path = write_csv(tmp_path / "v.csv", "t,volts", [[0, 1]])
    assert main(["amp", "--driver", "mdt693b", "--port", mdt.port, "stream", "--file", path]) == 2
    assert "t,u" in capsys.readouterr().err
    assert main(["amp", "--driver", "mdt693b", "--port", "/nonexistent/tty", "info"]) == 2
    assert "cannot open" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["amp", "--driver", "mdt693b", "--port", mdt.port, "set", "x=abc"])


def test_can_driver_from_the_cli(capsys):
    channel = f"cli-{uuid.uuid4().hex[:8]}"
    with serve_can(channel) as sim:
        assert main(["amp", "--driver", "can", "--port", f"virtual:{channel}", "set", "x=1.25", "y=2.5"]) == 0
        assert "y=2.5000 V" in capsys.readouterr().out
        assert sim.outputs == {"x": 1.25, "y": 2.5, "z": 0.0}


def test_stream_refuses_steps_above_max_step_before_sending(mdt, tmp_path, capsys):
    path = write_csv(tmp_path / "v.csv", "t,u", [[0, 1.0], [1, 2.0], [2, 9.0]])
    assert main(["amp", "--driver", "mdt693b", "--port", mdt.port, "--max-step", "5", "stream", "--file", path]) == 2
    err = capsys.readouterr().err
    assert "row 4" in err and "max-step" in err
    assert mdt.sink.count == 0


def test_stream_keeps_the_time_column(mdt, tmp_path, capsys):
    """A 0.5 s file of 26 rows (50 Hz) takes its 0.5 s, not as long as the link allows."""
    n = 26
    path = write_csv(tmp_path / "v.csv", "t,u", np.column_stack([10.0 + np.arange(n) * 0.02, np.linspace(1, 2, n)]))
    assert main(["amp", "--driver", "mdt693b", "--port", mdt.port, "stream", "--file", path]) == 0
    cap = capsys.readouterr()
    elapsed = float(cap.out.split(" in ")[1].split(" s:")[0])
    assert 0.5 <= elapsed < 2.0                     # never early; generous on a busy machine
    assert "schedule 0.500 s" in cap.out and "warning" not in cap.err
    assert len(mdt.sink.history) == n


def test_stream_warns_when_the_rate_is_not_reached(mdt, tmp_path, capsys):
    """1000 rows at 1 MHz cannot go over a 115200-baud pty: the run says so."""
    n = 1000
    path = write_csv(tmp_path / "v.csv", "t,u", np.column_stack([np.arange(n) * 1e-6, np.full(n, 3.0)]))
    assert main(["amp", "--driver", "mdt693b", "--port", mdt.port, "stream", "--file", path]) == 0
    err = capsys.readouterr().err
    assert "warning: the t column of" in err and "was not kept" in err and err.count("\n") == 1
    assert main(["amp", "--driver", "mdt693b", "--port", mdt.port, "stream", "--file", path, "--rate", "1e6"]) == 0
    assert "warning: --rate 1e+06 Hz was not kept" in capsys.readouterr().err


def test_stream_has_a_default_step_limit(mdt, tmp_path, capsys):
    path = write_csv(tmp_path / "v.csv", "t,u", [[0, 1.0], [0.01, 2.0], [0.02, 40.0]])
    assert main(["amp", "--driver", "mdt693b", "--port", mdt.port, "stream", "--file", path]) == 2
    err = capsys.readouterr().err
    assert "row 4" in err and "exceeds --max-step 10 V" in err and "nothing was sent" in err
    assert mdt.sink.count == 0
    assert main(["amp", "--driver", "mdt693b", "--port", mdt.port, "--max-step", "50", "stream",
                 "--file", path]) == 0
    assert mdt.device.outputs["x"] == 40.0


def test_wave_plays_a_file_on_the_amplifier_clock_for_n_cycles(tmp_path, capsys):
    from afmctl.sim_backend.amplifiers.base import RecordingSink
    n, rate = 200, 2000
    x = 20.0 + 5.0 * np.sin(2 * np.pi * np.arange(n) / n)
    path = write_csv(tmp_path / "w.csv", "t,ux,uy,uz", np.column_stack([np.arange(n) / rate, x,
                                                                       np.full(n, 3.0), np.full(n, 4.0)]))
    channel = f"wave-{uuid.uuid4().hex[:8]}"
    sink = RecordingSink(max_history=100_000)
    with serve_can(channel, sink) as sim:
        assert main(["amp", "--driver", "can", "--port", f"virtual:{channel}", "--max-step", "25", "wave",
                     "--file", path, "--rate-Hz", str(rate), "--cycles", "3"]) == 0
        out = capsys.readouterr().out
        assert f"played {3 * n} samples (3 cycle(s)) at 2000 Hz" in out and " 0 underrun(s)" in out
        played = [(t, v) for t, v in sink.history if t >= sim.stream.t0_s]
        assert len(played) == 3 * n
        assert [t for t, _ in played] == [sim.stream.t0_s + k / rate for k in range(3 * n)]
        assert np.max(np.abs(np.array([v["x"] for _, v in played]) - np.tile(x, 3))) <= 0.00125 + 1e-9


def test_wave_refuses_bad_arguments_a_bad_wrap_and_other_drivers(mdt, tmp_path, capsys):
    path = write_csv(tmp_path / "w.csv", "t,u", [(0.0, 1.0), (0.001, 5.0), (0.002, 9.0)])  # steps 4 V
    channel = f"wave-{uuid.uuid4().hex[:8]}"
    with serve_can(channel) as sim:
        base = ["amp", "--driver", "can", "--port", f"virtual:{channel}", "--max-step", "10", "wave", "--file", path]
        assert main(base + ["--rate-Hz", "1000.5"]) == 2
        assert "--rate-Hz: 1000.5 must be a whole number" in capsys.readouterr().err
        assert main(base + ["--rate-Hz", "1000", "--cycles", "0"]) == 2
        assert main(["amp", "--driver", "can", "--port", f"virtual:{channel}", "--max-step", "5", "wave",
                     "--file", path, "--rate-Hz", "1000", "--cycles", "2"]) == 2
        assert "the wrap from the last row to the first is 8 V" in capsys.readouterr().err
        assert main(["amp", "--driver", "can", "--port", f"virtual:{channel}", "wave", "--file", path,
                     "--rate-Hz", "1000", "--cycles", "2", "--max-step", "5"]) == 2     # after the action too
        assert "the wrap from the last row to the first is 8 V" in capsys.readouterr().err
        assert sim.stream.played == 0 and sim.received == 0
    assert main(["amp", "--driver", "mdt693b", "--port", mdt.port, "wave", "--file", path, "--rate-Hz", "100"]) == 2
    assert "wave works with --driver can" in capsys.readouterr().err


@pytest.mark.parametrize("driver", ["gcs", "can"])
def test_wave_record_writes_the_measured_motion_as_a_motion_file(driver, tmp_path, capsys):
    from afmctl.data.motion_files import read_motion_csv
    from afmctl.sim_backend.scanner import Scanner, default_scanner_config
    n, rate = 200, 10_000
    x = 60.0 + 30.0 * np.sin(2 * np.pi * np.arange(n) / n)
    path = write_csv(tmp_path / "w.csv", "t,ux,uy,uz", np.column_stack([np.arange(n) / rate, x,
                                                                       np.full(n, 3.0), np.full(n, 4.0)]))
    out_csv = tmp_path / "motion.csv"
    scanner = Scanner(default_scanner_config())
    if driver == "can":
        channel = f"rec-{uuid.uuid4().hex[:8]}"
        server_cm, port = serve_can(channel, scanner), f"virtual:{channel}"
    else:
        server_cm = serve_pty("gcs", sink=scanner)
        port = None
    with server_cm as server:
        port = port or server.port
        assert main(["amp", "--driver", driver, "--port", port, "--max-step", "100", "wave", "--file", path,
                     "--rate-Hz", str(rate), "--record", str(out_csv)]) == 0
    out = capsys.readouterr().out
    assert f"recorded {n} points every 100 us" in out and str(out_csv) in out
    rec = read_motion_csv(out_csv)
    if driver == "gcs":        # the x, y, z columns: three axes recorded
        assert set(rec.y_nm) == {"x", "y", "z"}
    assert len(rec) == n and rec.period_s == pytest.approx(1e-4)
    np.testing.assert_allclose(rec.u_V["x"], x, atol=0.002)
    assert np.ptp(rec.y_nm["x"]) > 2000.0


def test_wave_record_is_refused_on_a_device_without_a_recorder(mdt, tmp_path, capsys):
    path = write_csv(tmp_path / "w.csv", "t,u", [(0.0, 1.0), (0.001, 2.0)])
    assert main(["amp", "--driver", "mdt693b", "--port", mdt.port, "wave", "--file", path, "--rate-Hz", "100",
                 "--record", str(tmp_path / "m.csv")]) == 2
    err = capsys.readouterr().err
    assert "afmctl: error:" in err and "no data recorder" in err and "external sensor" in err


def test_a_refused_first_row_says_it_is_measured_from_the_output_and_how_to_pass(mdt, tmp_path, capsys):
    """The README's tour: after set x=10, a file starting at 21.6 V is a step from the present
    output (not between rows); the message names the fix, and --max-step after the action works."""
    path = write_csv(tmp_path / "v.csv", "t,u", [[0, 21.6], [0.01, 22.0], [0.02, 22.4]])
    base = ["amp", "--driver", "mdt693b", "--port", mdt.port]
    assert main(base + ["set", "x=10"]) == 0
    capsys.readouterr()
    assert main(base + ["stream", "--file", path]) == 2
    err = capsys.readouterr().err
    assert "row 2" in err and "from the present output of axis x (10 V)" in err and "--max-step 11.6" in err
    assert "set x=21.6" in err and err.count("\n") == 1
    assert main(base + ["stream", "--file", path, "--max-step", "11.6"]) == 0
    assert mdt.device.outputs["x"] == 22.4


def test_stream_help_lists_max_step(capsys):
    with pytest.raises(SystemExit):
        main(["amp", "--driver", "mdt693b", "--port", "x", "stream", "--help"])
    out = capsys.readouterr().out
    assert "--max-step V" in out and "present output" in out and "115200 baud" in out


def test_refusals_name_the_fix(mdt, tmp_path, capsys):
    base = ["amp", "--driver", "mdt693b", "--port", mdt.port]
    path = write_csv(tmp_path / "v.csv", "t,u", [[0, 0.0], [0.01, 60.0]])
    assert main(base + ["--limit", "0:50", "stream", "--file", path]) == 2
    err = capsys.readouterr().err
    assert "outside the limits [0, 50] V" in err and "narrowed by --limit" in err
    assert "afmctl compensate ... --limits 0 50 --clip" in err
    assert main(base + ["stream", "--file", path]) == 2
    assert "step of 60 V from the row before" in (err := capsys.readouterr().err) and "--max-step 60 " in err
    assert main(base + ["--max-step", "5", "set", "x=30"]) == 2
    err = capsys.readouterr().err
    assert "set x=30: a step of 30 V from the present output" in err and "--max-step 30" in err
    assert "max_step_V" not in err
    assert mdt.sink.count == 0


def test_info_over_tcp_shows_no_baud_rate(capsys):
    from afmctl.sim_backend.amplifiers import RecordingSink, make_device
    from afmctl.sim_backend.amplifiers.tcp_server import TcpServer
    with TcpServer(make_device("gcs", RecordingSink())) as server:
        assert main(["amp", "--driver", "gcs", "--port", server.port, "info"]) == 0
    out = capsys.readouterr().out
    assert "baudrate" not in out and "link: TCP (no baud rate)" in out
    assert "device_limits_V: {'x': [0.0, 120.0]" in out       # the range the controller reports


def test_nv200_settings_advice_speaks_the_command_line(tmp_path, capsys, caplog):
    with serve_pty("nv200") as server:
        base = ["amp", "--driver", "nv200", "--port", server.port]
        assert main(base + ["set", "x=5"]) == 0
        err = capsys.readouterr().err + caplog.text
        assert "--restore-settings" in err and "restore_settings=True" not in err
        server.device.params["modsrc"] = 1        # as stored in the unit, e.g. after a power cycle
        assert main(base + ["--restore-settings", "set", "x=6"]) == 0
        assert server.device.params["modsrc"] == 1          # written back at the end
    assert main(["amp", "--driver", "gcs", "--port", "x", "--restore-settings", "info"]) == 2
    assert "only --driver nv200" in capsys.readouterr().err
