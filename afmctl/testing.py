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
