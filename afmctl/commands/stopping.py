"""Waiting in a command's main thread for Ctrl-C / SIGTERM."""
from __future__ import annotations

import threading
import time


def wait_for_stop(stop: threading.Event, duration_s: float | None = None) -> None:
    """Wait until ``stop`` is set (by a Ctrl-C / SIGTERM handler) or ``duration_s`` [s] has
    passed, in short waits. A wait without a timeout blocks the main thread in a lock that a
    signal does not interrupt when the kernel hands the signal to another thread (zenoh's
    own), so the handler never ran: `afmctl sim --zenoh` ignored a SIGTERM now and then
    (docs/DRIVERS.md's zenoh block in tests/test_doc_blocks.py)."""
    deadline = None if duration_s is None else time.monotonic() + duration_s
    while not stop.is_set():
        left = 0.2 if deadline is None else min(0.2, deadline - time.monotonic())
        if left <= 0:
            return
        stop.wait(left)
