"""The simulator's truth on zenoh: :class:`SimPublisher` publishes on
``<prefix>/<scanner>/sim/**`` for ``afmctl sim`` (docs/ZENOH.md, *The simulator's truth*)."""
from __future__ import annotations

import json
import threading
from collections.abc import Mapping
from typing import Any

import numpy as np

from .jsonvalues import jsonable
from .messages import SCHEMA_VERSION, SimTipMsg
from .presence import declare_alive, undeclare_quietly
from .session import open_session
from .settings import ZenohSettings


class SimPublisher:
    """Publishes the simulator's truth on ``<prefix>/<scanner>/sim/...`` (used by ``afmctl sim``).

    ``publish_tip(t_s, position_nm)`` → ``sim/tip`` (JSON :class:`~afmctl.zenoh_api.messages.SimTipMsg`,
    one position [nm] x, y, z at time ``t_s`` [s]); ``publish_json(leaf, data)`` →
    ``sim/<leaf>`` for anything else (e.g. image metadata). Blocking congestion control.
    While it lives, the scanner's liveliness token ``<prefix>/<scanner>/alive`` is declared
    (:mod:`.presence`).
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
        self._alive = declare_alive(self.session, self.settings, scanner_name)

    def publish_tip(self, t_s: float, position_nm: Any) -> None:
        pos = [float(v) for v in np.asarray(position_nm, float).reshape(3)]
        with self._lock:
            msg = SimTipMsg(seq=self._seq["tip"], t_s=float(t_s), position_nm=pos)
            self._tip.put(msg.to_json_bytes())
            self._seq["tip"] += 1

    def publish_json(self, leaf: str, data: Mapping[str, Any]) -> None:
        with self._lock:
            seq = self._seq.get(leaf, 0)
            body = {**jsonable(dict(data)), "schema": SCHEMA_VERSION, "seq": seq}
            self.session.put(self.settings.key(self.scanner_name, f"sim/{leaf}"),
                             json.dumps(body, allow_nan=False).encode(), congestion_control=self._block)
            self._seq[leaf] = seq + 1

    def close(self) -> None:
        undeclare_quietly(self._alive)
        self._tip.undeclare()
        if self._own_session:
            self.session.close()

    def __enter__(self) -> "SimPublisher":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
