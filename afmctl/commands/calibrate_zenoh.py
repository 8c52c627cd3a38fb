"""``stop`` on zenoh while ``afmctl calibrate`` runs (``[zenoh] enabled = true``).

The calibration answers on the scanner's ``cmd`` key, the queryable ``afmctl run`` answers
on (docs/ZENOH.md, *Commands*): ``stop`` and ``estop`` stop it as Ctrl-C does (the piece
playing stops, the output ramps to the safe value, the command exits 130); ``status``
answers ``{"state": "calibrating", "what", "piece", "pieces", "left_s"}``; any other
command is refused (``ok: false``, naming the three). Every query gets exactly one reply.
Like run, sim and learn it declares the scanner's presence (``<prefix>/<scanner>/alive``).
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

#: what a calibration answers; the rest is refused
ANSWERED = ("stop", "estop", "status")


class CalibrationCommands:
    """The ``cmd`` queryable of one calibration. ``settings``: the ``[zenoh]`` table;
    ``scanner``: the scanner's name; ``stop``: ends the calibration (any thread);
    ``status``: what it is doing now (a JSON-able dict)."""

    def __init__(self, settings: Any, scanner: str, stop: Callable[[], None],
                 status: Callable[[], dict[str, Any]]) -> None:
        from ..zenoh_api.presence import declare_alive
        from ..zenoh_api.session import open_session
        self.settings = settings
        self.key = settings.key(scanner, "cmd")
        self._stop = stop
        self._status = status
        self.session = open_session(settings, scanner)
        self._queryable = self.session.declare_queryable(self.key, self._on_query, complete=True)
        self._alive = declare_alive(self.session, settings, scanner)     # as run, sim and learn do

    def _on_query(self, query: Any) -> None:
        """zenoh callback: decode, act (a stop only sets a flag), reply once; never blocks."""
        from ..zenoh_api.cmd_queryable import refuse, reply
        from ..zenoh_api.messages import CMD_NAMES, CmdReply, CmdRequest, MessageError, decode_json
        try:
            payload = query.payload
            if payload is not None and len(payload.to_bytes()) > 0:
                req = decode_json(payload.to_bytes(), CmdRequest, self.settings.max_message_bytes)
            else:
                params = dict(query.parameters) if query.parameters is not None else {}
                req = CmdRequest(cmd=params.get("cmd", ""))
        except (MessageError, ValueError) as err:
            msg = str(err) if isinstance(err, MessageError) else "field cmd: allowed: " + ", ".join(CMD_NAMES)
            reply(query, CmdReply(seq=0, cmd="?", ok=False, error=msg))
            return
        if req.cmd not in ANSWERED:
            refuse(query, req, f"afmctl calibrate is running: it answers {', '.join(ANSWERED)}")
            return
        if req.cmd in ("stop", "estop"):
            log.warning("zenoh %s: stopping the calibration", req.cmd)
            self._stop()
            result: dict[str, Any] = {"state": "stopping"}
        else:
            result = {"state": "calibrating", **self._status()}
        reply(query, CmdReply(seq=req.seq, cmd=req.cmd, ok=True, result=result))

    def close(self) -> None:
        from ..zenoh_api.presence import undeclare_quietly
        try:
            undeclare_quietly(self._alive)
            self._queryable.undeclare()
        finally:
            self.session.close()

    def __enter__(self) -> "CalibrationCommands":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
