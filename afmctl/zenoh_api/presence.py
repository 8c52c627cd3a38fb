"""Presence of a service on zenoh: the liveliness token ``<prefix>/<scanner>/alive``.

Every ``afmctl run``, ``sim`` and ``learn`` with zenoh on declares it for as long as its
session lives (docs/ZENOH.md, *Presence*). zenoh itself withdraws the token when the
process ends or its link is lost — a killed process included — so a liveliness subscriber
(``afmctl view``, any script) knows which scanners exist without polling. Several services
of one scanner (its ``run`` and its ``sim``) declare the same key; it stays alive while any
of them does."""
from __future__ import annotations

import logging
from typing import Any

from .settings import ZenohSettings

log = logging.getLogger(__name__)

#: the leaf of the liveliness token
ALIVE_LEAF = "alive"


def declare_alive(session: Any, settings: ZenohSettings, scanner: str) -> Any:
    """Declare ``<prefix>/<scanner>/alive`` on ``session``; returns the token (``undeclare()``
    it, or close the session, to withdraw it)."""
    key = settings.key(scanner, ALIVE_LEAF)
    token = session.liveliness().declare_token(key)
    log.info("presence: %s declared", key)
    return token


def undeclare_quietly(token: Any) -> None:
    """Withdraw ``token``; a session already closed has withdrawn it already."""
    if token is None:
        return
    try:
        token.undeclare()
    except Exception:  # noqa: BLE001 - the session is gone: so is the token
        log.debug("token already gone", exc_info=True)
