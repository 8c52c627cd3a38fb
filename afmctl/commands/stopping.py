"""Waiting for Ctrl-C or SIGTERM in a verb that serves until stopped (``afmctl sim``,
``afmctl router``)."""
from __future__ import annotations

import threading
import time

#: longest the main thread sleeps between two looks at the stop event [s]
POLL_S = 0.2


def wait_stopped(stop: threading.Event, duration_s: float | None = None) -> None:
    """Return once ``stop`` is set (a signal handler sets it) or ``duration_s`` [s] have
    passed (None: never). The main thread wakes every :data:`POLL_S`: Python runs a signal's
    handler only in the main thread, between two bytecodes, and a signal the kernel gave to
    another thread (zenoh's, the simulator's) does not wake a main thread blocked in an
    untimed wait — a ``docs/ZENOH.md`` doc test once saw ``afmctl sim`` serve on after its
    SIGTERM until a second one came."""
    deadline = None if duration_s is None else time.monotonic() + duration_s
    while True:
        left = POLL_S if deadline is None else min(POLL_S, deadline - time.monotonic())
        if left <= 0.0 or stop.wait(left):
            return
