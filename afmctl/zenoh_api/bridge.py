"""The zenoh API of the afmctl service (keys and payloads in docs/ZENOH.md).

:class:`ZenohBridge` connects one :class:`afmctl.control.controller.Controller` to zenoh:

* it is a controller *sink*: ``on_setpoints`` / ``on_drift`` / ``on_status`` are called by
  the controller's dispatcher thread (never the loop thread) and publish on
  ``<prefix>/<scanner>/setpoint`` (binary batches), ``.../drift`` and ``.../status`` (JSON)
  with blocking congestion control, so a slow subscriber slows the dispatcher, never the
  loop, and no sample is dropped (:mod:`.publishers`);
* it subscribes to ``.../trajectory`` and ``.../temperature``; the zenoh callbacks only
  check size, decode and validate the payload and put it on a bounded queue (:mod:`.inputs`);
* it declares the liveliness token ``.../alive`` (:mod:`.presence`) and serves
  ``.../status`` as a queryable too: a late joiner asks for the last status at once instead
  of waiting for the next one (any observer may; ``cmd status`` is an operator's);
* it serves ``.../cmd`` (start, stop, estop, status, config, drift-measurement — a drift
  measurement for the Kalman filter, see docs/DRIFT.md); queries are queued too
  (:mod:`.cmd_queryable`).

One worker thread (:mod:`.worker`) takes the queue and calls the controller. A rejected
message (bad JSON, wrong schema version, out of range, oversized, queue full, refused by
the controller) never reaches the controller: it is counted and reported on ``status``
with a one-line error naming the field and the allowed range (:mod:`.ledger`), and the
service keeps running.

:class:`~afmctl.zenoh_api.sim_publisher.SimPublisher` publishes the simulator's truth on ``.../sim/**``.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..errors import AfmctlError
from .cmd_queryable import CommandQueryable, refuse
from .inputs import LEAVES, InputSubscribers, position_range_from_config
from .jsonvalues import jsonable, state_name
from .ledger import RECENT_ERRORS, BridgeLedger
from .messages import StatusMsg
from .presence import declare_alive, undeclare_quietly
from .publishers import RecordPublishers
from .session import open_session
from .settings import ZenohSettings
from .sim_publisher import SimPublisher
from .worker import BridgeWorker

__all__ = ["RECENT_ERRORS", "SimPublisher", "ZenohBridge", "open_session", "position_range_from_config"]

log = logging.getLogger(__name__)

#: the loggers of the bridge's parts (a child process forwards their records, see .process)
LOGGERS = (__name__, "afmctl.zenoh_api.inputs", "afmctl.zenoh_api.cmd_queryable",
           "afmctl.zenoh_api.worker", "afmctl.zenoh_api.ledger", "afmctl.zenoh_api.presence")


class ZenohBridge:
    """Publish a controller's setpoints/drift/status and accept trajectories, temperatures
    and commands over zenoh. Use as a context manager or call :meth:`close`.

    ``controller`` needs (afmctl.control.controller.Controller): ``add_sink``, ``submit_segment(positions_nm
    (N,3), dt_s)``, ``set_temperature(t_s, T_C)``, ``start(source)`` (None = queue mode),
    ``stop()``, ``estop()``, ``state``, ``stats()``; optionally ``remove_sink`` and ``config``.
    ``session``: an already open zenoh session to use (not closed by the bridge).

    The bridge composes its parts — :class:`RecordPublishers`, :class:`InputSubscribers`,
    :class:`CommandQueryable`, one :class:`BridgeWorker` and a :class:`BridgeLedger` —
    and owns the session and the status message.
    """

    def __init__(self, controller: Any, settings: ZenohSettings | None = None, scanner_name: str = "scanner", *,
                 session: Any = None, status_period_s: float = 1.0, queue_size: int = 64,
                 position_range_nm: Mapping[str, tuple[float, float]] | None = None) -> None:
        self.settings = settings or ZenohSettings()
        self.scanner_name = scanner_name
        self.controller = controller
        self.status_period_s = float(status_period_s)
        self.position_range_nm = dict(position_range_nm) if position_range_nm is not None \
            else position_range_from_config(getattr(controller, "config", None))
        try:
            self.keys = {leaf: self.settings.key(scanner_name, leaf)
                         for leaf in ("setpoint", "drift", "status", *LEAVES, "cmd")}
        except ValueError as err:
            raise AfmctlError(f"scanner.name: {err}") from None

        self._own_session = session is None
        self.session = open_session(self.settings, scanner_name) if session is None else session
        self._ledger = BridgeLedger()
        self.counters = self._ledger.counters
        self._last_status: dict[str, Any] = {}
        self._closed = threading.Event()
        self._worker = BridgeWorker(f"afmctl-zenoh-{scanner_name}", queue_size, self.status_period_s,
                                    self._ledger, self._closed, self._handle, self.publish_status, self._drop)
        self._inbox = self._worker.queue
        try:
            self._declare()
        except Exception as err:  # e.g. an invalid key: do not leak the session
            if self._own_session:
                self.session.close()
            raise AfmctlError(f"zenoh: cannot declare the API keys ({' '.join(str(err).split())})") from None
        self._worker.start()
        controller.add_sink(self)
        log.info("zenoh API up: %s/%s/* (mode %s, listen %s)", self.settings.prefix, scanner_name,
                 self.settings.mode, self.settings.listen)

    def _declare(self) -> None:
        s, put = self.session, self._worker.put
        self._pub = RecordPublishers(s, self.keys, self.settings, self._ledger, self._closed)
        self._inputs = InputSubscribers(s, self.keys, self.settings, self.controller, self.position_range_nm,
                                        self._ledger, put)
        self._cmd = CommandQueryable(s, self.keys["cmd"], self.settings, self.controller, self.position_range_nm,
                                     self._ledger, put, self.status)
        self._status_queryable = s.declare_queryable(self.keys["status"], self._on_status_query, complete=True)
        self._alive = declare_alive(s, self.settings, self.scanner_name)

    def _on_status_query(self, query: Any) -> None:
        """zenoh callback: the last published status (a late joiner's first picture)."""
        payload = self._pub.last_status
        try:
            if payload is None and not self.closed:
                payload = self.status().to_json_bytes()
            if payload is not None:
                query.reply(self.keys["status"], payload)
        except Exception:  # noqa: BLE001 - the querier may be gone, the controller too
            log.debug("status query not answered", exc_info=True)
        finally:
            query.drop()

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> "ZenohBridge":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Undeclare everything, stop the worker, close the session (if the bridge opened it)."""
        if self._closed.is_set():
            return
        self._closed.set()
        remove = getattr(self.controller, "remove_sink", None)
        if callable(remove):
            try:
                remove(self)
            except Exception:  # pragma: no cover - best effort
                log.debug("remove_sink failed", exc_info=True)
        undeclare_quietly(self._alive)
        self._status_queryable.undeclare()
        self._inputs.undeclare()
        self._cmd.undeclare()
        self._worker.stop()
        self._pub.undeclare()
        if self._own_session:
            self.session.close()

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    # ------------------------------------------------------------------ controller sink
    def on_setpoints(self, batch: np.ndarray) -> None:
        """Publish a setpoint batch (split into ``settings.setpoint_batch`` records)."""
        if self.closed or len(batch) == 0:
            return
        self._pub.setpoints(batch)

    def on_drift(self, estimate: Any) -> None:
        """Publish a drift estimate (dict/object with ``drift_nm`` or ``estimate_nm``, or an array (3,))."""
        if self.closed:
            return
        problem = self._pub.drift(estimate)
        if problem is not None:
            self._ledger.record_error("drift", problem)

    def on_status(self, status: Any) -> None:
        """Merge the controller's status report into ours and publish it."""
        if self.closed:
            return
        if isinstance(status, Mapping):
            self._last_status = dict(status)
        elif status is not None:
            self._last_status = {"state": state_name(status)}
        self.publish_status()

    # ------------------------------------------------------------------ status
    def status(self) -> StatusMsg:
        """The current status message (state, loop statistics, bridge counters, recent errors)."""
        ctl = self.controller
        try:
            stats = dict(ctl.stats())
        except Exception as err:  # a broken stats() must not kill the status
            stats = {"stats_error": str(err)}
        extra = {k: v for k, v in self._last_status.items() if k not in ("state", "stats")}
        stats.update({"bridge": dict(self.counters), **({"controller": extra} if extra else {})})
        errors = self._ledger.errors()
        seq = self._pub.status_seq()
        return StatusMsg(seq=seq, scanner=self.scanner_name, t_s=time.time(),
                         state=state_name(getattr(ctl, "state", None)),
                         stats=jsonable(stats), errors=errors, rejected=self.counters["rejected"])

    def publish_status(self) -> None:
        if self.closed:
            return
        self._pub.status(self.status())

    def reject(self, source: str, message: str) -> None:
        """Count and report a rejected message (published on ``status``)."""
        log.warning("rejected %s: %s", source, message)
        self._ledger.record_error(source, message)
        self.publish_status()

    # ------------------------------------------------------------------ worker
    def _handle(self, kind: str, item: Any) -> None:
        """Worker thread: one queued item."""
        if kind in ("tick", "wake"):
            return
        if kind == "reject":
            self.reject(*item)
            return
        if kind in LEAVES:
            self._inputs.handle(kind, item, lambda source, message: self.reject(source, message))
            return
        if kind == "query":
            query, req = item
            self._cmd.answer(query, req)
            return
        raise AssertionError(f"unknown inbox item {kind}")  # pragma: no cover

    def _drop(self, kind: str, item: Any) -> None:
        """Worker thread at shutdown: answer a still queued query so that its client does not wait."""
        if kind == "query":
            query, req = item
            refuse(query, req, "service shutting down")
