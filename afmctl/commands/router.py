"""``afmctl router``: a zenoh router for a lab of scanners, with the lab's access control."""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from .stopping import wait_stopped

HELP = "run a zenoh router for a lab of scanners (TLS, users, access per scanner)"

DESCRIPTION = """\
Run a zenoh router (eclipse-zenoh's own, from the installed package) that a lab's
scanners, viewers and scripts connect to as clients: `afmctl run`, `sim` and `learn` with
[zenoh] mode = "client" and connect = ["tcp/<router>:7447"]. Who may do what is decided
here, by an access-control file (TOML) naming which subject may serve, operate or only
observe which scanner (docs/ZENOH.md, "A lab"):

  observers = ["watchers"]                 # may watch every scanner
  [subjects]                               # who connects: usernames / cert_common_names / interfaces
  stage1-svc = { usernames = ["svc-stage1"] }
  alice = { usernames = ["alice"] }
  watchers = { usernames = ["viewer"] }
  [scanners.stage1]
  services = ["stage1-svc"]                # may run / simulate / learn stage1
  operators = ["alice"]                    # may command stage1 (cmd, trajectory, temperature)

Everything else is denied. Without --acl (and no [router] acl), every session may serve
and watch any scanner and nobody may command one. The router listens on loopback only
(tcp/127.0.0.1:7447) unless told otherwise; scouting is off.

The configuration file holds one [router] table (paths relative to the file):

  [router]
  listen = ["tcp/127.0.0.1:7447"]
  connect = []                             # routers of other rooms: the lab spans them
  acl = "acl.toml"
  [router.auth]
  dictionary_file = "users.txt"            # user:password lines the router accepts
  # user = "room-a"; password = "..."      # what it presents to the routers it connects to
  [router.tls]                             # for tls/ endpoints; mtls = true: client certificates
  # root_ca = "ca.pem"; certificate = "router.pem"; private_key = "router.key"; mtls = true

Examples:
  afmctl router                                          # loopback, nobody may command
  afmctl router --config examples/lab/router.toml        # the lab of docs/ZENOH.md
  afmctl router --config examples/lab/router.toml --listen tcp/0.0.0.0:7447
  afmctl router --config examples/lab/router.toml --print-config   # zenoh's configuration, then exit

Stop with Ctrl-C or SIGTERM (exit 0). Bad configuration or ACL: one line naming the file
and the field, exit status 2.
"""


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("router", help=HELP, description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", type=Path, default=None, metavar="FILE.toml",
                   help="router configuration: a [router] table (see above)")
    p.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="listen here instead of router.listen (repeatable), e.g. tcp/127.0.0.1:7447")
    p.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="link with the router of another room (repeatable; replaces router.connect)")
    p.add_argument("--acl", type=Path, default=None, metavar="ACL.toml",
                   help="the lab's access-control file (replaces router.acl)")
    p.add_argument("--print-config", action="store_true",
                   help="print the zenoh configuration (access control included, passwords masked) and exit")
    p.set_defaults(func=run)


def settings_from_args(args: argparse.Namespace) -> Any:
    """The :class:`afmctl.zenoh_api.router.RouterSettings` of the file and the flags."""
    from ..zenoh_api.router import load_router_settings
    overrides: dict[str, Any] = {"listen": args.listen, "connect": args.connect}
    if args.acl is not None:
        overrides["acl"] = args.acl.resolve()
    return load_router_settings(args.config, overrides)


def _masked(values: dict[str, Any]) -> dict[str, Any]:
    out = dict(values)
    if out.get("transport/auth/usrpwd/password") is not None:
        out["transport/auth/usrpwd/password"] = "***"
    return out


def run(args: argparse.Namespace) -> int:
    from ..zenoh_api.router import Router
    settings = settings_from_args(args)
    values = settings.to_json()          # reads and checks the ACL file
    if args.print_config:
        print(json.dumps(_masked(values), indent=2))
        return 0
    stop = threading.Event()
    old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        with Router(settings):
            acl = str(settings.acl) if settings.acl is not None else "none (nobody may command)"
            print(f"afmctl router: listening on {', '.join(settings.listen)}"
                  + (f", linked to {', '.join(settings.connect)}" if settings.connect else "")
                  + f"; access control {acl}", flush=True)
            print("stop with Ctrl-C or SIGTERM", flush=True)
            wait_stopped(stop)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    print("afmctl router: stopped", file=sys.stderr, flush=True)
    return 0
