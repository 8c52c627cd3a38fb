"""Test and bench helpers: serve a simulated amplifier for the duration of a ``with``.

>>> from sim_backend.testing import serve_pty
>>> with serve_pty("mdt693b") as server:          # doctest: +SKIP
...     print(server.port)                        # a stable path to the pty
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import TYPE_CHECKING

from .amplifiers.base import RecordingSink


@contextlib.contextmanager
def serve_pty(protocol: str, sink=None, baud: int = 115200, *, link=None, latency_s: float = 0.0,
              **device_options) -> Iterator["PtyServer"]:
    """Serve a simulated ``protocol`` (mdt693b, mdt694b, gcs, nv200) on a pty.

    Yields the running :class:`~afmctl.sim_backend.amplifiers.pty_server.PtyServer`
    (``.port`` stable path, ``.device`` the simulator, ``.sink``). Without a ``sink`` a
    :class:`RecordingSink` records every output change. ``latency_s`` models a USB-serial
    adapter's latency timer on the replies."""
    from .amplifiers import make_device
    from .amplifiers.pty_server import PtyServer
    sink = sink if sink is not None else RecordingSink()
    server = PtyServer(make_device(protocol, sink, **device_options), baud=baud, link=link, latency_s=latency_s)
    server.sink = sink  # type: ignore[attr-defined]
    with server:
        yield server


@contextlib.contextmanager
def serve_can(channel: str = "afm0", sink=None, *, interface: str = "virtual", **options) -> Iterator["SimCANAmplifier"]:
    """Run a :class:`~afmctl.sim_backend.amplifiers.can_amp.SimCANAmplifier` on a python-can
    channel (``virtual`` by default: in-process, no kernel CAN)."""
    from .amplifiers.can_amp import SimCANAmplifier
    sink = sink if sink is not None else RecordingSink()
    amp = SimCANAmplifier(channel, sink, interface=interface, **options)
    with amp:
        yield amp


def open_fds() -> set[int]:
    """File descriptors open in this process now (Linux ``/proc/self/fd``; empty elsewhere)."""
    import os
    try:
        return {int(n) for n in os.listdir("/proc/self/fd")}
    except OSError:
        return set()


@contextlib.contextmanager
def no_leaks(grace_s: float = 2.0) -> Iterator[None]:
    """Assert that the block leaves no thread and no file descriptor behind (servers,
    notifiers and ports it opened must be closed by its end). Threads get ``grace_s`` [s]
    to finish; a leak raises AssertionError naming the threads / fds."""
    import os
    import threading
    import time
    threads = set(threading.enumerate())
    fds = open_fds()
    yield
    deadline = time.monotonic() + grace_s
    while True:
        extra_threads = [t for t in threading.enumerate() if t not in threads and t.is_alive()]
        extra_fds = open_fds() - fds
        if not extra_threads and not extra_fds or time.monotonic() > deadline:
            break
        time.sleep(0.02)

    def describe(fd: int) -> str:
        try:
            return f"{fd}->{os.readlink(f'/proc/self/fd/{fd}')}"
        except OSError:
            return str(fd)
    assert not extra_threads, f"threads left running: {[t.name for t in extra_threads]}"
    assert not extra_fds, f"file descriptors left open: {[describe(fd) for fd in sorted(extra_fds)]}"


if TYPE_CHECKING:  # pragma: no cover - names for type checkers only
    from .amplifiers.can_amp import SimCANAmplifier
    from .amplifiers.pty_server import PtyServer
