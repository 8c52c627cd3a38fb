"""Test and bench helpers: serve a simulated amplifier for the duration of a ``with``.

>>> from sim_backend.testing import serve_pty
>>> with serve_pty("mdt693b") as server:          # doctest: +SKIP
...     print(server.port)                        # a stable path to the pty
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator

from sim_backend.amplifiers.base import RecordingSink


@contextlib.contextmanager
def serve_pty(protocol: str, sink=None, baud: int = 115200, *, link=None, latency_s: float = 0.0,
              **device_options) -> Iterator["PtyServer"]:
    """Serve a simulated ``protocol`` (mdt693b, mdt694b, gcs, nv200) on a pty.

    Yields the running :class:`~sim_backend.amplifiers.pty_server.PtyServer`
    (``.port`` stable path, ``.device`` the simulator, ``.sink``). Without a ``sink`` a
    :class:`RecordingSink` records every output change. ``latency_s`` models a USB-serial
    adapter's latency timer on the replies."""
    from sim_backend.amplifiers import make_device
    from sim_backend.amplifiers.pty_server import PtyServer
    sink = sink if sink is not None else RecordingSink()
    server = PtyServer(make_device(protocol, sink, **device_options), baud=baud, link=link, latency_s=latency_s)
    server.sink = sink  # type: ignore[attr-defined]
    with server:
        yield server


@contextlib.contextmanager
def serve_can(channel: str = "afm0", sink=None, *, interface: str = "virtual", **options) -> Iterator["SimCANAmplifier"]:
    """Run a :class:`~sim_backend.amplifiers.can_amp.SimCANAmplifier` on a python-can
    channel (``virtual`` by default: in-process, no kernel CAN)."""
    from sim_backend.amplifiers.can_amp import SimCANAmplifier
    sink = sink if sink is not None else RecordingSink()
    amp = SimCANAmplifier(channel, sink, interface=interface, **options)
    with amp:
        yield amp


if False:  # pragma: no cover - names for type checkers only
    from sim_backend.amplifiers.can_amp import SimCANAmplifier
    from sim_backend.amplifiers.pty_server import PtyServer
