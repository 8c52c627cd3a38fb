"""The zenoh API of the afmctl service (keys and payloads in docs/ZENOH.md).

:class:`ZenohBridge` connects one :class:`afmctl.control.controller.Controller` to zenoh:

* it is a controller *sink*: ``on_setpoints`` / ``on_drift`` / ``on_status`` are called by
  the controller's dispatcher thread (never the loop thread) and publish on
  ``<prefix>/<scanner>/setpoint`` (binary batches), ``.../drift`` and ``.../status`` (JSON)
  with blocking congestion control, so a slow subscriber slows the dispatcher, never the
  loop, and no sample is dropped;
* it subscribes to ``.../trajectory`` and ``.../temperature``; the zenoh callbacks only
  check size, decode and validate the payload and put it on a bounded queue;
* it serves ``.../cmd`` (start, stop, estop, status, config, drift-measurement — a drift
  measurement for the Kalman filter, see docs/DRIFT.md); queries are queued too.

One worker thread takes the queue and calls the controller. A rejected message (bad JSON,
wrong schema version, out of range, oversized, queue full, refused by the controller)
never reaches the controller: it is counted and reported on ``status`` with a one-line
error naming the field and the allowed range, and the service keeps running.

:class:`SimPublisher` publishes the simulator's truth on ``.../sim/**``.
"""
from __future__ import annotations

import functools
import json
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..errors import AfmctlError
from .messages import (
    CmdReply,
    CMD_NAMES,
    CmdRequest,
    DriftMsg,
    ErrorInfo,
    SCHEMA_VERSION,
    MessageError,
    SimTipMsg,
    StatusMsg,
    TemperatureMsg,
    decode_json,
    decode_trajectory,
    drift_measurement_args,
    encode_setpoints,
)
from .settings import ZenohSettings

log = logging.getLogger(__name__)

#: how many recent errors ``status`` carries
RECENT_ERRORS = 20


def open_session(settings: ZenohSettings, scanner_name: str | None = None) -> Any:
    """Open a zenoh session from :class:`ZenohSettings`; a failure is an :class:`AfmctlError`."""
    import zenoh
    config = settings.to_zenoh_config(scanner_name)
    try:
        return zenoh.open(config)
    except Exception as err:  # zenoh.ZError; e.g. the listen port is taken
        raise AfmctlError(f"zenoh: cannot open session ({' '.join(str(err).split())}); "
                          f"check zenoh.listen {settings.listen} / zenoh.connect {settings.connect}") from None


def _jsonable(value: Any) -> Any:
    """Plain JSON values from numpy scalars/arrays, enums, nested dicts (NaN/inf -> None)."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    if hasattr(value, "value") and isinstance(getattr(value, "value"), (str, int)):  # Enum
        return value.value
    if hasattr(value, "model_dump"):
        return _jsonable(value.model_dump(mode="json"))
    return str(value)


def _state_name(state: Any) -> str:
    if state is None:
        return "unknown"
    value = getattr(state, "value", state)
    return str(value)


class ZenohBridge:
    """Publish a controller's setpoints/drift/status and accept trajectories, temperatures
    and commands over zenoh. Use as a context manager or call :meth:`close`.

    ``controller`` needs (afmctl.control.controller.Controller): ``add_sink``, ``submit_segment(positions_nm
    (N,3), dt_s)``, ``set_temperature(t_s, T_C)``, ``start(source)`` (None = queue mode),
    ``stop()``, ``estop()``, ``state``, ``stats()``; optionally ``remove_sink`` and ``config``.
    ``session``: an already open zenoh session to use (not closed by the bridge).
    """

    def __init__(self, controller: Any, settings: ZenohSettings | None = None, scanner_name: str = "scanner", *,
                 session: Any = None, status_period_s: float = 1.0, queue_size: int = 64,
                 position_range_nm: Mapping[str, tuple[float, float]] | None = None) -> None:
        import zenoh

        self.settings = settings or ZenohSettings()
        self.scanner_name = scanner_name
        self.controller = controller
        self.status_period_s = float(status_period_s)
        self.position_range_nm = dict(position_range_nm) if position_range_nm is not None \
            else position_range_from_config(getattr(controller, "config", None))
        try:
            self.keys = {leaf: self.settings.key(scanner_name, leaf)
                         for leaf in ("setpoint", "drift", "status", "trajectory", "temperature", "cmd")}
        except ValueError as err:
            raise AfmctlError(f"scanner.name: {err}") from None

        self._own_session = session is None
        self.session = open_session(self.settings, scanner_name) if session is None else session
        self._lock = threading.Lock()          # seq counters, errors, publishers
        self._seq = {"setpoint": 0, "drift": 0, "status": 0}
        self._last_in_seq: dict[str, int] = {}
        self._errors: deque[ErrorInfo] = deque(maxlen=RECENT_ERRORS)
        self.counters = {"rejected": 0, "accepted": 0, "setpoint_batches": 0, "setpoint_samples": 0,
                         "seq_gaps_in": 0, "queue_full": 0}
        self._last_status: dict[str, Any] = {}
        self._last_setpoint: tuple[int, list[float]] | None = None   # (sample seq, u_V) of the last record
        self._inbox: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=queue_size)
        self._closed = threading.Event()

        try:
            self._declare(zenoh)
        except Exception as err:  # e.g. an invalid key: do not leak the session
            if self._own_session:
                self.session.close()
            raise AfmctlError(f"zenoh: cannot declare the API keys ({' '.join(str(err).split())})") from None
        self._worker = threading.Thread(target=self._work, name=f"afmctl-zenoh-{scanner_name}", daemon=True)
        self._worker.start()
        controller.add_sink(self)
        log.info("zenoh API up: %s/%s/* (mode %s, listen %s)", self.settings.prefix, scanner_name,
                 self.settings.mode, self.settings.listen)

    def _declare(self, zenoh: Any) -> None:
        block = zenoh.CongestionControl.BLOCK
        reliable = zenoh.Reliability.RELIABLE
        self._pub = {
            "setpoint": self.session.declare_publisher(self.keys["setpoint"], congestion_control=block,
                                                       reliability=reliable, priority=zenoh.Priority.DATA_HIGH),
            "drift": self.session.declare_publisher(self.keys["drift"], congestion_control=block,
                                                    reliability=reliable),
            "status": self.session.declare_publisher(self.keys["status"], congestion_control=block,
                                                     reliability=reliable),
        }
        self._subs = [
            self.session.declare_subscriber(self.keys[leaf], functools.partial(self._on_sample, leaf))
            for leaf in ("trajectory", "temperature")
        ]
        self._queryable = self.session.declare_queryable(self.keys["cmd"], self._on_query, complete=True)

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
        for sub in self._subs:
            sub.undeclare()
        self._queryable.undeclare()
        self._put_inbox(("wake", None), block=False)
        self._worker.join(timeout=5.0)
        with self._lock:
            for pub in self._pub.values():
                pub.undeclare()
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
        step = self.settings.setpoint_batch
        with self._lock:
            if self._closed.is_set():
                return
            for start in range(0, len(batch), step):
                part = batch[start:start + step]
                payload = encode_setpoints(self._seq["setpoint"], part)
                self._pub["setpoint"].put(payload)
                self._seq["setpoint"] += 1
                self.counters["setpoint_batches"] += 1
                self.counters["setpoint_samples"] += len(part)
            last = batch[-1]
            self._last_setpoint = (int(last["seq"]), [float(v) for v in last["u_V"]])

    def on_drift(self, estimate: Any) -> None:
        """Publish a drift estimate (dict/object with ``drift_nm`` or ``estimate_nm``, or an array (3,))."""
        if self.closed:
            return
        msg_fields = _drift_fields(estimate)
        with self._lock:
            if self._closed.is_set():
                return
            inputs = msg_fields["inputs"]
            # the drift predictor's inputs: the temperature and the voltages of the sample
            # the estimate belongs to (its heat term); the controller sends them in this order
            if self._last_setpoint is not None and "u_V" not in inputs \
                    and inputs.get("seq") == self._last_setpoint[0]:
                inputs["u_V"] = self._last_setpoint[1]
            if msg_fields["T_C"] is not None:
                inputs.setdefault("T_C", msg_fields["T_C"])
            try:
                payload = DriftMsg(seq=self._seq["drift"], **msg_fields).to_json_bytes()
            except ValueError as err:   # NaN/inf from the controller: say so, publish nothing wrong
                bad = err
            else:
                self._pub["drift"].put(payload)
                self._seq["drift"] += 1
                return
        self._record_error("drift", f"drift estimate not published: {_one_line(bad)}")

    def on_status(self, status: Any) -> None:
        """Merge the controller's status report into ours and publish it."""
        if self.closed:
            return
        if isinstance(status, Mapping):
            self._last_status = dict(status)
        elif status is not None:
            self._last_status = {"state": _state_name(status)}
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
        with self._lock:
            errors = list(self._errors)
            seq = self._seq["status"]
        return StatusMsg(seq=seq, scanner=self.scanner_name, t_s=time.time(),
                         state=_state_name(getattr(ctl, "state", None)),
                         stats=_jsonable(stats), errors=errors, rejected=self.counters["rejected"])

    def publish_status(self) -> None:
        if self.closed:
            return
        msg = self.status()
        with self._lock:
            if self._closed.is_set():
                return
            msg = msg.model_copy(update={"seq": self._seq["status"]})
            self._pub["status"].put(msg.to_json_bytes())
            self._seq["status"] += 1

    def reject(self, source: str, message: str) -> None:
        """Count and report a rejected message (published on ``status``)."""
        log.warning("rejected %s: %s", source, message)
        self._record_error(source, message)
        self.publish_status()

    # ------------------------------------------------------------------ zenoh callbacks (never block)
    def _payload(self, sample: Any, leaf: str) -> bytes | None:
        data = sample.payload.to_bytes()
        if len(data) > self.settings.max_message_bytes:
            self._put_inbox(("reject", (leaf,
                             f"payload: {len(data)} bytes; allowed at most {self.settings.max_message_bytes}")))
            return None
        return bytes(data)

    def _on_sample(self, leaf: str, sample: Any) -> None:
        """zenoh callback of ``trajectory`` and ``temperature``: size check, decode and
        validate here, then queue for the worker (never blocks)."""
        data = self._payload(sample, leaf)
        if data is None:
            return
        try:
            if leaf == "trajectory":
                msg = decode_trajectory(data, self.settings.max_message_bytes)
            else:
                msg = decode_json(data, TemperatureMsg, self.settings.max_message_bytes)
        except MessageError as err:
            self._put_inbox(("reject", (leaf, str(err))))
            return
        except Exception as err:  # a decoder bug must still end as an error on status
            log.exception("decoding a %s payload failed", leaf)
            self._put_inbox(("reject", (leaf, f"payload: cannot be decoded ({_one_line(err)})")))
            return
        self._put_inbox((leaf, msg))

    def _on_query(self, query: Any) -> None:
        payload = query.payload
        try:
            if payload is not None and len(payload.to_bytes()) > 0:
                req = decode_json(payload.to_bytes(), CmdRequest, self.settings.max_message_bytes)
            else:
                params = dict(query.parameters) if query.parameters is not None else {}
                req = CmdRequest(cmd=params.get("cmd", ""))  # type: ignore[arg-type]
        except (MessageError, ValueError) as err:
            msg = str(err) if isinstance(err, MessageError) else "field cmd: allowed: " + ", ".join(CMD_NAMES)
            self._reply(query, CmdReply(seq=0, cmd="?", ok=False, error=msg))
            self._put_inbox(("reject", ("cmd", msg)))
            return
        if req.cmd == "estop":
            # an emergency stop never waits behind queued trajectories: Controller.estop()
            # only raises a flag for the loop thread, so it is safe to call right here
            self._reply(query, self._run_cmd(req))
            return
        if not self._put_inbox(("query", (query, req))):
            self._reply(query, CmdReply(seq=req.seq, cmd=req.cmd, ok=False, error="service busy: queue full"))

    def _put_inbox(self, item: tuple[str, Any], block: bool = False) -> bool:
        try:
            self._inbox.put(item, block=block)
            return True
        except queue.Full:
            with self._lock:
                self.counters["queue_full"] += 1
            self._record_error(item[0], f"input queue full ({self._inbox.maxsize}); message dropped")
            return False

    # ------------------------------------------------------------------ worker
    def _work(self) -> None:
        next_status = time.monotonic() + self.status_period_s
        while not self._closed.is_set():
            timeout = max(0.0, next_status - time.monotonic())
            try:
                kind, item = self._inbox.get(timeout=timeout)
            except queue.Empty:
                kind, item = "tick", None
            try:
                self._handle(kind, item)
            except Exception as err:  # never let the worker die
                log.exception("zenoh worker: %s", err)
                self._record_error(kind, f"internal error: {err}")
            if time.monotonic() >= next_status and not self._closed.is_set():
                next_status = time.monotonic() + self.status_period_s
                try:
                    self.publish_status()
                except Exception:  # pragma: no cover
                    log.debug("status publish failed", exc_info=True)
        # answer what is still queued so that no client waits for a timeout
        while True:
            try:
                kind, item = self._inbox.get_nowait()
            except queue.Empty:
                break
            if kind == "query":
                q, req = item
                self._reply(q, CmdReply(seq=req.seq, cmd=req.cmd, ok=False, error="service shutting down"))

    def _record_error(self, source: str, message: str) -> None:
        with self._lock:
            self.counters["rejected"] += 1
            self._errors.append(ErrorInfo(t_s=time.time(), source=source, message=message))

    def _check_seq(self, key: str, seq: int) -> None:
        last = self._last_in_seq.get(key)
        if last is not None and seq != last + 1 and seq != 0:
            self.counters["seq_gaps_in"] += 1
            log.info("%s: sequence %d after %d", key, seq, last)
        self._last_in_seq[key] = seq

    def _handle(self, kind: str, item: Any) -> None:
        if kind in ("tick", "wake"):
            return
        if kind == "reject":
            self.reject(*item)
            return
        if kind in ("trajectory", "temperature"):
            self._check_seq(kind, item.seq)
            try:
                if kind == "trajectory":
                    positions = item.positions(self.settings.max_segment_samples)
                    self._check_range(positions)
                    self.controller.submit_segment(positions, item.dt_s)
                else:
                    self.controller.set_temperature(item.t_s, item.T_C)
            except Exception as err:  # refused by the controller: report, keep running
                self.reject(kind, _one_line(err))
                return
            with self._lock:
                self.counters["accepted"] += 1
            return
        if kind == "query":
            query, req = item
            self._reply(query, self._run_cmd(req))
            return
        raise AssertionError(f"unknown inbox item {kind}")  # pragma: no cover

    def _run_cmd(self, req: CmdRequest) -> CmdReply:
        ctl = self.controller
        try:
            if req.cmd == "start":
                self._start(req.args)
                result: dict[str, Any] = {"state": _state_name(ctl.state)}
            elif req.cmd == "stop":
                ctl.stop()
                result = {"state": _state_name(ctl.state)}
            elif req.cmd == "estop":
                ctl.estop()
                result = {"state": _state_name(ctl.state)}
            elif req.cmd == "status":
                result = self.status().model_dump(mode="json", by_alias=True)
            elif req.cmd == "drift-measurement":
                m = drift_measurement_args(req.args)
                ctl.submit_drift_measurement(m.measured_nm(), m.std_nm, m.t_s)
                result = {"state": _state_name(ctl.state)}
            else:  # config
                result = self._config_dump()
        except Exception as err:
            message = _one_line(err)
            self._record_error("cmd", f"{req.cmd}: {message}")
            return CmdReply(seq=req.seq, cmd=req.cmd, ok=False, error=message)
        with self._lock:
            self.counters["accepted"] += 1
        return CmdReply(seq=req.seq, cmd=req.cmd, ok=True, result=_jsonable(result))

    def _start(self, args: dict[str, Any]) -> None:
        """``start``: ``{}`` runs segments sent on ``trajectory`` as they come (queue mode);
        ``{"trajectory": {...}}`` queues that trajectory (segment, line or raster body) first;
        ``{"configured": true}`` runs the trajectory of the service's configuration."""
        unknown = set(args) - {"trajectory", "configured"}
        if unknown:
            raise MessageError(f"field args: unknown {', '.join(sorted(unknown))}; allowed: trajectory, configured")
        ctl = self.controller
        if args.get("configured"):
            config = getattr(ctl, "config", None)
            if config is None or getattr(config, "trajectory", None) is None:
                raise MessageError("field args.configured: this service has no configured trajectory")
            ctl.start(config.trajectory)
            return
        spec = args.get("trajectory")
        if spec is not None:
            if not isinstance(spec, dict):
                raise MessageError("field args.trajectory: expected a trajectory object (segment, line or raster)")
            body = {"schema": SCHEMA_VERSION, "seq": 0, **spec}
            msg = decode_trajectory(json.dumps(body).encode(), self.settings.max_message_bytes)
            positions = msg.positions(self.settings.max_segment_samples)
            self._check_range(positions)
            ctl.submit_segment(positions, msg.dt_s)
        ctl.start(None)

    def _check_range(self, positions: np.ndarray) -> None:
        for i, axis in enumerate(("x", "y", "z")):
            rng = self.position_range_nm.get(axis)
            if rng is None:
                continue
            lo, hi = rng
            col = positions[:, i]
            bad = (col < lo) | (col > hi)
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                raise MessageError(f"positions_nm: sample {k}: {axis} = {col[k]:.6g} nm outside the scan range "
                                   f"{lo:.6g}..{hi:.6g} nm")

    def _config_dump(self) -> dict[str, Any]:
        config = getattr(self.controller, "config", None)
        if config is None or not hasattr(config, "model_dump"):
            return {}
        data = config.model_dump(mode="json")
        z = data.get("zenoh")
        if isinstance(z, dict) and isinstance(z.get("auth"), dict) and z["auth"].get("password") is not None:
            z["auth"]["password"] = "***"
        return data

    def _reply(self, query: Any, reply: CmdReply) -> None:
        try:
            query.reply(query.key_expr, reply.to_json_bytes())
        except Exception:  # the querier may be gone
            log.debug("reply failed", exc_info=True)
        finally:
            try:
                query.drop()
            except Exception:  # pragma: no cover
                pass


def position_range_from_config(config: Any, margin: float = 0.1) -> dict[str, tuple[float, float]]:
    """Allowed target range per driven axis [nm]: the voltage limits through the linear
    calibration (``scanner.calibration``), widened by ``margin`` of the span on each side
    (hysteresis models bend the map a little). Empty when ``config`` is not an afmctl Config."""
    try:
        axes = list(config.scanner.axes)
        out = {}
        for axis in axes:
            lo_V, hi_V = config.limits(axis)
            spec = config.scanner.axis_spec(axis)
            a = (lo_V - spec.offset_V) * spec.nm_per_V
            b = (hi_V - spec.offset_V) * spec.nm_per_V
            lo, hi = min(a, b), max(a, b)
            pad = margin * (hi - lo)
            out[axis] = (lo - pad, hi + pad)
        return out
    except AttributeError:
        return {}


def _one_line(err: BaseException) -> str:
    from pydantic import ValidationError
    if isinstance(err, ValidationError):
        from afmctl.compensators.errortext import validation_error_line
        return validation_error_line(err)
    return " ".join(str(err).split()) or type(err).__name__


def _drift_fields(estimate: Any) -> dict[str, Any]:
    """DriftMsg fields from whatever the controller hands over."""
    def get(name: str) -> Any:
        if isinstance(estimate, Mapping):
            return estimate.get(name)
        return getattr(estimate, name, None)

    if isinstance(estimate, np.ndarray):
        return {"t_s": time.time(), "drift_nm": _jsonable(np.asarray(estimate, float).reshape(3))}
    drift = get("drift_nm")
    if drift is None:
        drift = get("estimate_nm")
    std = get("std_nm")
    t_s = get("t_s")
    T_C = get("T_C")
    known = {"drift_nm", "estimate_nm", "std_nm", "t_s", "T_C"}
    inputs = {}
    if isinstance(estimate, Mapping):
        inputs = {k: v for k, v in estimate.items() if k not in known}
    return {
        "t_s": float(t_s) if t_s is not None else time.time(),
        "drift_nm": [float(v) for v in np.asarray(drift, float).reshape(3)],
        "std_nm": None if std is None else [float(v) for v in np.asarray(std, float).reshape(3)],
        "T_C": None if T_C is None else float(T_C),
        "inputs": _jsonable(inputs),
    }


class SimPublisher:
    """Publishes the simulator's truth on ``<prefix>/<scanner>/sim/...`` (used by ``afmctl sim``).

    ``publish_tip(t_s, position_nm)`` → ``sim/tip`` (JSON :class:`~afmctl.zenoh_api.messages.SimTipMsg`,
    one position [nm] x, y, z at time ``t_s`` [s]); ``publish_json(leaf, data)`` →
    ``sim/<leaf>`` for anything else (e.g. image metadata). Blocking congestion control.
    """

    def __init__(self, settings: ZenohSettings | None = None, scanner_name: str = "scanner", *,
                 session: Any = None) -> None:
        import zenoh
        self.settings = settings or ZenohSettings()
        self.scanner_name = scanner_name
        self._own_session = session is None
        self.session = open_session(self.settings, scanner_name) if session is None else session
        self._block = zenoh.CongestionControl.BLOCK
        self._tip = self.session.declare_publisher(self.settings.key(scanner_name, "sim/tip"),
                                                   congestion_control=self._block)
        self._seq: dict[str, int] = {"tip": 0}
        self._lock = threading.Lock()

    def publish_tip(self, t_s: float, position_nm: Any) -> None:
        pos = [float(v) for v in np.asarray(position_nm, float).reshape(3)]
        with self._lock:
            msg = SimTipMsg(seq=self._seq["tip"], t_s=float(t_s), position_nm=pos)
            self._tip.put(msg.to_json_bytes())
            self._seq["tip"] += 1

    def publish_json(self, leaf: str, data: Mapping[str, Any]) -> None:
        with self._lock:
            seq = self._seq.get(leaf, 0)
            body = {**_jsonable(dict(data)), "schema": SCHEMA_VERSION, "seq": seq}
            self.session.put(self.settings.key(self.scanner_name, f"sim/{leaf}"),
                             json.dumps(body, allow_nan=False).encode(), congestion_control=self._block)
            self._seq[leaf] = seq + 1

    def close(self) -> None:
        self._tip.undeclare()
        if self._own_session:
            self.session.close()

    def __enter__(self) -> "SimPublisher":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
