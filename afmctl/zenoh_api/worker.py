"""The zenoh bridge's worker: one thread that takes the bridge's bounded queue (what the
zenoh callbacks hand over) and calls the controller, and publishes ``status`` every
``status_period_s`` [s] (docs/ZENOH.md, *Status*)."""
from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

from .ledger import BridgeLedger

log = logging.getLogger(__name__)


class BridgeWorker:
    """A bounded queue of ``(kind, item)`` and the thread that runs ``handle(kind, item)``
    for each (``("tick", None)`` when nothing came for a status period) and ``tick()``
    every ``status_period_s`` [s]. An exception in either is logged and recorded, never
    fatal. When ``closed`` is set the thread stops and passes what is still queued to
    ``drop(kind, item)``, so that no client waits for a timeout.
    """

    def __init__(self, name: str, queue_size: int, status_period_s: float, ledger: BridgeLedger,
                 closed: threading.Event, handle: Callable[[str, Any], None], tick: Callable[[], None],
                 drop: Callable[[str, Any], None]) -> None:
        self.queue: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=queue_size)
        self.status_period_s = float(status_period_s)
        self._ledger = ledger
        self._closed = closed
        self._handle = handle
        self._tick = tick
        self._drop = drop
        self._thread = threading.Thread(target=self._work, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    def put(self, item: tuple[str, Any], block: bool = False) -> bool:
        """Queue ``item``; when the queue is full, count and record it and return False."""
        try:
            self.queue.put(item, block=block)
            return True
        except queue.Full:
            self._ledger.count("queue_full")
            self._ledger.record_error(item[0], f"input queue full ({self.queue.maxsize}); message dropped")
            return False

    def stop(self, timeout_s: float = 5.0) -> None:
        """Wake the thread (``closed`` must be set) and wait up to ``timeout_s`` [s] for it."""
        self.put(("wake", None), block=False)
        self._thread.join(timeout=timeout_s)

    def _work(self) -> None:
        next_status = time.monotonic() + self.status_period_s
        while not self._closed.is_set():
            timeout = max(0.0, next_status - time.monotonic())
            try:
                kind, item = self.queue.get(timeout=timeout)
            except queue.Empty:
                kind, item = "tick", None
            try:
                self._handle(kind, item)
            except Exception as err:  # never let the worker die
                log.exception("zenoh worker: %s", err)
                self._ledger.record_error(kind, f"internal error: {err}")
            if time.monotonic() >= next_status and not self._closed.is_set():
                next_status = time.monotonic() + self.status_period_s
                try:
                    self._tick()
                except Exception:  # pragma: no cover
                    log.debug("status publish failed", exc_info=True)
        while True:
            try:
                kind, item = self.queue.get_nowait()
            except queue.Empty:
                break
            self._drop(kind, item)
