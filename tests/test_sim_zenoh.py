"""``afmctl sim --zenoh``: the simulator's true tip position on zenoh ``afm/<scanner>/sim/tip``.

End to end: ``afmctl sim`` as a subprocess listening on a free loopback port, a real zenoh
session in the test connected to it (scouting off), raw MDT693B bytes on the pty; plus the
decimating, never-blocking :class:`afmctl.simulation.service.TipPublisher` and the CLI errors.
"""
from __future__ import annotations

import contextlib
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import serial

from afmctl.zenoh_api.messages import SimTipMsg, decode_json
from afmctl.zenoh_api.settings import ZenohSettings, free_loopback_endpoint
from afmctl.testing import wait_for as _wait_for, stop_process

import zenoh


def _processes_mentioning(text: str) -> list[int]:
    """PIDs whose command line contains ``text`` (to prove nothing was left running)."""
    pids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/cmdline", "rb") as f:
                    if text.encode() in f.read():
                        pids.append(int(entry))
            except OSError:
                pass
    return pids


def _read_until(lines: "queue.Queue[str]", prefix: str, timeout_s: float = 30.0) -> list[str]:
    """Lines from the reader queue up to and including the first one starting with ``prefix``."""
    got: list[str] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            line = lines.get(timeout=max(0.01, deadline - time.monotonic()))
        except queue.Empty:
            break
        got.append(line)
        if line.startswith(prefix):
            return got
    raise AssertionError(f"no line starting with {prefix!r}; got {got!r}")




@contextlib.contextmanager
def _sim(*args):
    """``afmctl sim`` as a subprocess and a queue of its stdout lines (read by a thread)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "afmctl", "sim", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    lines: queue.Queue[str] = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(ln.rstrip("\n")) for ln in proc.stdout],
                              name="sim-stdout", daemon=True)
    reader.start()
    try:
        yield proc, lines
    finally:
        stop_process(proc, timeout_s=5.0)     # still running: the test failed; its stacks, then kill
        reader.join(timeout=5)
        proc.stdout.close()
        proc.stderr.close()


def test_sim_publishes_the_true_tip_position_that_follows_the_amplifier_voltage():
    endpoint = free_loopback_endpoint()
    rate_Hz = 50.0
    with _sim("--zenoh", "--zenoh-listen", endpoint, "--scanner", "t1", "--publish-rate", str(rate_Hz)) as (proc, out):
        lines = _read_until(out, "zenoh:")
        pty_path = lines[0]
        assert pty_path.startswith("/dev/pts/")
        assert lines[-1].startswith(f"zenoh: publishing afm/t1/sim/tip at up to {rate_Hz:g} Hz")
        assert endpoint in lines[-1]

        tips: list[SimTipMsg] = []
        lock = threading.Lock()

        def on_tip(sample):
            msg = decode_json(sample.payload.to_bytes(), SimTipMsg)
            with lock:
                tips.append(msg)

        def snapshot() -> list[SimTipMsg]:
            with lock:
                return list(tips)

        session = zenoh.open(ZenohSettings(listen=[], connect=[endpoint]).to_zenoh_config())
        try:
            sub = session.declare_subscriber("afm/t1/sim/tip", on_tip)
            assert _wait_for(lambda: len(snapshot()) >= 10), "no tip positions arrived"
            before = snapshot()
            x0 = before[-1].position_nm[0]
            assert abs(x0) < 50.0                                # 0 V: the tip is at rest

            with serial.serial_for_url(pty_path, timeout=0.05, write_timeout=1.0) as port:
                port.write(b"XVOLTAGE=50\r")                     # raw MDT693B bytes (echo on)
                reply = b""
                deadline = time.monotonic() + 3.0
                while not reply.endswith(b">") and time.monotonic() < deadline:
                    reply += port.read(max(1, port.in_waiting))
                assert reply.endswith(b">"), reply
            n_cmd = len(snapshot())
            # one more second of simulated time after the command
            assert _wait_for(lambda: len(snapshot()) > n_cmd
                             and snapshot()[-1].t_s - snapshot()[n_cmd].t_s > 1.0, 8.0)
            sub.undeclare()
        finally:
            session.close()
        got = snapshot()

        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
        err = proc.stderr.read()
        assert "Traceback" not in err and "afmctl sim: stopped" in err
        assert "published" in err

    seqs = [m.seq for m in got]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "sequence gap"
    t = np.array([m.t_s for m in got])
    assert np.all(np.diff(t) >= 1.0 / rate_Hz - 1e-9)        # decimated to at most rate_Hz
    assert np.median(np.diff(t)) < 2.0 / rate_Hz               # ... and not much slower
    x = np.array([m.position_nm[0] for m in got])
    late = t >= t[-1] - 0.3
    step = x[late].mean() - x0
    assert step > 1000.0, f"x did not follow 50 V: moved {step:.0f} nm"     # ~3 µm at 50 V
    assert np.ptp(x[late]) < 0.03 * step, "x did not settle"                # only creep left
    assert np.all(np.abs(np.array([m.position_nm[2] for m in got])) < 50.0)  # z stayed at 0 V
    assert _processes_mentioning(endpoint) == []


def test_sim_zenoh_on_a_taken_port_is_a_one_line_error(capsys):
    from afmctl.cli import main
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
        assert main(["sim", "--zenoh-listen", endpoint, "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("afmctl: error: zenoh: cannot open session") and err.count("\n") == 1


@pytest.mark.parametrize("args, field", [
    (["--zenoh-listen", "127.0.0.1:7447"], "--zenoh-listen"),
    (["--zenoh-connect", "tcp/localhost"], "--zenoh-connect"),
    (["--zenoh", "--scanner", "a/b"], "--scanner"),
    (["--zenoh", "--publish-rate", "0"], "--publish-rate"),
    (["--zenoh", "--publish-rate", "nan"], "--publish-rate"),
])
def test_sim_bad_zenoh_arguments_name_the_flag(args, field, capsys):
    from afmctl.cli import main
    assert main(["sim", *args, "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"afmctl: error: {field}") and err.count("\n") == 1, err


def test_sim_settings_zenoh_section_is_off_by_default_and_checked(tmp_path):
    import re

    from afmctl.errors import AfmctlError
    from afmctl.simulation.service import load_settings, scanner_name
    settings = load_settings(None)
    assert settings.zenoh.enabled is False and settings.sim.publish_rate_Hz == 100.0
    assert scanner_name(settings) == "sim0"
    cfg = tmp_path / "sim.toml"
    cfg.write_text('[scanner]\nname = "stage2"\n[sim]\npublish_rate_Hz = 20\n'
                   '[zenoh]\nenabled = true\nlisten = ["tcp/127.0.0.1:7600"]\n')
    settings = load_settings(cfg)
    assert settings.zenoh.enabled and settings.zenoh.listen == ["tcp/127.0.0.1:7600"]
    assert scanner_name(settings) == "stage2" and settings.sim.publish_rate_Hz == 20.0
    cfg.write_text('[zenoh]\nlisten = ["nowhere"]\n')
    with pytest.raises(AfmctlError, match=f"^{re.escape(str(cfg))}: field zenoh.listen"):
        load_settings(cfg)
    cfg.write_text("[sim]\npublish_rate_Hz = 0\n")
    with pytest.raises(AfmctlError, match=r"field sim.publish_rate_Hz = 0: .*allowed: 0.1 <= value <= 10000"):
        load_settings(cfg)


class _Gate:
    """A publish callable that blocks until released (a stalled subscriber/link)."""

    def __init__(self) -> None:
        self.open = threading.Event()
        self.entered = threading.Event()
        self.got: list[tuple[float, np.ndarray]] = []

    def __call__(self, t_s, position_nm) -> None:
        self.entered.set()
        self.open.wait(10.0)
        self.got.append((t_s, position_nm))


def test_tip_publisher_never_blocks_drops_the_oldest_and_drains_on_close():
    from afmctl.simulation.service import TipPublisher
    gate = _Gate()
    tips = TipPublisher(gate, rate_Hz=64.0, queue_size=5).start()
    dt_s = 2.0 ** -10                              # ~1 kHz ticks; binary fractions keep t exact
    try:
        worst = 0.0
        pos = np.zeros(3)
        tips.offer(0.0, pos)
        assert gate.entered.wait(5.0)              # the publisher is now stuck in publish()
        for k in range(1, 2048):                   # 2 s of ticks, decimated to 64 Hz
            pos[0] = k
            t0 = time.perf_counter()
            tips.offer(k * dt_s, pos)
            worst = max(worst, time.perf_counter() - t0)
        assert worst < 0.05                        # the publisher is stuck, offer is not
        assert tips.queued == 128                  # every 16th tick
        assert tips.dropped == 128 - 5 - 1         # one in the gate, the 5 newest queued
    finally:
        gate.open.set()
        tips.close()
    assert tips.published == len(gate.got) == 6
    # the first (already taken) and the five newest survive; every one is a copy
    kept = [0, 1968, 1984, 2000, 2016, 2032]
    assert [t for t, _ in gate.got] == [k * dt_s for k in kept]
    assert [p[0] for _, p in gate.got] == [float(k) for k in kept]
    assert tips.offer(1.0, pos) is False           # closed: nothing more is taken


def test_tip_publisher_decimates_on_simulated_time_and_survives_publish_errors():
    from afmctl.simulation.service import TipPublisher
    got: list[float] = []

    def flaky(t_s, position_nm):
        if len(got) == 2:
            got.append(-1.0)
            raise RuntimeError("link down")
        got.append(t_s)

    with TipPublisher(flaky, rate_Hz=10.0, queue_size=1000) as tips:
        for t in np.arange(0.0, 1.0, 0.013):       # 77 ticks over 1 s
            tips.offer(float(t), [0.0, 0.0, 0.0])
        tips.offer(5.0, [0.0, 0.0, 0.0])           # after a long gap: resynchronised
        tips.offer(5.05, [0.0, 0.0, 0.0])          # too soon after 5.0
        tips.offer(5.15, [0.0, 0.0, 0.0])
        tips.offer(5.2, None)                      # no plant: nothing to publish
    assert tips.errors == 1 and tips.published == len(got) - 1
    times = [t for t in got if t >= 0]
    assert len(times) == 10 + 2 - 1                # 10 per simulated second, one lost to the error
    assert np.all(np.diff(times[:-2]) >= 0.1 - 1e-9)
    assert times[-2:] == [5.0, 5.15]


def test_sim_zenoh_connect_joins_a_listening_peer_and_takes_no_port(capsys):
    """``--zenoh-connect`` alone: the simulator connects to an existing peer (e.g. the one
    of ``afmctl run``) and listens on nothing."""
    from afmctl.cli import main
    endpoint = free_loopback_endpoint()
    got: list[SimTipMsg] = []
    session = zenoh.open(ZenohSettings(listen=[endpoint]).to_zenoh_config())
    try:
        sub = session.declare_subscriber("afm/c1/sim/tip",
                                         lambda s: got.append(decode_json(s.payload.to_bytes(), SimTipMsg)))
        assert main(["sim", "--zenoh-connect", endpoint, "--scanner", "c1", "--duration", "1.0"]) == 0
        sub.undeclare()
    finally:
        session.close()
    out = capsys.readouterr().out
    assert f"zenoh: publishing afm/c1/sim/tip at up to 100 Hz (peer, connect {endpoint})" in out
    assert len(got) >= 10
    seqs = [m.seq for m in got]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
