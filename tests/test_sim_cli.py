"""``afmctl sim`` as a subprocess: first line is the pty path, the pty speaks MDT693B,
SIGTERM stops it with exit status 0."""
from __future__ import annotations

import contextlib
import os
import select
import signal
import subprocess
import sys
import time

import pytest
import serial

from afmctl.sim_backend.testing import no_leaks
from afmctl.testing import stop_process


def _start(*extra):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "afmctl", "sim", *extra], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


@contextlib.contextmanager
def _running(*extra):
    """``afmctl sim`` as a subprocess; killed at the end if it did not stop itself."""
    proc = _start(*extra)
    try:
        yield proc
    finally:
        stop_process(proc, timeout_s=5.0)     # still running: the test failed; its stacks, then kill


def _first_line(proc, timeout_s=60.0) -> str:
    ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
    assert ready, "afmctl sim printed nothing"
    return proc.stdout.readline().strip()


def _ask(port, cmd: bytes, end: bytes = b">") -> bytes:
    port.write(cmd)
    buf, deadline = b"", time.monotonic() + 2.0
    while not buf.endswith(end) and time.monotonic() < deadline:
        buf += port.read(max(1, port.in_waiting))
    return buf


def _sockets_of(pid: int) -> list[str]:
    out = []
    for fd in os.listdir(f"/proc/{pid}/fd"):
        with contextlib.suppress(OSError):
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
            if target.startswith("socket:"):
                out.append(target)
    return out


def test_sim_prints_the_pty_serves_mdt693b_and_stops_on_sigterm():
    with _running() as proc:
        path = _first_line(proc)
        assert path.startswith("/dev/pts/") and os.path.exists(path)
        assert _sockets_of(proc.pid) == []      # zenoh is off by default: no network port
        with serial.serial_for_url(path, timeout=0.05, write_timeout=1.0) as port:
            assert _ask(port, b"ECHO=0\r") == b"ECHO=0\r>"
            assert _ask(port, b"XVOLTAGE=12.5\r") == b">"
            assert _ask(port, b"XVOLTAGE?\r") == b"[ 12.5]\r>"   # measured output, 0.1 V
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0


def test_sim_with_a_config_file_chooses_the_protocol(tmp_path):
    cfg = tmp_path / "sim.toml"
    cfg.write_text('[amplifier]\nprotocol = "nv200"\nbaud = 57600\n[sim]\ntick_s = 0.02\n')
    with _running("--config", str(cfg)) as proc:
        path = _first_line(proc)
        with serial.serial_for_url(path, timeout=0.05, write_timeout=1.0) as port:
            assert _ask(port, b"avmax\r\n", b"\x11") == b"avmax,130.000\r\n\x11"
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=20) == 0


def test_sim_bad_config_is_a_one_line_error(tmp_path):
    cfg = tmp_path / "sim.toml"
    cfg.write_text('[amplifier]\nprotocol = "foo"\n')
    r = subprocess.run([sys.executable, "-m", "afmctl", "sim", "--config", str(cfg)], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2
    assert r.stderr.startswith(f"afmctl: error: {cfg}: field amplifier.protocol = 'foo'")
    assert "Traceback" not in r.stderr


def test_sim_bad_scanner_override_names_the_field(tmp_path):
    cfg = tmp_path / "sim.toml"
    cfg.write_text("[scanner]\ndt_s = -1.0\n")
    r = subprocess.run([sys.executable, "-m", "afmctl", "sim", "--config", str(cfg)], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2
    assert r.stderr.startswith("afmctl: error: field scanner.dt_s")


def test_sim_service_advances_the_plant_on_the_wall_clock_and_calls_on_tick():
    from afmctl.simulation.service import SimService, load_settings
    ticks = []
    settings = load_settings(None)
    settings.sim.tick_s = 0.02
    service = SimService(settings, on_tick=lambda t, pos: ticks.append((t, pos)))
    with no_leaks(), service:
        assert os.path.islink(service.port) and service.pty_path.startswith("/dev/pts/")
        with serial.serial_for_url(service.port, timeout=0.05, write_timeout=1.0) as port:
            _ask(port, b"ECHO=0\r")
            assert _ask(port, b"XVOLTAGE=30\r") == b">"
        deadline = time.monotonic() + 20.0
        while len(ticks) < 10 and time.monotonic() < deadline:
            time.sleep(0.02)
        wall = service.clock()
    assert len(ticks) >= 10
    times = [t for t, _ in ticks]
    assert times == sorted(times)
    assert ticks[-1][1].shape == (3,)
    assert abs(service.scanner.time_s - wall) < 0.5      # the plant kept up with the wall clock
    assert service.scanner.held_voltage_V()[0] == 30.0
    assert not os.path.exists(service.port)             # cleaned up


def test_make_scanner_uses_the_real_scanner_and_names_a_bad_field():
    from afmctl.errors import AfmctlError
    from afmctl.simulation.service import make_scanner
    from afmctl.sim_backend.scanner import Scanner
    sink, description = make_scanner({})
    assert isinstance(sink, Scanner) and description.startswith("scanner ")
    with pytest.raises(AfmctlError, match=r"^field scanner\.dt_s: "):
        make_scanner({"dt_s": -1.0})


def test_sim_bad_arguments_are_one_line_errors(tmp_path, capsys):
    from afmctl.cli import main
    for args in (["--duration", "nan"], ["--duration", "-1"], ["--baud", "10"],
                 ["--link", str(tmp_path / "missing-dir" / "tty"), "--duration", "0.1"]):
        assert main(["sim", *args]) == 2
        err = capsys.readouterr().err
        assert err.startswith("afmctl: error: ") and err.count("\n") == 1 and "Traceback" not in err


def test_sim_record_file_grows_while_the_simulator_runs(tmp_path):
    """--record is flushed every RECORD_FLUSH_S while running, not only at stop."""
    from afmctl.simulation.service import RECORD_FLUSH_S, SimService, load_settings
    from afmctl.testing import wait_until
    record = tmp_path / "rec.csv"
    service = SimService(load_settings(None), record=record)
    with no_leaks(), service:
        with serial.serial_for_url(service.port, timeout=0.05, write_timeout=1.0) as port:
            _ask(port, b"ECHO=0\r")
            assert _ask(port, b"XVOLTAGE=12.5\r") == b">"

        def rows():
            return record.read_text().splitlines()
        wait_until(lambda: len(rows()) >= 2, 10 * RECORD_FLUSH_S + 5.0, 0.05)
        assert rows()[0] == "t_s,x_V,y_V,z_V" and rows()[-1].split(",")[1] == "12.5"
        assert service._thread is not None and service._thread.is_alive()   # still running


def test_sigusr1_prints_every_threads_stack_and_the_sim_keeps_running():
    """A process that seems stuck explains itself: ``kill -USR1`` prints the stacks to stderr
    (what ``afmctl.testing.stop_process`` asks for before it kills a child)."""
    with _running() as proc:
        assert _first_line(proc).startswith("/")
        proc.send_signal(signal.SIGUSR1)
        time.sleep(0.5)
        assert proc.poll() is None
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "Current thread" in err and "Thread 0x" in err, err


def test_a_wave_table_plays_on_the_simulators_clock_with_no_host_polling():
    """The device's wave generator is played by the simulator's clock thread, not only by
    its server's polls: a server busy with a long reply (or, here, with no client at all)
    must not leave the scanner running past points not yet handed to it (they would be
    dropped, the recorded piezo voltage holding still: issue 38's ``READ_WHILE_PLAYING``)."""
    import numpy as np

    from afmctl.drivers import codec_gcs_wave as wcodec
    from afmctl.simulation.service import SimService, load_settings
    settings = load_settings(None)
    settings.amplifier.protocol, settings.amplifier.tcp = "gcs", "127.0.0.1:0"
    service = SimService(settings)
    ramp = np.round(np.linspace(0.0, 60.0, 2000), 4)     # 2000 points × 10 servo cycles of 50 µs: 1 s
    with no_leaks(), service:
        service.device.feed(b"SVO 1 0 2 0 3 0\n")
        for line in wcodec.encode_wav_pnt(1, ramp, 0, 120):
            service.device.feed(line)
        service.device.feed(wcodec.encode_start([1], 10, 1))
        deadline = time.monotonic() + 10.0
        while service.scanner.held_voltage_V()[0] < 60.0 and time.monotonic() < deadline:
            time.sleep(0.05)
        # nothing was sent to the device meanwhile: only the clock thread played the table
        assert service.scanner.held_voltage_V()[0] == 60.0
        assert service.device.wave.gens[1].played == ramp.size
        assert service.scanner.late_changes == 0            # every point reached the scanner in time


def test_the_scanner_counts_changes_handed_over_in_its_past():
    """What the clock test above relies on: a change played for a time the scanner has
    already simulated past (by more than a sample) is counted, one in its future is not."""
    import numpy as np

    from afmctl.sim_backend.scanner import Scanner, default_scanner_config
    scanner = Scanner(default_scanner_config())
    scanner.advance(0.1)
    scanner.play([0.05, 0.0999999, 0.2], np.full((3, 3), 10.0))
    assert scanner.late_changes == 1


def test_a_signal_another_thread_took_still_stops_a_serving_verb():
    """``afmctl sim`` and ``afmctl router`` wait for Ctrl-C / SIGTERM in their main thread;
    Python runs the handler only there, and a signal the kernel gives to another thread
    (zenoh's, the simulator's) does not wake an untimed wait. ``wait_stopped`` looks again
    every ``POLL_S``: the handler runs within that, not at the end of the duration."""
    import signal
    import threading
    import time

    from afmctl.commands.stopping import POLL_S, wait_stopped
    stop = threading.Event()
    old = signal.signal(signal.SIGUSR1, lambda *_: stop.set())
    try:
        def poke() -> None:
            time.sleep(0.1)
            signal.pthread_kill(threading.get_ident(), signal.SIGUSR1)   # to this thread, not the main one
        t = threading.Thread(target=poke)
        t.start()
        t0 = time.monotonic()
        wait_stopped(stop, 30.0)
        took = time.monotonic() - t0
        t.join(timeout=5)
    finally:
        signal.signal(signal.SIGUSR1, old)
    assert stop.is_set() and took < 10.0 * POLL_S + 5.0 < 30.0
    t0 = time.monotonic()
    wait_stopped(threading.Event(), 0.3)                 # the duration still ends it
    assert 0.25 <= time.monotonic() - t0 < 5.0
