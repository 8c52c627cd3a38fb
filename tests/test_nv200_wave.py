"""NV200 arbitrary waveform buffer: codec bytes, the simulator's generator on its 50 us clock,
our driver against the simulator over a real pty, and ``afmctl amp --driver nv200 wave``."""
from __future__ import annotations

import time

import numpy as np
import pytest

from afmctl.drivers import codec_nv200_wave as wcodec
from afmctl.drivers.errors import LimitError
from afmctl.drivers.registry import open_amplifier
from afmctl.sim_backend.amplifiers.base import RecordingSink
from afmctl.sim_backend.amplifiers.nv200 import SimNV200
from afmctl.sim_backend.testing import serve_pty


def test_buffer_lines_are_percent_of_the_unit_range_inside_the_limits():
    lines = wcodec.encode_buffer([-20.0, 55.0, 130.0], -20.0, 130.0, -20.0, 130.0)
    assert lines == [b"gbarb,0,0.00000\r\n", b"gbarb,1,50.00000\r\n", b"gbarb,2,100.00000\r\n"]
    (line,) = wcodec.encode_buffer([49.999999], -20.0, 130.0, -20.0, 50.0)
    assert float(line.split(b",")[2]) * 1.5 - 20.0 <= 50.0        # as sent: inside the 50 V limit
    assert wcodec.encode_start(10, 4, 0) == (b"goarb,0\r\ngsarb,0\r\ngearb,9\r\ngcarb,0\r\ngtarb,4\r\n"
                                              b"modsrc,3\r\ngrun,1\r\n")


def test_sim_plays_start_then_loop_indices_on_its_clock():
    clock = [0.0]
    sink = RecordingSink()
    dev = SimNV200(sink, now=lambda: clock[0])
    for cmd in (b"gbarb,0,10\r", b"gbarb,1,20\r", b"gbarb,2,30\r", b"goarb,0\r", b"gsarb,1\r", b"gearb,2\r",
                b"gcarb,3\r", b"gtarb,4\r", b"modsrc,3\r"):
        assert dev.feed(cmd) == b""
    clock[0] = 0.00012
    dev.feed(b"grun,1\r")                            # starts on the next 50 us tick: 150 us
    assert dev.feed(b"grun\r") == b"grun,1\r\n\x11"
    clock[0] = 1.0
    assert dev.feed(b"grun\r") == b"grun,0\r\n\x11"
    assert [h[1]["x"] for h in sink.history] == [-5.0, 10.0, 25.0, 10.0, 25.0, 10.0, 25.0]  # 0 1 2 | 1 2 | 1 2
    assert [h[0] for h in sink.history] == pytest.approx([150e-6 + k * 200e-6 for k in range(7)], abs=1e-12)
    assert dev.wave.played == 7
    assert dev.feed(b"gbarb,1024,5\r") == b"error,4\r\n\x11" and dev.feed(b"gbarb,0,101\r") == b"error,4\r\n\x11"
    assert dev.feed(b"gtarb,0\r") == b"error,4\r\n\x11"


def _ramp(amp, v: float) -> None:
    for u in np.linspace(0, v, 21)[1:]:
        amp.set_voltages({"x": float(u)})


def test_driver_uploads_plays_and_hands_the_setpoint_back_without_a_jump():
    with serve_pty("nv200") as server, open_amplifier("nv200", server.port, max_step_V=1.0) as amp:
        _ramp(amp, 10.0)
        table = 10.0 + 5.0 * np.sin(np.linspace(0, 2 * np.pi, 201))[:-1]
        assert amp.upload_wave("x", table) == 200
        got = -20.0 + np.array(server.device.wave.values[:200]) / 100.0 * 150.0
        assert np.max(np.abs(got - table)) < 1e-3
        before = len(server.sink.history)
        st = amp.start_wave(rate_Hz=10_000, cycles=2)
        assert st.divider == 2 and st.rate_Hz == 10_000
        deadline = time.monotonic() + 5
        while amp.wave_status().running["x"]:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        played = server.sink.history[before:]
        t = np.array([h[0] for h in played])
        assert np.allclose(np.diff(t), 100e-6, atol=1e-9) and len(played) == 399   # sample 0 = 10 V: no change
        assert server.device.params["modsrc"] == 0 and server.device.params["set"] == pytest.approx(table[-1], abs=1e-3)
        assert server.device.outputs["x"] == pytest.approx(table[-1], abs=1e-3)
        amp.set_voltages({"x": float(table[-1]) + 0.5})


def test_driver_refuses_bad_tables_and_rates_before_sending():
    with serve_pty("nv200") as server, open_amplifier("nv200", server.port, max_step_V=1.0,
                                                     host_limits=(0.0, 50.0)) as amp:
        _ramp(amp, 10.0)
        with pytest.raises(LimitError, match=r"sample 3 = 12 V steps 1.5 V from sample 2"):
            amp.upload_wave("x", [10.0, 10.0, 10.5, 12.0])
        with pytest.raises(LimitError, match="the NV200 buffer holds 1024"):
            amp.upload_wave("x", np.full(1025, 10.0))
        with pytest.raises(LimitError, match="sample 1 = 51 V is outside the limits"):
            amp.upload_wave("x", [10.0, 51.0])
        assert server.device.wave.values[:2] == [0.0, 0.0]
        amp.upload_wave("x", [10.0, 10.5])
        with pytest.raises(LimitError, match="3000 Hz is not the servo rate 20000 Hz"):
            amp.start_wave(rate_Hz=3000)
        assert not server.device.wave.params["grun"]


def test_stop_wave_stops_an_endless_run_and_the_output_holds():
    with serve_pty("nv200") as server, open_amplifier("nv200", server.port, max_step_V=1.0) as amp:
        _ramp(amp, 10.0)
        amp.upload_wave("x", np.r_[np.linspace(10, 14, 9), np.linspace(14, 10, 9)[1:-1]])
        assert amp.start_wave(divider=20, cycles=0).running["x"]
        time.sleep(0.05)
        st = amp.stop_wave()
        assert not st.running["x"] and server.device.params["modsrc"] == 0
        held = server.device.outputs["x"]
        # the table travels as percent of the unit's -20..130 V range with PERCENT_DECIMALS
        # decimals: a sample plays within half that step of the voltage asked (14 V came back
        # as 14.000005 V), so the held output lies in the table's range widened by that much
        quantum_V = 0.5 * 10.0 ** -wcodec.PERCENT_DECIMALS / 100.0 * (130.0 - -20.0)
        assert server.device.params["set"] == pytest.approx(held, abs=1e-3)
        assert 10.0 - quantum_V <= held <= 14.0 + quantum_V


def test_amp_wave_cli_with_the_nv200(tmp_path, capsys):
    from afmctl.cli import main
    n = 100
    x = 4.0 + 4.0 * np.sin(np.pi * np.arange(n) / n) ** 2
    path = tmp_path / "w.csv"
    np.savetxt(path, np.column_stack([np.arange(n) / 1000, x]), delimiter=",", header="t,u", comments="",
               fmt="%.6f")
    with serve_pty("nv200") as server:
        assert main(["amp", "--driver", "nv200", "--port", server.port, "--max-step", "5", "wave", "--file",
                     str(path), "--rate-Hz", "5000", "--cycles", "2"]) == 0
        out = capsys.readouterr().out
        assert "played 100 points x 2 cycle(s) on x at 5000 Hz" in out and "every 4 tick(s) of 50 us" in out
        assert server.device.wave.played == 200 and server.device.params["modsrc"] == 0
