"""The zenoh bridge's bookkeeping: counters, recent errors and input sequence checks, as
reported under ``stats.bridge`` and ``errors`` on ``status`` (docs/ZENOH.md)."""
from __future__ import annotations

import logging
import threading
import time
from collections import deque

from .messages import ErrorInfo

log = logging.getLogger(__name__)

#: how many recent errors ``status`` carries
RECENT_ERRORS = 20


class BridgeLedger:
    """Counters and the last :data:`RECENT_ERRORS` errors of one bridge.

    ``lock`` guards the counters and the errors; the bridge's publishers share it for their
    sequence numbers, so a status message is consistent with what was published.
    """

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.counters = {"rejected": 0, "accepted": 0, "setpoint_batches": 0, "setpoint_samples": 0,
                         "seq_gaps_in": 0, "queue_full": 0}
        self._errors: deque[ErrorInfo] = deque(maxlen=RECENT_ERRORS)
        self._last_in_seq: dict[str, int] = {}

    def record_error(self, source: str, message: str) -> None:
        """Count a rejection and keep its one-line ``message`` (``source``: key leaf or ``cmd``)."""
        with self.lock:
            self.counters["rejected"] += 1
            self._errors.append(ErrorInfo(t_s=time.time(), source=source, message=message))

    def count(self, name: str, n: int = 1) -> None:
        """Add ``n`` to counter ``name``."""
        with self.lock:
            self.counters[name] += n

    def errors(self) -> list[ErrorInfo]:
        """The recent errors, oldest first."""
        with self.lock:
            return list(self._errors)

    def check_seq(self, key: str, seq: int) -> None:
        """Count a gap in an input's sequence numbers (a restart at 0 is no gap); worker thread only."""
        last = self._last_in_seq.get(key)
        if last is not None and seq != last + 1 and seq != 0:
            self.counters["seq_gaps_in"] += 1
            log.info("%s: sequence %d after %d", key, seq, last)
        self._last_in_seq[key] = seq
