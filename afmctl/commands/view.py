"""``afmctl view``: a local web page that shows running scanners live (docs/VIEW.md)."""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

HELP = "watch running scanners live in a web browser (zenoh → local web page)"

DESCRIPTION = """\
Open a local web page that shows one or more running scanners live, fed by the zenoh
keys `afmctl run` and `afmctl sim --zenoh` publish (docs/ZENOH.md):

  * voltages [V] and targets [nm] per axis against the controller's time [s];
  * the tip path against the target in x–y [nm] (needs the simulator's sim/tip);
  * the tracking error [nm] tip − target, and its RMS in % of the scan range;
  * the drift estimate [nm] with its 1-σ band (when the predictor gives one);
  * the loop statistics and state from `status`;
  * the image [nm] as it builds up (the simulator's sim/image: `afmctl sim --sample ...`).

The viewer only watches; it never commands the scanner. It joins zenoh as a peer that
listens on nothing and connects to the endpoints you give:

  afmctl run --config stage1.toml &                 # [zenoh] listen = ["tcp/127.0.0.1:7447"]
  afmctl sim --zenoh --zenoh-listen tcp/127.0.0.1:7500 --scanner stage1 --sample grating2d &
  afmctl view --connect tcp/127.0.0.1:7447 --connect tcp/127.0.0.1:7500
  # then open http://127.0.0.1:8765/ in a browser

Without --scanner every scanner under the prefix is shown (a card per scanner side by side
and a selector for the panels); with --scanner NAME (repeatable) only those. The viewer
watches the scanners' liveliness tokens (<prefix>/<scanner>/alive): a scanner appears when
its `afmctl run`, `sim` or `learn` starts, is greyed out when it went away, and its last
status is asked for at once. A whole lab behind one `afmctl router` (docs/ZENOH.md):

  afmctl view --config examples/lab/view.toml --connect tcp/127.0.0.1:7447
 The page is served on 127.0.0.1 only, unless
--http says otherwise (port 0: any free port; the URL is printed first).

TLS, mutual TLS and user/password authentication: give a TOML file whose [zenoh] table
holds them (the same table as in `afmctl run` configs; a service config works as is —
its listen endpoints are ignored, the viewer listens on nothing):

  [zenoh]
  connect = ["tls/stage1.lab:7447"]
  [zenoh.tls]
  root_ca = "/etc/afmctl/ca.pem"
  certificate = "/etc/afmctl/viewer.pem"     # with mtls: its CN is matched by [zenoh.acl]
  private_key = "/etc/afmctl/viewer.key"
  [zenoh.auth]
  user = "viewer"
  password = "..."

With the service's (or the lab router's) access control on, the viewer must be one of its
`observers`.
Stop with Ctrl-C.
"""


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("view", help=HELP, description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="zenoh endpoint of a scanner service, simulator or router, e.g. tcp/127.0.0.1:7447 "
                        "(repeatable; adds to [zenoh] connect of --config)")
    p.add_argument("--scanner", action="append", default=None, metavar="NAME",
                   help="show only this scanner (repeatable; default: every scanner seen)")
    p.add_argument("--http", default="127.0.0.1:8765", metavar="HOST:PORT",
                   help="where to serve the page (default 127.0.0.1:8765; port 0 = any free port)")
    p.add_argument("--config", type=Path, default=None, metavar="FILE.toml",
                   help="TOML file whose [zenoh] table sets prefix, TLS, authentication (see above)")
    p.add_argument("--display-rate", type=float, default=200.0, metavar="HZ",
                   help="points per second kept per stream for display, 1..2000 (default 200)")
    p.add_argument("--history", type=float, default=30.0, metavar="S",
                   help="seconds of history kept and plotted, 1..600 (default 30)")
    p.set_defaults(func=run)


def parse_http(value: str) -> tuple[str, int]:
    """``HOST:PORT`` → (host, port); an :class:`AfmctlError` names the flag and the range."""
    from ..errors import AfmctlError
    host, sep, port = value.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise AfmctlError(f"--http: {value!r} must be HOST:PORT with port 0..65535, e.g. 127.0.0.1:8765")
    return host, int(port)


def zenoh_settings(config: Path | None, connect: list[str] | None):
    """The viewer's :class:`ZenohSettings`: ``[zenoh]`` of ``config`` (if given), listening
    on nothing, connecting to its ``connect`` plus ``--connect``."""
    import tomllib

    from pydantic import ValidationError

    from ..errors import AfmctlError
    from ..zenoh_api.settings import ZenohSettings
    table: dict[str, Any] = {}
    if config is not None:
        try:
            table = tomllib.loads(config.read_text(encoding="utf-8")).get("zenoh", {})
        except OSError as err:
            raise AfmctlError(f"{config}: cannot read ({err.strerror})") from None
        except tomllib.TOMLDecodeError as err:
            raise AfmctlError(f"{config}: not valid TOML ({err})") from None
    table = {**table, "enabled": True, "listen": [], "acl": {}}
    table["connect"] = list(table.get("connect", [])) + list(connect or [])
    if table.get("mode") == "router":
        table["mode"] = "peer"
    try:
        settings = ZenohSettings.model_validate(table)
    except ValidationError as err:
        first = err.errors()[0]
        loc = ".".join(str(p) for p in first["loc"])
        msg = first["msg"].removeprefix("Value error, ")
        if first["loc"][0] == "connect":
            raise AfmctlError(f"--connect{f' / {config} zenoh.connect' if config else ''}: {msg}") from None
        raise AfmctlError(f"{config}: field zenoh.{loc}: {msg}") from None
    if not settings.connect:
        raise AfmctlError("--connect: give at least one zenoh endpoint, e.g. --connect tcp/127.0.0.1:7447")
    return settings


def _check_range(flag: str, value: float, lo: float, hi: float, unit: str) -> None:
    from ..errors import AfmctlError
    if not lo <= value <= hi:
        raise AfmctlError(f"{flag}: {value:g} {unit} must be between {lo:g} and {hi:g}")


def run(args: argparse.Namespace) -> int:
    from ..errors import AfmctlError
    from ..view.app import bind
    from ..view.feed import ViewFeed
    _check_range("--display-rate", args.display_rate, 1.0, 2000.0, "Hz")
    _check_range("--history", args.history, 1.0, 600.0, "s")
    host, port = parse_http(args.http)
    settings = zenoh_settings(args.config, args.connect)
    feed = ViewFeed(settings, args.scanner, display_rate_Hz=args.display_rate, history_s=args.history)
    try:
        feed.keys()
    except ValueError as err:
        raise AfmctlError(f"--scanner: {err}") from None
    try:
        sock = bind(host, port)
    except OSError as err:
        raise AfmctlError(f"--http {args.http}: cannot listen ({err.strerror or err})") from None
    # uvicorn re-raises the signal that stopped it once it has shut down; with these
    # handlers in place that ends `serve` and the viewer exits 0. A signal that comes before
    # uvicorn takes the signals over (right after the address is printed) stops the server
    # too: it was swallowed, and the viewer served on after a SIGTERM (docs/ZENOH.md's lab
    # block, tests/test_doc_blocks.py)
    import signal
    early = EarlyStop()
    old = {s: signal.signal(s, early.on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        _serve(feed, sock, settings, args.scanner, early)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    print("afmctl view: stopped", file=sys.stderr, flush=True)
    return 0


class EarlyStop:
    """Ctrl-C / SIGTERM before the server handles them: remembered, and passed on to the
    server once it exists (``server.should_exit``, what uvicorn's own handler sets)."""

    def __init__(self) -> None:
        self.requested = False
        self.server: Any = None

    def on_signal(self, sig: int, frame: Any) -> None:
        self.requested = True
        if self.server is not None:
            self.server.should_exit = True

    def attach(self, server: Any) -> None:
        self.server = server
        if self.requested:
            server.should_exit = True


def _serve(feed: Any, sock: Any, settings: Any, scanners: list[str] | None, early: Any) -> None:
    from ..view.app import make_app, serve
    with sock, feed:
        h, p = sock.getsockname()[:2]
        url_host = f"[{h}]" if ":" in h else h
        print(f"afmctl view: http://{url_host}:{p}/", flush=True)
        print(f"watching {', '.join(scanners or ['every scanner'])} via "
              f"{', '.join(settings.connect)} (prefix {settings.prefix}); stop with Ctrl-C", flush=True)
        serve(make_app(feed), sock, early)
