"""Helpers for tests of afmctl and of programs built on it (shipped in the package, as
ophyd-async does). Simulated devices to test against live in :mod:`sim_backend.testing`."""
from __future__ import annotations

import time
from collections.abc import Callable


def wait_for(cond: Callable[[], object], timeout_s: float = 10.0, interval_s: float = 0.01) -> bool:
    """Poll ``cond()`` every ``interval_s`` seconds until it is true or ``timeout_s``
    seconds have passed; return its last truth value (one final check after the timeout)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(interval_s)
    return bool(cond())
