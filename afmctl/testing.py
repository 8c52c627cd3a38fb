"""Helpers for tests of afmctl and of programs built on it (shipped in the package, as
ophyd-async does). Simulated devices to test against live in :mod:`afmctl.sim_backend.testing`."""
from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any


def wait_for(cond: Callable[[], object], timeout_s: float = 10.0, interval_s: float = 0.01) -> bool:
    """Poll ``cond()`` every ``interval_s`` seconds until it is true or ``timeout_s``
    seconds have passed; return its last truth value (one final check after the timeout)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(interval_s)
    return bool(cond())


def assert_no_threads_left(prefix: str = "afmctl-", timeout_s: float = 2.0) -> None:
    """Fail unless every thread whose name starts with ``prefix`` (the controller's,
    the run log's, the zenoh bridge's) has ended within ``timeout_s`` seconds. What leaked is
    stopped before the failure is raised (:func:`stop_leaked_threads`), so that one leak
    does not starve the tests after it."""
    leaked, survivors = stop_leaked_threads(prefix, timeout_s)
    if leaked:
        raise AssertionError(f"threads left running: {leaked}"
                             + (f"; still running after stopping them: {survivors}" if survivors else
                                "; stopped them"))


def stop_leaked_threads(prefix: str = "afmctl-", timeout_s: float = 2.0,
                        join_s: float = 5.0) -> tuple[list[str], list[str]]:
    """Wait up to ``timeout_s`` [s] for the threads named ``prefix``… to end; then close
    every started controller still running (:meth:`afmctl.control.controller.Controller.close`:
    stop, then estop) and join what is left for up to ``join_s`` [s]. Returns (names of the
    threads that had leaked, names of those still alive after all that)."""
    import threading
    left: list[str] = []

    def none_left() -> bool:
        left[:] = [t.name for t in threading.enumerate() if t.name.startswith(prefix)]
        return not left

    if wait_for(none_left, timeout_s, 0.02):
        return [], []
    leaked = list(left)
    from afmctl.control.controller import started_controllers
    for ctl in started_controllers():
        if ctl.running:
            ctl.close(timeout=join_s)
    deadline = time.monotonic() + join_s
    for t in threading.enumerate():
        if t.name.startswith(prefix) and t is not threading.current_thread():
            t.join(max(deadline - time.monotonic(), 0.0))
    none_left()
    return leaked, list(left)


#: Device-timed output (stream, FIFO wave) in tests: the most underruns a test tolerates, as a
#: fraction of the samples played. An underrun is the host late beyond the FIFO's low water
#: mark, and it is safe (the output holds for a tick). On a quiet machine there are none
#: (docs/BENCHMARKS.md measures that); on a loaded 2-core machine there are some: 6 of
#: ~10,000 samples (issue #22), and on the shared development machine at a load average of 12
#: 171 of 3,119 samples (5.5 %) without and 671 (21.5 %) with a CPU hog on one core
#: (tests/test_loop_stream.py's 20 ms host stalls at 1 kHz, 2026-11-26). Tests check what must
#: hold whatever the load — limits, slew, every played sample logged, samples on the device's
#: clock — and bound this count only against a producer that does not keep up at all.
MAX_UNDERRUN_FRACTION = 0.5


def stop_process(proc: Any, timeout_s: float = 20.0) -> int:
    """End a child ``afmctl`` process as a user would: SIGTERM, then wait ``timeout_s`` [s].
    One that does not end is asked for its threads' stacks (SIGUSR1, printed to its stderr:
    the failure explains itself) and killed. Returns the exit status (negative: a signal)."""
    import signal
    import subprocess
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(OSError):
                proc.send_signal(signal.SIGUSR1)
            time.sleep(1.0)
            proc.kill()
            proc.wait(10.0)
    return int(proc.returncode)


def assert_few_underruns(underruns: int, samples: int) -> None:
    """Fail when ``underruns`` exceeds :data:`MAX_UNDERRUN_FRACTION` of ``samples``."""
    allowed = int(MAX_UNDERRUN_FRACTION * samples)
    if not 0 <= underruns <= allowed:
        raise AssertionError(f"{underruns} underruns in {samples} samples; at most {allowed} "
                             f"({MAX_UNDERRUN_FRACTION:.0%}) expected even on a loaded machine")


def ticks_on_the_device_clock(times_s: Any, t0_s: float, rate_Hz: float) -> int:
    """Device-timed output as a simulator recorded it: every time [s] must be one of the
    device's ticks ``t0_s + k / rate_Hz`` (k integer, increasing, from 0; 1 ns tolerance for
    the float sum) — zero jitter by construction of the device clock. Returns the ticks
    skipped between the first and the last sample (each an underrun: the output held)."""
    import numpy as np
    t = np.asarray(times_s, dtype=np.float64)
    if len(t) == 0:
        return 0
    k = np.rint((t - t0_s) * rate_Hz)
    off = np.abs(t - (t0_s + k / rate_Hz))
    if k[0] < 0 or np.any(np.diff(k) < 1) or off.max() > 1e-9:
        raise AssertionError(f"samples off the device clock: first tick {k[0]:g}, smallest tick step "
                             f"{np.diff(k).min() if len(k) > 1 else 1:g}, largest offset {off.max():.3g} s")
    return int(k[-1] - k[0] + 1 - len(k))


def wait_until(cond: Callable[[], object], timeout_s: float = 5.0, interval_s: float = 0.005,
               what: str | None = None) -> None:
    """Like :func:`wait_for`, but raise ``AssertionError`` naming what was awaited (``what``,
    else the condition's name, or a lambda's source line) when ``cond()`` is still false
    after ``timeout_s`` seconds."""
    if not wait_for(cond, timeout_s, interval_s):
        raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what or describe(cond)}")


def describe(cond: Callable[[], object]) -> str:
    """A readable name for a condition: its qualified name, or for a lambda its source."""
    name = getattr(cond, "__qualname__", None) or repr(cond)
    if "<lambda>" in name:
        import inspect
        try:
            source = " ".join(inspect.getsource(cond).split())
        except (OSError, TypeError):
            return name
        start = source.find("lambda")
        return source[start:] if start >= 0 else source
    return name


@contextlib.contextmanager
def can_rig(prefix: str = "rig", *, fd: bool = False, max_history: int = 1_000_000) -> Iterator[tuple[str, Any, Any, Any]]:
    """The simulated CAN amplifier on a fresh python-can ``virtual`` channel, recording every
    output (:class:`afmctl.sim_backend.amplifiers.base.RecordingSink`), with our CAN driver
    connected to it: yields ``(channel, amplifier, simulator, sink)``; closed on exit."""
    import uuid

    from afmctl.drivers.can_amp import CANAmplifier
    from afmctl.sim_backend.amplifiers.base import RecordingSink
    from afmctl.sim_backend.testing import serve_can
    channel = f"{prefix}-{uuid.uuid4().hex[:8]}"
    sink = RecordingSink(max_history=max_history)
    with serve_can(channel, sink, record_seq=True) as sim:
        amp = CANAmplifier.open(f"virtual:{channel}", fd=fd)
        amp.connect()
        try:
            yield channel, amp, sim, sink
        finally:
            amp.close()


class HostStalls:
    """A hook that stalls the thread calling it (``Controller.stream_stall_hook``: the
    producer of a device-timed output) for ``stall_s`` [s] once every ``every_s`` [s], the
    first ``first_s`` after it was made; :attr:`times` holds when each stall ended
    (``time.monotonic``)."""

    def __init__(self, stall_s: float = 0.020, every_s: float = 1.0, first_s: float = 0.5) -> None:
        self.stall_s, self.every_s, self.first_s = stall_s, every_s, first_s
        self.t0 = time.monotonic()
        self.times: list[float] = []

    def __call__(self) -> None:
        if time.monotonic() - self.t0 >= self.first_s + self.every_s * len(self.times):
            time.sleep(self.stall_s)
            self.times.append(time.monotonic())


def bridge_on_free_port(controller, scanner_name: str = "s1", server=None, *, attempts: int = 3,
                        **bridge_options):
    """A :class:`afmctl.zenoh_api.bridge.ZenohBridge` for ``controller`` listening on a fresh
    loopback port, and the client settings that reach it: ``(bridge, client_settings)``.
    Retried ``attempts`` times, because another process may take the port between choosing
    and binding it. ``server``: base server settings for :func:`afmctl.zenoh_api.settings.loopback_pair`."""
    from .errors import AfmctlError
    from .zenoh_api.bridge import ZenohBridge
    from .zenoh_api.settings import loopback_pair
    for attempt in range(attempts):
        srv, cli = loopback_pair(server)
        try:
            return ZenohBridge(controller, srv, scanner_name, **bridge_options), cli
        except AfmctlError:
            if attempt == attempts - 1:
                raise
    raise ValueError(f"attempts: {attempts} must be at least 1")


def make_config(runlog_dir: str | Path | None = None, toml: str = "", **sections: dict[str, Any]):
    """An :class:`afmctl.config.Config` for tests, instead of TOML templates per test file: the
    in-process simulator (``simulation.enabled``), a run log in ``runlog_dir`` (no fsync,
    flushed every 20 ms; ``runlog.enabled = false`` when ``runlog_dir`` is None), then
    ``toml`` (text, e.g. ``"[compensation.drift]\\nenabled = true\\n"``) and ``sections``
    (``loop={"rate_Hz": 1000}``) merged in, later ones winning. Validated like a file, so a bad
    value raises the same one-line :class:`afmctl.errors.AfmctlError`."""
    from .config import _deep_merge, config_from_dict, parse_toml
    runlog: dict[str, Any] = ({"enabled": False} if runlog_dir is None else
                              {"dir": str(runlog_dir), "fsync": False, "flush_interval_s": 0.02})
    data: dict[str, Any] = {"simulation": {"enabled": True}, "runlog": runlog}
    data = _deep_merge(data, parse_toml(toml, "make_config(toml=...)"))
    return config_from_dict(_deep_merge(data, sections), "make_config")
