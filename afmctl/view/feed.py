"""The zenoh side of ``afmctl view``: one session, subscribers on the published keys of
one or more scanners, one :class:`~afmctl.view.scanner_feed.ScannerFeed` per scanner.

The viewer only ever *watches* (what an ``observers`` subject of the service's or the lab
router's access control may do): it subscribes, watches the scanners' liveliness tokens
``<prefix>/<scanner>/alive`` (which scanners exist; one whose token went away is marked
gone) and asks each scanner that appears for its last ``status`` at once (the status
queryable every ``afmctl run`` serves), so a late joiner need not wait for the next one.
It never puts, and never queries ``cmd``. Its session is built from
:class:`afmctl.zenoh_api.settings.ZenohSettings`, so TLS, mutual TLS and user/password
authentication work as for any other peer (docs/ZENOH.md)."""
from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from ..zenoh_api.messages import MessageError
from ..zenoh_api.settings import ZenohSettings
from .scanner_feed import ScannerFeed

log = logging.getLogger(__name__)

#: the keys watched (leaf after ``<prefix>/<scanner>/``) and the feed method each goes to
LEAVES = {"setpoint": "on_setpoints", "drift": "on_drift", "status": "on_status",
          "sim/tip": "on_tip", "sim/image": "on_image", "learn": "on_learn"}
#: most scanners one viewer tracks (a wildcard subscription cannot grow without bound)
MAX_SCANNERS = 16


def _valid_name(settings: ZenohSettings, name: str) -> bool:
    """A scanner name as the services use it (one key chunk of letters, digits, _ - .)."""
    try:
        settings.key(name, "status")
    except ValueError:
        return False
    return True


class ViewFeed:
    """``ViewFeed(settings, scanners=None)``: watch ``scanners`` (None: every scanner under
    ``settings.prefix``, discovered from its messages, at most :data:`MAX_SCANNERS`).
    ``start()`` opens the session, ``close()`` ends it; ``feeds()`` the scanners seen."""

    def __init__(self, settings: ZenohSettings, scanners: list[str] | None = None, *,
                 display_rate_Hz: float = 200.0, history_s: float = 30.0) -> None:
        self.settings = settings
        self.scanners = list(scanners) if scanners else None
        self.display_rate_Hz, self.history_s = display_rate_Hz, history_s
        self._feeds: dict[str, ScannerFeed] = {}
        self._lock = threading.Lock()
        self._session: Any = None
        self._subs: list[Any] = []
        self._alive_sub: Any = None
        self.ignored = 0          # messages of scanners beyond MAX_SCANNERS or with invalid names

    @property
    def max_rows(self) -> int:
        """Rows each stream of each scanner holds at most (server and page alike)."""
        return max(1, int(self.display_rate_Hz * self.history_s))

    def keys(self) -> list[str]:
        """The key expressions subscribed to."""
        names = self.scanners or ["*"]
        for n in self.scanners or []:
            self.settings.key(n, "status")        # raises ValueError on a bad name
        return [f"{self.settings.prefix}/{n}/{leaf}" for n in names for leaf in LEAVES]

    def start(self) -> "ViewFeed":
        from ..zenoh_api.session import open_session
        keys = self.keys()
        self._session = open_session(self.settings)
        for key in keys:
            leaf = key.split("/", self.settings.prefix.count("/") + 2)[-1]
            self._subs.append(self._session.declare_subscriber(key, self._callback(leaf)))
        # presence: the tokens alive now (history) and every one that comes or goes
        self._alive_sub = self._session.liveliness().declare_subscriber(self.alive_key(), self._on_alive,
                                                                         history=True)
        log.info("watching %s and %s", ", ".join(keys), self.alive_key())
        return self

    def alive_key(self) -> str:
        """The liveliness key expression watched (one scanner's, or every scanner's)."""
        name = self.scanners[0] if self.scanners and len(self.scanners) == 1 else "*"
        return f"{self.settings.prefix}/{name}/alive"

    def _on_alive(self, sample: Any) -> None:
        """zenoh callback: a scanner's token came (ask for its status at once) or went."""
        import zenoh
        skip = len(self.settings.prefix) + 1
        name = str(sample.key_expr)[skip:].split("/", 1)[0]
        if self.scanners and name not in self.scanners:
            return
        feed = self.feed(name)
        if feed is None:
            return
        came = sample.kind == zenoh.SampleKind.PUT
        feed.set_alive(came)
        log.info("scanner %s %s", name, "alive" if came else "gone")
        if came and self._session is not None:
            try:
                self._session.get(self.settings.key(name, "status"), self._status_reply(feed))
            except Exception:  # noqa: BLE001 - the session is closing
                log.debug("status query failed", exc_info=True)

    def _status_reply(self, feed: ScannerFeed) -> Callable[[Any], None]:
        def on_reply(reply: Any) -> None:
            if reply.ok is None:
                return
            try:
                feed.on_status(reply.ok.payload.to_bytes())
            except MessageError as err:
                feed.reject("status", err)
        return on_reply

    def _callback(self, leaf: str) -> Callable[[Any], None]:
        method = LEAVES[leaf]
        skip = len(self.settings.prefix) + 1

        def on_sample(sample: Any) -> None:
            name = str(sample.key_expr)[skip:].split("/", 1)[0]
            feed = self.feed(name)
            if feed is None:
                return
            try:
                getattr(feed, method)(sample.payload.to_bytes())
            except MessageError as err:
                feed.reject(leaf, err)
            except Exception as err:  # noqa: BLE001 - never let a payload kill the zenoh thread
                log.exception("%s: %s message failed", name, leaf)
                feed.reject(leaf, err)
        return on_sample

    def feed(self, name: str) -> ScannerFeed | None:
        """The feed of scanner ``name`` (created on its first message), or None when the
        viewer already tracks :data:`MAX_SCANNERS` others or ``name`` is not a valid
        scanner name (both counted in ``ignored``)."""
        with self._lock:
            feed = self._feeds.get(name)
            if feed is None:
                if len(self._feeds) >= MAX_SCANNERS or not _valid_name(self.settings, name):
                    self.ignored += 1
                    return None
                feed = self._feeds[name] = ScannerFeed(name, self.display_rate_Hz, self.history_s)
                log.info("scanner %s seen", name)
            return feed

    def feeds(self) -> dict[str, ScannerFeed]:
        with self._lock:
            return dict(self._feeds)

    def close(self) -> None:
        if self._alive_sub is not None:
            self._alive_sub.undeclare()
            self._alive_sub = None
        for sub in self._subs:
            sub.undeclare()
        self._subs.clear()
        if self._session is not None:
            self._session.close()
            self._session = None

    def __enter__(self) -> "ViewFeed":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
