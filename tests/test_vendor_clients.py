"""Back to back with the vendors' own client libraries (python-can's lesson): PIPython,
the ``nv200`` library and the ``mdt69x`` MDT69xB client drive our simulated amplifiers over
real ptys; and the reverse — our drivers against simulators that answer the way those
libraries expect real units to (a sensored NV200, replies 50 ms late).

The ``nv200`` library needs Python >= 3.12: the test builds (once) a venv ``.venv-nv200``
beside the project with the interpreter named by ``AFMCTL_PYTHON312`` or found as
``python3.12``, and runs ``tests/vendor/nv200_client.py`` in it as a subprocess; without
such an interpreter it is skipped and says why.
"""
from __future__ import annotations

import contextlib
import glob
import importlib.util
import inspect
import json
import logging
import math
import os
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial

from afmctl.drivers.registry import open_amplifier
from afmctl.sim_backend.testing import serve_pty
from afmctl.testing import stop_process

ROOT = Path(__file__).resolve().parents[1]
NV200_VENV = ROOT / ".venv-nv200"
NV200_REQUIREMENT = "nv200>=1.6,<2"


# ----------------------------------------------------------------- PIPython → SimGCS
@contextlib.contextmanager
def _pipython(port: str):
    """PIPython's GCSDevice on its pure-Python serial gateway (no PI DLL on Linux)."""
    from pipython import GCSDevice
    from pipython.pidevice.interfaces.piserial import PISerial
    gateway = PISerial(port=port, baudrate=115200)
    try:
        with GCSDevice(gateway=gateway) as dev:  # its exit unregisters the gateway callback
            yield dev
    finally:
        gateway.close()


def test_pipython_connects_fast_and_identifies_a_gcs2_e727():
    with serve_pty("gcs") as server:
        t0 = time.monotonic()
        with _pipython(server.port) as pi:
            idn = pi.qIDN()
            elapsed = time.monotonic() - t0
            assert elapsed < 1.0, f"PIPython needed {elapsed:.2f} s to connect and identify"
            assert pi.devname == "E-727" and "Physik Instrumente" in idn
            assert pi.qCSV() == 2.0
            assert pi.axes == ["1", "2", "3"]
            assert pi.HasqVOL() and pi.HasSVA()  # capability table known for the model: no HLP? round trip


def test_pipython_open_loop_get_set_limits_and_errors():
    from pipython import GCSError
    with serve_pty("gcs") as server:
        with _pipython(server.port) as pi:
            assert pi.qSVO() == {"1": True, "2": True, "3": True}       # servo on at power-up
            with pytest.raises(GCSError) as info:
                pi.SVA("1", 10.0)
            assert info.value.val == 303                                # not in open loop
            pi.SVO(pi.axes, [False, False, False])
            with pytest.raises(GCSError) as info:
                pi.MOV("1", 5.0)
            assert info.value.val == 5                                  # MOV with servo off
            pi.SVA(["1", "2"], [10.0, 20.5])
            assert pi.qSVA()["1"] == pytest.approx(10.0) and pi.qVOL()[2] == pytest.approx(20.5)
            assert pi.qVMI() == {1: 0.0, 2: 0.0, 3: 0.0} and pi.qVMA()[3] == pytest.approx(120.0)
            assert pi.qTMN()["1"] == 0.0 and pi.qTMX()["1"] == 100.0
            assert pi.qPOS()["1"] == pytest.approx(10.0 / 120.0 * 100.0, abs=1e-3)
            with pytest.raises(GCSError) as info:
                pi.SVA("1", 500.0)
            assert info.value.val == 302                                # outside VMI..VMA
            assert pi.qERR() == 0
            assert server.sink.last["x"] == 10.0 and server.sink.last["y"] == 20.5


def test_pipython_wave_generator_plays_on_the_simulated_servo_clock():
    """PIPython's own wave calls: WAV_LIN, pitools.writewavepoints (WAV_PNT bunches), WSL,
    WGC, WTR, TWC, WGO, qWGO, IsGeneratorRunning (#9), waitonwavegen, qWAV, qSPA."""
    from pipython import pitools
    with serve_pty("gcs") as server:
        with _pipython(server.port) as pi:
            pi.SVO(pi.axes, [False, False, False])
            assert pi.qSPA(1, 0x0E000200)[1][0x0E000200] == pytest.approx(50e-6)   # servo update time [s]
            pi.WAV_LIN(table=1, firstpoint=10, numpoints=80, append="X", speedupdown=0, amplitude=40.0,
                       offset=10.0, seglength=100)
            points = [20.0 + 0.1 * k for k in range(250)]
            pitools.writewavepoints(pi, 2, points, bunchsize=60)
            assert pi.qWAV([1, 2], [1, 1]) == {1: {1: 100.0}, 2: {1: 250.0}}
            assert server.device.wave.tables[2] == pytest.approx(points)
            pi.WSL([1, 2], [1, 2])
            # generator 1 runs 20 cycles (0.5 s): still running when the client asks, however loaded
            # the machine; generator 2 one cycle of 250 points (0.125 s)
            pi.WGC([1, 2], [20, 1])
            pi.WTR([1, 2], [5, 10], [0, 0])
            pi.TWC()
            assert pi.qWSL([1, 2]) == {1: 1, 2: 2} and pi.qWGC([1, 2]) == {1: 20, 2: 1}
            assert pi.qWTR([1, 2]) == {1: [5, 0], 2: [10, 0]}
            before = len(server.sink.history)
            pi.WGO([1, 2], [1, 1])
            assert pi.qWGO([1, 2]) == {1: 1, 2: 1} and all(pi.IsGeneratorRunning().values())
            pitools.waitonwavegen(pi, timeout=5, polldelay=0.01)
            assert pi.qWGO([1, 2]) == {1: 0, 2: 0} and pi.qERR() == 0
            assert pi.qVOL()[1] == pytest.approx(50.0) and pi.qVOL()[2] == pytest.approx(points[-1])
    played = server.sink.history[before:]
    t = [h[0] for h in played]
    t0 = min(t)
    # every output change lies on the 50 us servo grid (both generators start on one tick)
    assert all(abs(ti / 50e-6 - round(ti / 50e-6)) < 1e-6 for ti in t)
    ty = [h[0] for h, g in zip(played[1:], played) if h[1]["y"] != g[1]["y"]]       # generator 2's changes
    assert max(ty) - t0 == pytest.approx(249 * 10 * 50e-6, abs=1e-9)
    xs = [h[1]["x"] for h in played]
    assert min(xs) == 10.0 and max(xs) == 50.0


def test_pipython_datarecorder_records_a_wave_from_the_simulated_scanner_sensor():
    """PIPython's datarectools.Datarecorder: servo time and table size from SPA? (after an
    unknown parameter it reads the error and carries on), RTR, DRC (actual position of axis 1,
    its open-loop control value, the piezo voltage of output 1), DRT 0 (start with the wave
    generator), WGO, DRL? (wait), DRR? (the buffered GCS array read in its background
    thread); the actual position is the simulated scanner's position sensor, the piezo
    voltage its amplifier stage's output (the command through 5 kHz and the slew limit; the
    sine's steepest slope, 6.3 kV/s, is within the default scanner's 10 kV/s)."""
    from pipython import datarectools, pitools
    from pipython.datarectools import RecordOptions, TriggerSources
    from afmctl.sim_backend.scanner import Scanner, default_scanner_config
    scanner = Scanner(default_scanner_config())
    points = [30.0 + 20.0 * math.sin(2 * math.pi * k / 200) for k in range(200)]
    with serve_pty("gcs", sink=scanner) as server:
        with _pipython(server.port) as pi:
            pi.SVO(pi.axes, [False, False, False])
            pi.SVA("1", points[0])
            # as a context manager: its exit unregisters the gateway callback it registered (PIPython
            # keeps those callbacks for every gateway; a stale one would fire on the next connection)
            with datarectools.Datarecorder(pi) as drec:
                assert drec.servotime == pytest.approx(50e-6) and drec.maxnumvalues == 262144 // 8
                drec.numvalues = 200
                drec.samplerate = 2
                drec.options = (RecordOptions.ACTUAL_POSITION_2, RecordOptions.OPENLOOP_INPUT_14,
                                RecordOptions.PIEZO_VOLTAGE_7)
                drec.sources = ("1", "1", "1")
                drec.trigsources = TriggerSources.DEFAULT_0
                drec.arm()
                assert pi.qDRC([1, 2, 3]) == {1: ["1", 2], 2: ["1", 14], 3: ["1", 7]}
                assert pi.qRTR() == 2 and pi.qTNR() == 8
                pitools.writewavepoints(pi, 1, points, bunchsize=50)
                pi.WSL(1, 1)
                pi.WGC(1, 1)
                pi.WTR(1, 2, 0)
                pi.WGO(1, 1)
                header, data = drec.getdata(timeout=10)
            assert pi.qERR() == 0
    assert header["NDATA"] == 200 and header["DIM"] == 3 and header["SAMPLE_TIME"] == pytest.approx(100e-6)
    assert "Actual Position" in header["NAME0"] and "Open loop" in header["NAME1"] and "Voltage" in header["NAME2"]
    assert data[1] == pytest.approx(points, abs=1e-4)              # the voltage of each wave point
    # the piezo voltage: point k is read as wave point k goes out, so it holds point k-1
    # through the amplifier's 5 kHz lag (32 us against the 100 us points: settled but not quite)
    lag = [abs(v - p) for v, p in zip(data[2][1:], points)]
    assert 1e-3 < max(lag) < 0.05 * (max(points) - min(points))
    assert max(data[0]) - min(data[0]) > 1.0                       # [µm]: the sensor saw the scanner move


def test_pipython_sees_the_recorder_shared_among_the_tables_it_chose():
    """``SPA 1 0x16000300 n`` as PIPython sends it: TNR? and PIPython's own table size
    (``getmaxnumvalues``: 0x16000200 over 0x16000300) follow; out of range is error 17."""
    from pipython import GCSError, datarectools
    with serve_pty("gcs") as server:
        with _pipython(server.port) as pi:
            pi.SPA("1", 0x16000300, 3)
            assert pi.qTNR() == 3 and datarectools.getmaxnumvalues(pi) == 262144 // 3
            with pytest.raises(GCSError) as err:
                pi.SPA("1", 0x16000300, 9)
            assert err.value.val == 17
            pi.SPA("1", 0x16000300, 8)
            assert pi.qTNR() == 8 and datarectools.getmaxnumvalues(pi) == 262144 // 8 and pi.qERR() == 0


# ------------------------------------------------------------ mdt69x → SimMDT693B
def test_mdt69x_client_gets_sets_and_reads_limits_on_all_three_axes():
    import mdt69x
    with serve_pty("mdt693b") as server:
        c = mdt69x.Controller(server.port)  # probes with an empty line, then cm=1 (MDT693A mode)
        try:
            assert c.get_compatibility() == c.COMPATIBILITY_ON
            assert c.get_switch_limit() == 150.0
            for k, ax in enumerate("xyz"):
                assert getattr(c, f"set_{ax}_voltage")(10.0 + k) == c.SUCCESS
                assert getattr(c, f"get_{ax}_voltage")() == pytest.approx(10.0 + k, abs=0.05)
                assert getattr(c, f"get_{ax}_voltage_min")() == 0.0
                assert getattr(c, f"get_{ax}_voltage_max")() == 150.5
                assert getattr(c, f"set_{ax}_voltage_max")(100.0) == c.SUCCESS
                assert getattr(c, f"get_{ax}_voltage_max")() == 100.0
                getattr(c, f"set_{ax}_voltage")(120.0)                  # clamped by the new limit
                assert getattr(c, f"get_{ax}_voltage")() == pytest.approx(100.0, abs=0.05)
            assert server.sink.last == {"x": 100.0, "y": 100.0, "z": 100.0}
        finally:
            c.close()


@contextlib.contextmanager
def _afmctl_sim(*args: str):
    """``afmctl sim`` as a subprocess (its first line is the pty path); stopped at the end."""
    proc = subprocess.Popen([sys.executable, "-m", "afmctl", "sim", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 120)
        assert ready, "afmctl sim printed nothing"
        yield proc.stdout.readline().strip()
    finally:
        stop_process(proc)


def _approx(v: float):
    return lambda r: r == pytest.approx(v, abs=0.05)   # read-back: the measured output at 0.1 V


def _mdt69x_steps(c, compat: bool) -> list[tuple[str, tuple, object]]:
    """(method, arguments, expected result or a check on it), in order: every call of the
    ``mdt69x`` Controller that behaves the same in both modes, from power-up settings."""
    S, F = c.SUCCESS, c.FAIL
    return [
        ("get_compatibility", (), c.COMPATIBILITY_ON if compat else c.COMPATIBILITY_OFF),
        ("get_echo_status", (), c.ECHO_OFF),
        ("get_switch_limit", (), 150.0),
        ("get_serial_number", (), "SIM00001"),
        ("set_name", ("stage 7",), S),
        ("get_name", (), lambda r: r.strip() == "stage 7"),   # the client keeps the line's CR
        ("get_id", (), lambda r: r is None and c._model == "Model MDT693B" and c._name.strip() == "stage 7"
         and c._serial_number.strip() == "SIM00001" and c._voltage_range == "150V"),
        ("get_available_commands", (), lambda r: any(ln.startswith("MSENABLE?") for ln in c._commands)),
        ("get_intensity", (), 15),
        ("set_intensity", (7,), S),
        ("get_intensity", (), 7),
        ("set_intensity", (99,), S),                              # the client sends 15 instead
        ("get_intensity", (), 15),
        ("get_rotary_mode", (), c.ROTARY_MODE_DEFAULT),
        ("set_rotary_mode", (c.ROTARY_MODE_FINE,), S),
        ("get_rotary_mode", (), c.ROTARY_MODE_FINE),
        # not a mode: not defined, which compatibility mode answers with the bare prompt
        ("set_rotary_mode", (9,), S if compat else F),
        ("get_rotary_mode", (), c.ROTARY_MODE_FINE),
        ("set_rotary_mode", (c.ROTARY_MODE_DEFAULT,), S),
        ("get_push_mode", (), 0),                                 # PUSHDISABLE? 0 (the client calls it OFF)
        ("disable_push_mode", (), S),
        ("get_push_mode", (), 1),
        ("enable_push_mode", (), S),
        ("get_push_mode", (), 0),
        ("set_x_voltage", (10.0,), S), ("set_y_voltage", (11.0,), S), ("set_z_voltage", (12.0,), S),
        ("get_x_voltage", (), _approx(10.0)), ("get_y_voltage", (), _approx(11.0)),
        ("get_z_voltage", (), _approx(12.0)),
        ("get_xyz_voltage", (), lambda r: r == pytest.approx([10.0, 11.0, 12.0], abs=0.05)),
        ("set_all_voltage", (5.0,), S),
        ("get_xyz_voltage", (), lambda r: r == pytest.approx([5.0, 5.0, 5.0], abs=0.05)),
        ("set_xyz_voltage", (20.0, 21.0, 22.0), S),
        ("get_xyz_voltage", (), lambda r: r == pytest.approx([20.0, 21.0, 22.0], abs=0.05)),
        ("get_master_scan_state", (), c.MASTER_SCAN_OFF),
        # the client refuses until its own enable_master_scan() (its disable never clears that)
        ("set_master_voltage", (30.0,), S if c._master_scan_enabled else 0),
        ("enable_master_scan", (), S),
        ("get_master_scan_state", (), c.MASTER_SCAN_ON),
        ("set_master_voltage", (30.0,), S),
        ("get_master_voltage", (), _approx(30.0)),
        ("get_x_voltage", (), _approx(50.0)),                     # master scan adds to every channel
        ("get_xyz_voltage", (), lambda r: r == pytest.approx([50.0, 51.0, 52.0], abs=0.05)),
        ("disable_master_scan", (), S),
        ("get_master_scan_state", (), c.MASTER_SCAN_OFF),
        ("get_z_voltage", (), _approx(22.0)),
        ("get_x_voltage_min", (), 0.0), ("get_y_voltage_min", (), 0.0), ("get_z_voltage_min", (), 0.0),
        ("get_x_voltage_max", (), 150.5), ("get_y_voltage_max", (), 150.5), ("get_z_voltage_max", (), 150.5),
        ("get_sys_voltage_max", (), 150.5),
        ("set_x_voltage_max", (100.0,), S), ("set_y_voltage_max", (101.0,), S), ("set_z_voltage_max", (102.0,), S),
        ("get_x_voltage_max", (), 100.0), ("get_y_voltage_max", (), 101.0), ("get_z_voltage_max", (), 102.0),
        ("set_x_voltage", (120.0,), S),
        ("get_x_voltage", (), _approx(100.0)),                    # clamped by the new limit
        ("set_x_voltage_min", (3.0,), S), ("set_y_voltage_min", (4.0,), S),
        ("get_x_voltage_min", (), 3.0), ("get_y_voltage_min", (), 4.0),
        ("set_z_voltage_min", (6.0,), S),                         # the client sends SYSMIN= here
        ("get_x_voltage_min", (), 6.0), ("get_sys_voltage_min", (), 6.0),
        ("set_sys_voltage_max", (90.0,), S),
        ("get_sys_voltage_max", (), 90.0), ("get_y_voltage_max", (), 90.0),
        ("restore_all", (), S),
        ("get_x_voltage_max", (), 150.5), ("get_z_voltage_min", (), 0.0),
        ("set_echo_off", (), S),
    ]


def _run_steps(c, steps) -> set[str]:
    for k, (name, args, want) in enumerate(steps):
        got = getattr(c, name)(*args)
        ok = want(got) if callable(want) else got == want
        assert ok, f"step {k}: {name}{args} returned {got!r}, expected {want!r}"
    return {name for name, _, _ in steps}


def test_mdt69x_client_passes_every_call_it_has_against_afmctl_sim(capsys):
    """Every public method of ``mdt69x.Controller``, in MDT693A compatibility mode (where the
    client puts the unit) and in the normal mode, against ``afmctl sim``; a method this table
    does not call fails the test (a new client version must be covered)."""
    import mdt69x
    public = {n for n, f in inspect.getmembers(mdt69x.Controller, inspect.isfunction) if not n.startswith("_")}
    with _afmctl_sim("--protocol", "mdt693b") as port:
        c = mdt69x.Controller(port)   # probes with an empty line, then echo off and cm=1
        try:
            called = _run_steps(c, _mdt69x_steps(c, compat=True))
            assert c.set_compatibility_off() == c.SUCCESS
            called |= _run_steps(c, _mdt69x_steps(c, compat=False))
            assert c.set_compatibility_on() == c.SUCCESS and c.get_compatibility() == c.COMPATIBILITY_ON
            called |= {"set_compatibility_off", "set_compatibility_on"}
        finally:
            c.close()
        called.add("close")
    printed = capsys.readouterr().out
    assert "Model MDT693B" in printed and "INTENSITY?" in printed and "Master Scan not enabled" in printed
    assert public - called == set(), f"mdt69x calls not exercised: {sorted(public - called)}"


def test_herosdevices_mdt69xb_wire_format():
    """What herosdevices' MDT693B/MDT694B driver sends and parses (read from its source; the
    package itself pulls in GPIO/laser SDKs, so its bytes are replayed here): ``echo=0`` at
    connect, lower-case ``xvoltage=``/``xmin=``/``xmax=`` sets, and queries read up to the
    first CR, brackets stripped for the voltages."""
    with serve_pty("mdt693b") as server:
        with serial.serial_for_url(server.port, baudrate=115200, timeout=1.0) as port:
            def send(cmd: str) -> bytes:
                port.reset_input_buffer()
                port.write(cmd.encode("ascii") + b"\r")
                return port.read_until(b"\r") if cmd.endswith("?") else port.read_until(b">")

            send("echo=0")
            for ax, v in zip("xyz", (12.5, 40.0, 99.9)):
                assert send(f"{ax}voltage={v}") == b">"
                assert float(send(f"{ax}voltage?").decode().strip("[]\r")) == pytest.approx(v, abs=0.05)
                assert send(f"{ax}max=120") == b">" and send(f"{ax}min=2") == b">"
                assert float(send(f"{ax}max?").decode().rstrip()) == 120.0
                assert float(send(f"{ax}min?").decode().rstrip()) == 2.0
        assert server.sink.last == pytest.approx({"x": 12.5, "y": 40.0, "z": 99.9})


def test_our_driver_after_a_client_left_the_unit_in_compatibility_mode():
    import mdt69x
    with serve_pty("mdt693b") as server:
        mdt69x.Controller(server.port).close()
        assert server.device.compat
        with open_amplifier("mdt693b", server.port) as amp:
            amp.set_voltages({"x": 12.0, "y": 13.0, "z": 14.0})
            assert amp.get_voltages() == pytest.approx({"x": 12.0, "y": 13.0, "z": 14.0}, abs=0.05)
            assert amp.info()["prompt"] == "*"


# ----------------------------------------------------------------- nv200 → SimNV200
def _python312() -> str | None:
    for cand in (os.environ.get("AFMCTL_PYTHON312"), shutil.which("python3.12"),
                 *sorted(glob.glob("/root/.pyenv/versions/3.12*/bin/python3.12"))):
        # a pyenv shim exists even where that version is not selected: it must really run
        if cand and Path(cand).exists() and subprocess.run([cand, "--version"], capture_output=True,
                                                           timeout=30).returncode == 0:
            return cand
    return None


@pytest.fixture(scope="session")
def nv200_python() -> str:
    if sys.version_info >= (3, 12) and importlib.util.find_spec("nv200") is not None:
        return sys.executable  # installed with the test extra
    py = NV200_VENV / "bin" / "python"
    if py.exists() and subprocess.run([str(py), "-c", "import nv200"], capture_output=True).returncode == 0:
        return str(py)
    base = _python312()
    if base is None:
        pytest.skip("the nv200 library needs Python >= 3.12: no python3.12 found "
                    "(set AFMCTL_PYTHON312 to one)")
    subprocess.run([base, "-m", "venv", str(NV200_VENV)], check=True, timeout=300)
    res = subprocess.run([str(py), "-m", "pip", "install", "-q", NV200_REQUIREMENT],
                         capture_output=True, text=True, timeout=900)
    if res.returncode != 0:
        pytest.skip(f"could not install {NV200_REQUIREMENT} into {NV200_VENV}: {res.stderr.strip()[-300:]}")
    return str(py)


@pytest.mark.slow
@pytest.mark.parametrize("sensor", ["none", "strain gauge"])
def test_nv200_library_connects_sets_and_reads(nv200_python, sensor):
    client = ROOT / "tests" / "vendor" / "nv200_client.py"
    with serve_pty("nv200", sensor=sensor) as server:
        res = subprocess.run([nv200_python, str(client), server.port, "52"], capture_output=True,
                             text=True, timeout=120)
        assert res.returncode == 0, res.stderr[-2000:]
        out = json.loads(res.stdout.strip().splitlines()[-1])
        assert out["voltage_range_V"] == [-20.0, 130.0]
        assert out["setpoint"] == 52.0
        assert out["piezo_voltage_V"] == 52.0                      # the recorder's piezo voltage
        assert out["temperature_C"] > 0 and out["actuator"]
        if sensor == "none":
            assert out["meas"] == 52.0 and out["status_word"] & 0b110 == 0
        else:                                                      # meas is the position [µm]
            assert out["meas"] == pytest.approx((52 + 20) / 150 * 100, abs=1e-3)
            assert out["status_word"] & 0b110 == 0b010 and out["position_unit"] == "um"
        assert server.sink.last == {"x": 52.0}


# ------------------------------------------------------- our drivers, the reverse way
@pytest.mark.parametrize("sensor", ["strain gauge", "capacitive"])
def test_sensored_nv200_get_voltages_returns_volts(sensor):
    with serve_pty("nv200", sensor=sensor) as server:
        server.device.params["modsrc"] = 0        # nothing for the driver to change
        server.device.outputs["x"] = 0.0
        with open_amplifier("nv200", server.port) as amp:
            assert amp.info()["sensor"] == sensor
            assert amp.last_output == {"x": 0.0}  # the output, not the position (13.3 µm here)
            amp.set_voltages({"x": 52.0})
            assert amp.get_voltages() == {"x": 52.0}
            assert server.device.stored_writes == []  # cl and modsrc were 0: nothing written


def _count_first_run(dev, n: int):
    """Wrap the simulator's waveform generator: remember when the first ``n`` samples played."""
    inner = dev.wave.take_due
    dev.first_run_s = []

    def take_due(now_s: float):
        t, values = inner(now_s)
        dev.first_run_s.extend(t.tolist()[:max(0, n - len(dev.first_run_s))])
        return t, values
    return take_due


@pytest.mark.slow
def test_nv200_library_waveform_generator_uploads_and_runs_on_the_simulated_clock(nv200_python):
    """The library's WaveformGenerator: set_waveform (gbarb writes in % of the voltage range,
    gtarb, goarb/gsarb/gearb), start(cycles) (gcarb, modsrc 3, grun), is_running, waiting."""
    client = ROOT / "tests" / "vendor" / "nv200_wave_client.py"
    with serve_pty("nv200") as server:
        before = len(server.sink.history)
        server.device.wave.take_due = _count_first_run(server.device, 3 * 12)
        res = subprocess.run([nv200_python, str(client), server.port, "3"], capture_output=True,
                             text=True, timeout=120)
        assert res.returncode == 0, res.stderr[-2000:]
        out = json.loads(res.stdout.strip().splitlines()[-1])
        dev = server.device
    n, factor = out["points"], dev.wave.params["gtarb"]
    assert out["loop"] == {"start_index": 0, "loop_start_index": 0, "loop_end_index": n - 1}
    assert factor * 0.05 == pytest.approx(out["sample_time_ms"])
    assert out["finished"] and not out["running_at_end"]
    assert out["endless_running"] and not out["running_after_stop"]
    assert dev.params["modsrc"] == 3 and dev.wave.played > 3 * n
    want = [-20.0 + p / 100.0 * 150.0 for p in out["readback_pct"]]
    assert want == pytest.approx(out["values_V"][:4], abs=1e-3)
    played = server.sink.history[before:]
    t = [h[0] for h in played]
    step_s = factor * 50e-6
    first = dev.first_run_s                                        # the 3-cycle run: 36 samples back to back
    assert len(first) == 3 * n and first[-1] - first[0] == pytest.approx((3 * n - 1) * step_s, abs=1e-9)
    assert all(abs(ti / 50e-6 - round(ti / 50e-6)) < 1e-6 for ti in t)       # on the unit's 50 us clock
    assert max(h[1]["x"] for h in played) == pytest.approx(50.0, abs=0.05)
    assert min(h[1]["x"] for h in played) == pytest.approx(10.0, abs=0.05)


@pytest.mark.slow
def test_nv200_library_data_recorder_records_a_waveform_run_from_the_simulated_sensor(nv200_python):
    """The library's DataRecorder: recsrc (position, piezo voltage), recast 2 (start with the
    waveform generator), recstr, reclen, recrun (arm, then poll until 0), recoutf of both
    channels; the position is the simulated scanner's sensor [µm], the piezo voltage its
    amplifier stage's output (5 ms points: steps of at most 20 V settle within one)."""
    from afmctl.sim_backend.scanner import Scanner, default_scanner_config
    client = ROOT / "tests" / "vendor" / "nv200_recorder_client.py"
    scanner = Scanner(default_scanner_config())
    with serve_pty("nv200", sink=scanner, sensor="strain gauge") as server:
        res = subprocess.run([nv200_python, str(client), server.port, "2"], capture_output=True,
                             text=True, timeout=180)
        assert res.returncode == 0, res.stderr[-2000:]
        out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["finished"] and out["sources"] == [0, 2] and out["sample_time_ms"] == pytest.approx(5.0)
    assert len(out["position"]) == len(out["voltage"]) == 24
    # point k is read as buffer point k goes out: the piezo holds point k-1, settled (point 1
    # is still slewing from the 0 V before the run up to the first point's 60 V)
    assert out["voltage"][0] == pytest.approx(0.0, abs=0.01) and 0.0 < out["voltage"][1] < 60.0
    assert out["voltage"][2:] == pytest.approx((out["values_V"] * 2)[1:-1], abs=0.05)
    pos = out["position"]                                                  # µm: the scanner moved
    assert max(pos) - min(pos) > 2.0


def test_nv200_stored_settings_are_changed_only_when_needed_said_and_restored_on_request(caplog):
    with serve_pty("nv200") as server:
        server.device.params["cl"] = 1            # closed loop, analog input (power-up default)
        with caplog.at_level(logging.WARNING, logger="afmctl.drivers.nv200"):
            amp = open_amplifier("nv200", server.port, restore_settings=True)
        assert "cl was 1" in caplog.text and "modsrc was 1" in caplog.text
        assert amp.info()["changed_settings"] == {"cl": 1, "modsrc": 1}
        amp.set_voltages({"x": 5.0})
        amp.close()
        assert server.device.stored_writes == [("cl", 0), ("modsrc", 0), ("cl", 1), ("modsrc", 1)]
    with serve_pty("nv200") as server:
        with open_amplifier("nv200", server.port) as amp:  # default: leave them, and say so
            amp.set_voltages({"x": 5.0})
        assert server.device.stored_writes == [("modsrc", 0)]


@pytest.mark.slow
@pytest.mark.parametrize("driver", ["mdt693b", "gcs", "nv200"])
def test_connect_twenty_times_out_of_twenty_with_replies_50_ms_late(driver):
    ok = 0
    with serve_pty(driver, latency_s=0.05) as server:
        for _ in range(20):
            with open_amplifier(driver, server.port, timeout_s=0.5) as amp:
                amp.get_voltages()
                ok += 1
    assert ok == 20


@pytest.mark.parametrize("latency_s", [0.016, 0.12])   # a USB adapter's latency timer; serial over IP
@pytest.mark.parametrize("driver", ["mdt693b", "gcs", "nv200"])
def test_connect_with_late_replies(driver, latency_s):
    with serve_pty(driver, latency_s=latency_s) as server:
        with open_amplifier(driver, server.port, timeout_s=0.5) as amp:
            amp.set_voltages({"x": 10.0})
            assert amp.get_voltages()["x"] == pytest.approx(10.0, abs=amp.readback_resolution_V / 2 + 1e-9)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))
