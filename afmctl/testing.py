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
    the run log's, the zenoh bridge's) has ended within ``timeout_s`` seconds."""
    import threading
    left: list[str] = []

    def none_left() -> bool:
        left[:] = [t.name for t in threading.enumerate() if t.name.startswith(prefix)]
        return not left

    if not wait_for(none_left, timeout_s, 0.02):
        raise AssertionError(f"threads left running: {left}")


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
