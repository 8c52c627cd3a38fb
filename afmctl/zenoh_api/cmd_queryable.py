"""The zenoh bridge's ``cmd`` queryable (docs/ZENOH.md, *Commands*): start, stop, estop,
status, config, drift-measurement. The zenoh callback decodes the request and queues it
for the bridge's worker — except ``estop``, which acts at once — and every query gets
exactly one reply, also when it is refused or the service shuts down."""
from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping
from typing import Any

from .inputs import Enqueue, check_range
from .jsonvalues import jsonable, one_line, state_name
from .ledger import BridgeLedger
from .messages import (
    CMD_NAMES,
    SCHEMA_VERSION,
    CmdReply,
    CmdRequest,
    MessageError,
    StatusMsg,
    decode_json,
    decode_trajectory,
    drift_measurement_args,
)
from .settings import ZenohSettings

log = logging.getLogger(__name__)


class CommandQueryable:
    """The ``cmd`` queryable of one scanner and the commands it runs on ``controller``.

    ``enqueue`` puts ``("query", (query, request))`` / ``("reject", ...)`` on the worker's
    queue (never blocks; False when full); ``status`` builds the current status message;
    ``position_range_nm``: axis -> (lo, hi) [nm] for a trajectory given to ``start``.
    """

    def __init__(self, session: Any, key: str, settings: ZenohSettings, controller: Any,
                 position_range_nm: Mapping[str, tuple[float, float]], ledger: BridgeLedger,
                 enqueue: Enqueue, status: Callable[[], StatusMsg]) -> None:
        self.settings = settings
        self.controller = controller
        self.position_range_nm = position_range_nm
        self._ledger = ledger
        self._enqueue = enqueue
        self._status = status
        self._queryable = session.declare_queryable(key, self._on_query, complete=True)

    def undeclare(self) -> None:
        self._queryable.undeclare()

    def _on_query(self, query: Any) -> None:
        """zenoh callback: decode the request, queue it (estop: run it here); never blocks."""
        payload = query.payload
        try:
            if payload is not None and len(payload.to_bytes()) > 0:
                req = decode_json(payload.to_bytes(), CmdRequest, self.settings.max_message_bytes)
            else:
                params = dict(query.parameters) if query.parameters is not None else {}
                req = CmdRequest(cmd=params.get("cmd", ""))
        except (MessageError, ValueError) as err:
            msg = str(err) if isinstance(err, MessageError) else "field cmd: allowed: " + ", ".join(CMD_NAMES)
            reply(query, CmdReply(seq=0, cmd="?", ok=False, error=msg))
            self._enqueue(("reject", ("cmd", msg)))
            return
        if req.cmd == "estop":
            # an emergency stop never waits behind queued trajectories: Controller.estop()
            # only raises a flag for the loop thread, so it is safe to call right here
            self.answer(query, req)
            return
        if not self._enqueue(("query", (query, req))):
            refuse(query, req, "service busy: queue full")

    def answer(self, query: Any, req: CmdRequest) -> None:
        """Run ``req`` and reply to ``query`` with the result."""
        reply(query, self.run(req))

    def run(self, req: CmdRequest) -> CmdReply:
        """Run one command on the controller; a failure is an ``ok: false`` reply and an error on status."""
        ctl = self.controller
        try:
            if req.cmd == "start":
                detail = self._start(req.args)
                result: dict[str, Any] = {"state": state_name(ctl.state)}
                if detail:
                    result["detail"] = detail
            elif req.cmd == "stop":
                ctl.stop()
                result = {"state": state_name(ctl.state)}
            elif req.cmd == "estop":
                ctl.estop()
                result = {"state": state_name(ctl.state)}
            elif req.cmd == "status":
                result = self._status().model_dump(mode="json", by_alias=True)
            elif req.cmd == "drift-measurement":
                m = drift_measurement_args(req.args)
                ctl.submit_drift_measurement(m.measured_nm(), m.std_nm, m.t_s)
                result = {"state": state_name(ctl.state)}
            else:  # config
                result = self._config_dump()
        except Exception as err:
            message = one_line(err)
            self._ledger.record_error("cmd", f"{req.cmd}: {message}")
            return CmdReply(seq=req.seq, cmd=req.cmd, ok=False, error=message)
        self._ledger.count("accepted")
        return CmdReply(seq=req.seq, cmd=req.cmd, ok=True, result=jsonable(result))

    def _start(self, args: dict[str, Any]) -> str | None:
        """``start``: ``{}`` runs segments sent on ``trajectory`` as they come (queue mode);
        ``{"trajectory": {...}}`` queues that trajectory (segment, line or raster body) first;
        ``{"configured": true}`` runs the trajectory of the service's configuration. A run
        already in queue mode (``trajectory.kind = "queue"``, or an earlier ``start``) goes
        on: the trajectory is queued and the reply says so (returned here)."""
        unknown = set(args) - {"trajectory", "configured"}
        if unknown:
            raise MessageError(f"field args: unknown {', '.join(sorted(unknown))}; allowed: trajectory, configured")
        ctl = self.controller
        if args.get("configured"):
            config = getattr(ctl, "config", None)
            if config is None or getattr(config, "trajectory", None) is None:
                raise MessageError("field args.configured: this service has no configured trajectory")
            ctl.start(config.trajectory)
            return None
        spec = args.get("trajectory")
        if spec is not None:
            if not isinstance(spec, dict):
                raise MessageError("field args.trajectory: expected a trajectory object (segment, line or raster)")
            body = {"schema": SCHEMA_VERSION, "seq": 0, **spec}
            msg = decode_trajectory(json.dumps(body).encode(), self.settings.max_message_bytes)
            positions = msg.positions(self.settings.max_segment_samples)
            check_range(positions, self.position_range_nm)
            ctl.submit_segment(positions, msg.dt_s)
        if getattr(ctl, "queue_running", False):
            return ("already running in queue mode: segments sent on trajectory play as they arrive"
                    + (" (this one queued)" if spec is not None else ""))
        ctl.start(None)
        return None

    def _config_dump(self) -> dict[str, Any]:
        """The service's configuration as JSON (the zenoh password masked)."""
        config = getattr(self.controller, "config", None)
        if config is None or not hasattr(config, "model_dump"):
            return {}
        data: dict[str, Any] = config.model_dump(mode="json")
        z = data.get("zenoh")
        if isinstance(z, dict) and isinstance(z.get("auth"), dict) and z["auth"].get("password") is not None:
            z["auth"]["password"] = "***"
        return data


def refuse(query: Any, req: CmdRequest, error: str) -> None:
    """Reply ``ok: false`` with ``error`` to a request that is not run."""
    reply(query, CmdReply(seq=req.seq, cmd=req.cmd, ok=False, error=error))


def reply(query: Any, answer: CmdReply) -> None:
    """Send ``answer`` to ``query`` and finish the query (the querier may be gone)."""
    try:
        query.reply(query.key_expr, answer.to_json_bytes())
    except Exception:  # the querier may be gone
        log.debug("reply failed", exc_info=True)
    finally:
        try:
            query.drop()
        except Exception:  # pragma: no cover
            pass
