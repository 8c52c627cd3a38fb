"""The zenoh API in its own process, so that the control loop's timing does not depend on it.

:class:`ZenohBridgeProcess` runs an :class:`afmctl.zenoh_api.bridge.ZenohBridge` — its session,
publishers, subscribers, queryable and worker — in a child process (``spawn``), so that
zenoh's callbacks, JSON and pydantic work never hold the loop process's interpreter lock.
Every key, payload, ACL/TLS setting and reply is the bridge's own: the child runs the same
class. Between the two processes:

* **records out** — the controller's dispatcher calls this object's ``on_setpoints`` /
  ``on_drift`` / ``on_status`` (never the loop thread); each pickles its record into a
  length-prefixed frame and writes what a non-blocking pipe takes at once — no extra
  thread in this process, so no extra hand-over of the interpreter lock. What the pipe
  does not take waits in a bounded outbox for the next call; when a slow subscriber backs
  the child up until the outbox is full (:data:`OUTBOX_BYTES`), records for zenoh are
  dropped and counted (``stats.bridge.dropped_to_child`` on status): the loop, the
  dispatcher and the run log never wait for zenoh.
* **calls in** — the child's bridge talks to a :class:`ControllerProxy` whose methods
  (``submit_segment``, ``set_temperature``, ``start``, ``stop``, ``estop``,
  ``submit_drift_measurement``, ``stats``, ``state``, ``queue_running``) are forwarded over a second pipe and
  run by a thread of this process on the real controller — the same calls the in-process
  bridge makes from its worker thread, off the loop thread. An error raised by the
  controller comes back with its message (one line naming the field and the range).

* **log records** — the child's records (from the lowest level of this process's loggers
  of the bridge's parts, :data:`afmctl.zenoh_api.bridge.LOGGERS`, up) come back over a
  third pipe and go to this process's loggers of the same name.

A bridge that cannot start (e.g. the listen port is taken) raises :class:`AfmctlError` here
with the child's message. Ctrl-C is left to this process (the child ignores SIGINT); the
child exits when this process closes the bridge or dies.
"""
from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import signal
import struct
import threading
import time
from typing import Any

import numpy as np

from ..control import cpu_pinning
from ..errors import AfmctlError, error_line
from ..control.runlog import SETPOINT_DTYPE

log = logging.getLogger(__name__)

#: bytes of records waiting for the child beyond the pipe's own buffer (about 10 s of 1 kHz
#: setpoints); records that do not fit are dropped for zenoh and counted
OUTBOX_BYTES = 2 * 1024 * 1024
_FRAME = struct.Struct("!I")   # length of the pickled record that follows
#: controller methods the child may call
REMOTE_METHODS = frozenset({"submit_segment", "set_temperature", "start", "stop", "estop",
                            "submit_drift_measurement", "stats", "state", "queue_running"})
_CLOSE = ("close", None)


def _frame(item: tuple) -> bytes:
    body = pickle.dumps(item, protocol=pickle.HIGHEST_PROTOCOL)
    return _FRAME.pack(len(body)) + body


class RemoteError(AfmctlError):
    """An error the controller raised for a call from the zenoh child (its message)."""


class ZenohBridgeProcess:
    """A :class:`afmctl.zenoh_api.bridge.ZenohBridge` for ``controller`` in a child process (see
    the module docstring). ``settings``, ``scanner_name`` and ``bridge_options`` are the
    bridge's; ``start_timeout_s``: how long to wait for the child's session [s]."""

    def __init__(self, controller: Any, settings: Any = None, scanner_name: str = "scanner", *,
                 start_timeout_s: float = 60.0, **bridge_options: Any) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.controller = controller
        self.scanner_name = scanner_name
        data_in, self._data_out = ctx.Pipe(duplex=False)
        self._rpc, rpc_child = ctx.Pipe(duplex=True)
        self._logs, logs_child = ctx.Pipe(duplex=False)
        config = getattr(controller, "config", None)
        from .bridge import LOGGERS as BRIDGE_LOGGERS
        log_level = min(logging.getLogger(name).getEffectiveLevel() for name in BRIDGE_LOGGERS)
        self._proc = ctx.Process(target=_child_main, name=f"afmctl-zenoh-{scanner_name}", daemon=True,
                                 args=(settings, scanner_name, config, data_in, rpc_child, bridge_options,
                                       logs_child, log_level))
        self._proc.start()
        data_in.close()
        rpc_child.close()
        logs_child.close()
        self._log_thread = threading.Thread(target=self._relay_logs, name="afmctl-zenoh-log", daemon=True)
        self._log_thread.start()
        self._wait_ready(start_timeout_s)
        self._fd = self._data_out.fileno()
        os.set_blocking(self._fd, False)
        self._outbox = bytearray()        # whole frames not yet taken by the pipe
        self.dropped = 0
        self._child_gone = False
        self._closed = False
        self._lock = threading.Lock()
        self._server = threading.Thread(target=self._serve, name="afmctl-zenoh-rpc", daemon=True)
        self._server.start()
        controller.add_sink(self)

    def _wait_ready(self, timeout_s: float) -> None:
        """The child's first message: ready, or the error that stopped its bridge."""
        reply: tuple = ("error", f"zenoh: the bridge process did not start within {timeout_s:g} s")
        try:
            if self._rpc.poll(timeout_s):
                reply = self._rpc.recv()
        except (EOFError, OSError):
            self._proc.join(5.0)
            reply = ("error", f"zenoh: the bridge process ended at start (exit code {self._proc.exitcode})")
        if reply[0] != "ready":
            self._proc.join(5.0)
            if self._proc.is_alive():
                self._proc.terminate()
            self._rpc.close()
            self._data_out.close()
            self._log_thread.join(5.0)
            raise AfmctlError(reply[1])

    # ------------------------------------------------------------------ controller sink (dispatcher thread)
    def on_setpoints(self, batch: np.ndarray) -> None:
        self._post(("sp", np.ascontiguousarray(batch, dtype=SETPOINT_DTYPE).tobytes()))

    def on_drift(self, estimate: dict) -> None:
        self._post(("drift", estimate))

    def on_status(self, status: dict) -> None:
        self._post(("status", {**status, "dropped_to_child": self.dropped}))

    def _post(self, item: tuple) -> None:
        """Dispatcher thread: frame the record and write what the pipe takes now (never
        blocks); keep the rest for the next call, or drop the record when the outbox is full."""
        frame = _frame(item)
        with self._lock:
            if self._closed or self._child_gone:
                return
            if len(self._outbox) + len(frame) > OUTBOX_BYTES:
                self.dropped += 1
                if self.dropped == 1:
                    log.warning("zenoh bridge process is behind; dropping records for zenoh (the run log keeps all)")
            else:
                self._outbox += frame
            self._write_some()

    def _write_some(self) -> None:
        """Write the outbox to the non-blocking pipe until it is empty or the pipe is full."""
        while self._outbox:
            try:
                n = os.write(self._fd, self._outbox)
            except BlockingIOError:
                return
            except OSError:            # the child is gone
                self._child_gone = True
                self._outbox.clear()
                return
            del self._outbox[:n]

    def _thread_priority(self) -> None:
        """The pipe threads take the interpreter lock: with a real-time loop they run just
        below it (see :func:`afmctl.control.controller.helper_priority`)."""
        from ..control.controller import helper_priority
        config = getattr(self.controller, "config", None)
        plan = getattr(self.controller, "cpu_plan", None)
        helper_priority(getattr(getattr(config, "loop", None), "realtime_priority", None),
                        plan.others if plan is not None else None)

    # ------------------------------------------------------------------ calls from the child
    def _serve(self) -> None:
        """RPC thread: run the child's controller calls here, reply with result or error."""
        ctl = self.controller
        self._thread_priority()
        while True:
            try:
                method, args = self._rpc.recv()
            except (EOFError, OSError):
                return
            try:
                if method not in REMOTE_METHODS:
                    raise AfmctlError(f"zenoh child: {method!r} is not a controller call it may make")
                if method == "state":
                    result: Any = ctl.state.value
                elif method == "queue_running":
                    result = bool(ctl.queue_running)
                else:
                    result = getattr(ctl, method)(*args)
                reply: tuple = ("ok", result)
            except Exception as err:  # noqa: BLE001 - handed back to the caller in the child
                reply = ("err", error_line(err))
            try:
                self._rpc.send(reply)
            except (OSError, ValueError):
                return

    def _relay_logs(self) -> None:
        """Log thread: the child's log records go to this process's loggers of the same name."""
        self._thread_priority()
        while True:
            try:
                record = self._logs.recv()
            except (EOFError, OSError):
                break
            logger = logging.getLogger(record.name)
            if logger.isEnabledFor(record.levelno):
                logger.handle(record)
        self._logs.close()

    # ------------------------------------------------------------------ lifecycle
    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop taking records, let the child publish what is queued, undeclare and exit."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        remove = getattr(self.controller, "remove_sink", None)
        if callable(remove):
            remove(self)
        self._drain(_frame(_CLOSE), timeout_s)
        self._proc.join(timeout_s)
        if self._proc.is_alive():
            log.warning("zenoh bridge process did not exit; terminating it")
            self._proc.terminate()
            self._proc.join(2.0)
        self._data_out.close()
        self._rpc.close()
        self._server.join(timeout_s)
        self._log_thread.join(timeout_s)

    def _drain(self, last: bytes, timeout_s: float) -> None:
        """At close: write the outbox and ``last`` (waiting up to ``timeout_s`` for the child)."""
        t_end = time.monotonic() + timeout_s
        with self._lock:
            self._outbox += last
            while self._outbox and not self._child_gone and time.monotonic() < t_end:
                self._write_some()
                if self._outbox:
                    time.sleep(0.005)

    def __enter__(self) -> "ZenohBridgeProcess":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ControllerProxy:
    """The controller as the child's bridge sees it: calls go over ``conn`` to the parent
    (one at a time); ``config`` is the parent's configuration (a copy)."""

    def __init__(self, conn: Any, config: Any) -> None:
        self._conn = conn
        self._lock = threading.Lock()
        self.config = config

    def _call(self, method: str, *args: Any) -> Any:
        with self._lock:
            try:
                self._conn.send((method, args))
                reply = self._conn.recv()
            except (EOFError, OSError):
                raise AfmctlError("controller: the service process is gone") from None
        if reply[0] == "err":
            raise RemoteError(reply[1])
        return reply[1]

    def add_sink(self, sink: Any) -> None:   # records arrive over the data pipe instead
        pass

    def remove_sink(self, sink: Any) -> None:
        pass

    @property
    def state(self) -> str:
        return self._call("state")

    @property
    def queue_running(self) -> bool:
        return bool(self._call("queue_running"))

    def stats(self) -> dict[str, Any]:
        return self._call("stats")

    def submit_segment(self, positions_nm: np.ndarray, dt_s: float) -> int:
        return self._call("submit_segment", np.ascontiguousarray(positions_nm), dt_s)

    def set_temperature(self, t_s: float, T_C: float) -> None:
        self._call("set_temperature", t_s, T_C)

    def start(self, source: Any = None) -> None:
        self._call("start", source)

    def stop(self) -> None:
        self._call("stop")

    def estop(self) -> None:
        self._call("estop")

    def submit_drift_measurement(self, measured_drift_nm: Any, std_nm: float, t_s: float | None = None) -> None:
        self._call("submit_drift_measurement", measured_drift_nm, std_nm, t_s)


class _PipeLogQueue:
    """The queue of a :class:`logging.handlers.QueueHandler`: records go over a pipe."""

    def __init__(self, conn: Any) -> None:
        self.conn = conn

    def put_nowait(self, record: logging.LogRecord) -> None:
        try:
            self.conn.send(record)
        except (OSError, ValueError):   # the parent is gone
            pass


def _child_main(settings: Any, scanner_name: str, config: Any, data_in: Any, rpc: Any,
                options: dict[str, Any], logs: Any, log_level: int) -> None:
    """The child process: the bridge on a proxy, fed from ``data_in`` until close or EOF;
    its log records go to the parent (``logs``) from ``log_level`` up."""
    import logging.handlers
    signal.signal(signal.SIGINT, signal.SIG_IGN)     # Ctrl-C is the service's to handle
    loop = getattr(config, "loop", None)
    if loop is not None:   # off the loop's CPU, before zenoh starts its threads (they inherit it)
        cpu_pinning.pin_this_thread(cpu_pinning.plan_for(loop).others)
    root = logging.getLogger()
    root.setLevel(log_level)
    root.addHandler(logging.handlers.QueueHandler(_PipeLogQueue(logs)))  # type: ignore[arg-type]
    from .bridge import ZenohBridge
    proxy = ControllerProxy(rpc, config)
    try:
        bridge = ZenohBridge(proxy, settings, scanner_name, **options)
    except Exception as err:  # noqa: BLE001 - reported to the parent as its one line
        rpc.send(("error", error_line(err)))
        return
    rpc.send(("ready", None))
    try:
        _feed_bridge(bridge, data_in)
    finally:
        bridge.close()


def _read_exact(fd: int, n: int) -> bytes | None:
    """``n`` bytes from the blocking pipe ``fd``; None at end of file."""
    parts = []
    while n:
        chunk = os.read(fd, n)
        if not chunk:
            return None
        parts.append(chunk)
        n -= len(chunk)
    return b"".join(parts)


def _feed_bridge(bridge: Any, data_in: Any) -> None:
    """Hand the parent's records to the bridge's sink methods until close or EOF."""
    fd = data_in.fileno()
    while True:
        try:
            head = _read_exact(fd, _FRAME.size)
            body = _read_exact(fd, _FRAME.unpack(head)[0]) if head is not None else None
        except OSError:
            return
        if body is None:
            return
        kind, item = pickle.loads(body)
        if kind == "close":
            return
        if kind == "sp":
            bridge.on_setpoints(np.frombuffer(item, dtype=SETPOINT_DTYPE))
        elif kind == "drift":
            bridge.on_drift(item)
        elif kind == "status":
            bridge.counters["dropped_to_child"] = item.pop("dropped_to_child", 0)
            bridge.on_status(item)
