"""Publishing ``afmctl learn``'s progress on zenoh: one :class:`LearnMsg` per iteration on
``<prefix>/<scanner>/learn`` (docs/ZENOH.md), so that ``afmctl view`` or any subscriber
plots the convergence while the scanner learns."""
from __future__ import annotations

import logging
import time
from typing import Any

from .session import open_session
from .messages import LearnMsg
from .presence import declare_alive, undeclare_quietly
from .settings import ZenohSettings

log = logging.getLogger(__name__)


class LearnPublisher:
    """Publishes iterations of one learning run. ``settings``: the ``[zenoh]`` table;
    ``scanner``: the scanner's name; ``session``: an open session to use (not closed here),
    else one is opened from ``settings`` and closed by :meth:`close`. While it lives, the
    scanner's liveliness token ``<prefix>/<scanner>/alive`` is declared (:mod:`.presence`)."""

    def __init__(self, settings: ZenohSettings, scanner: str, session: Any = None) -> None:
        self.key = settings.key(scanner, "learn")
        self._own = session is None
        self.session = open_session(settings, scanner) if session is None else session
        self._pub = self.session.declare_publisher(self.key)
        self._alive = declare_alive(self.session, settings, scanner)
        self.seq = 0

    def publish(self, iteration: int, error: dict[str, float | None], *, step: float | None = None,
                state: str = "learning", detail: str = "") -> LearnMsg:
        """Put one iteration (``error``: ``max_pct``, ``rms_pct``, optionally
        ``central_max_pct`` / ``central_rms_pct``, % of the scan range)."""
        msg = LearnMsg(seq=self.seq, t_s=time.time(), iteration=iteration, step=step, state=state,
                       detail=detail[:500], **error)
        self._pub.put(msg.to_json_bytes())
        self.seq += 1
        return msg

    def close(self) -> None:
        try:
            undeclare_quietly(self._alive)
            self._pub.undeclare()
        finally:
            if self._own:
                self.session.close()

    def __enter__(self) -> "LearnPublisher":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
