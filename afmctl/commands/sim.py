"""``afmctl sim``: a simulated scanner behind a simulated amplifier on a pty, as its own
process. The first line printed is the pty path to give to ``afmctl amp``/``afmctl run``.

With ``--zenoh`` (off by default) the true tip position [nm] is published on
``<prefix>/<scanner>/sim/tip`` through :class:`TipPublisher` (decimated, own thread,
drop-oldest queue) and :class:`afmctl.zenoh_api.sim_publisher.SimPublisher`."""
from __future__ import annotations

import argparse
import contextlib
import logging
import math
import signal
import sys
import threading
from pathlib import Path
from typing import Any
from collections.abc import Callable

from ..simulation.service import SimService, TipPublisher, load_settings, scanner_name
from .stopping import wait_stopped

log = logging.getLogger(__name__)

HELP = "run a simulated scanner + amplifier on a pty (prints the device path first)"

DESCRIPTION = """\
Run the simulated piezo scanner behind a simulated amplifier that speaks the real
protocol (mdt693b, mdt694b, gcs or nv200) on a pseudo-terminal, throttled to the baud
rate. The FIRST line printed is the pty path; point any serial client at it:

  afmctl sim &                       # prints e.g. /dev/pts/7
  afmctl amp --driver mdt693b --port /dev/pts/7 set x=10

The scanner advances on the wall clock while the amplifier holds its output. Stop with
Ctrl-C or SIGTERM (exit 0).

The true tip position (x, y, z in nm) can be published on zenoh as
<prefix>/<scanner>/sim/tip (JSON {"schema", "seq", "t_s", "position_nm"}, default key
afm/sim0/sim/tip). With --sample NAME (grating1d, grating2d, standard) it also publishes
the image on .../sim/image: per published tip, the sample's height under the true tip
(JSON {"schema", "seq", "t_s", "position_nm", "height_nm", "sample"}), which `afmctl view`
shows as it builds up. Zenoh is OFF by default, so plain `afmctl sim` opens no network port;
--zenoh switches it on (peer mode, scouting off, listen on loopback only):

  afmctl sim --zenoh                                   # listens on tcp/127.0.0.1:7447
  afmctl sim --zenoh --zenoh-listen tcp/127.0.0.1:7500 --scanner stage1
                                                       # publishes afm/stage1/sim/tip

While zenoh is on, the simulator declares the scanner's presence, the liveliness token
<prefix>/<scanner>/alive (docs/ZENOH.md). Port 7447 is also the default of `afmctl run`; when both run on one machine give the
simulator another port with --zenoh-listen (or, with --zenoh-connect ENDPOINT alone,
connect it to a peer or router and listen on nothing). Publishing is decimated to publish_rate_Hz
(at most one sample per tick, i.e. 1/tick_s) and runs in its own thread with a small
drop-oldest queue, so a slow subscriber never stalls the simulated plant.

--config FILE.toml (all sections optional):
  [amplifier]
  protocol = "mdt693b"      # mdt693b | mdt694b | gcs | nv200
  baud = 115200             # bits/s of the simulated link (8N1)
  link = "/tmp/afm-amp"     # also make this stable symlink to the pty
  sensor = "capacitive"     # nv200 only: the actuator's position sensor (default none)
  [sim]
  tick_s = 0.01             # how often the plant is advanced to the wall clock [s]
  publish_rate_Hz = 100.0   # most sim/tip messages per second (0.1 .. 10000 Hz)
  publish_queue = 64        # samples waiting for the publisher; the oldest is dropped
  [scanner]                 # overrides of the default scanner (sim_backend ScannerConfig)
  name = "sim0"             # the <scanner> key chunk on zenoh
  dt_s = 1e-5
  [zenoh]                   # the same table as in `afmctl run` configs (docs/ZENOH.md)
  enabled = false           # true: publish afm/<scanner>/sim/tip
  listen = ["tcp/127.0.0.1:7447"]
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("sim", help=HELP, description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", type=Path, default=None, metavar="FILE.toml", help="simulation settings (see above)")
    p.add_argument("--protocol", choices=["mdt693b", "mdt694b", "gcs", "nv200"], default=None,
                   help="amplifier protocol (overrides the config; default mdt693b)")
    p.add_argument("--baud", type=int, default=None, help="simulated baud rate (default 115200)")
    p.add_argument("--link", default=None, help="also create this symlink to the pty")
    p.add_argument("--sensor", choices=["none", "strain gauge", "capacitive", "LVDT"], default=None,
                   help="nv200 only: the actuator's position sensor (default none: its recorder records voltages "
                        "only; with one, afmctl calibrate and learn can record the motion)")
    p.add_argument("--tcp", default=None, metavar="HOST:PORT",
                   help="serve on this loopback TCP endpoint instead of a pty, as controllers with an Ethernet "
                        "port are reached (gcs: E-727 port 50000; nv200: NV200/D NET); the driver's port is "
                        "socket://HOST:PORT; PORT 0 picks a free one (printed as 'link:')")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--record", type=Path, default=None, metavar="FILE.csv",
                   help="write every output change the amplifier applies to FILE.csv "
                        "(columns t_s,x_V,y_V,z_V, in the order received)")
    p.add_argument("--zenoh", action="store_true",
                   help="publish the true tip position on zenoh <prefix>/<scanner>/sim/tip (off by default)")
    p.add_argument("--zenoh-listen", action="append", default=None, metavar="ENDPOINT",
                   help="zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7500 (repeatable; implies --zenoh; "
                        "default tcp/127.0.0.1:7447)")
    p.add_argument("--zenoh-connect", action="append", default=None, metavar="ENDPOINT",
                   help="zenoh endpoint of a peer or router to connect to (repeatable; implies --zenoh)")
    p.add_argument("--publish-rate", type=float, default=None, metavar="HZ",
                   help="most sim/tip messages per second (overrides sim.publish_rate_Hz; default 100)")
    p.add_argument("--sample", choices=sorted(SAMPLES), default=None,
                   help="also publish the image on <prefix>/<scanner>/sim/image: the height of this "
                        "simulated sample under the true tip, one pixel per published tip (implies --zenoh)")
    p.add_argument("--scanner", default=None, metavar="NAME",
                   help="scanner name, the <scanner> key chunk on zenoh (default sim0)")
    p.set_defaults(func=run)


#: samples ``--sample`` can image (afmctl.sim_backend.samples, their default geometry)
SAMPLES = {"grating1d": "Grating1D", "grating2d": "Grating2D", "standard": "StandardSample"}


def image_publisher(sim_pub, sample_key: str) -> Callable[[float, Any], None]:
    """``publish(t_s, position_nm)`` that publishes the tip on ``sim/tip`` and the sample's
    height [nm] under it on ``sim/image`` (:class:`afmctl.zenoh_api.messages.SimImageMsg`)."""
    from afmctl.sim_backend import samples
    sample = getattr(samples, SAMPLES[sample_key])()

    def publish(t_s: float, position_nm: Any) -> None:
        sim_pub.publish_tip(t_s, position_nm)
        x, y = float(position_nm[0]), float(position_nm[1])
        h = float(sample.height_nm(x, y))
        sim_pub.publish_json("image", {"t_s": float(t_s), "position_nm": [float(v) for v in position_nm[:3]],
                                       "height_nm": h, "sample": sample.name})
    return publish


def _zenoh_overrides(settings, args) -> None:
    """Apply ``--zenoh``, ``--zenoh-listen``, ``--zenoh-connect``, ``--scanner``; check the key."""
    from pydantic import ValidationError

    from ..errors import AfmctlError
    if args.scanner is not None:
        settings.scanner["name"] = args.scanner
    if not (args.zenoh or args.zenoh_listen or args.zenoh_connect or args.sample):
        return
    update: dict[str, Any] = {"enabled": True}
    if args.zenoh_listen:
        update["listen"] = list(args.zenoh_listen)
    if args.zenoh_connect:
        update["connect"] = list(args.zenoh_connect)
        if not args.zenoh_listen:
            update["listen"] = []      # joining someone else's port: do not take 7447 too
    try:
        settings.zenoh = type(settings.zenoh).model_validate({**settings.zenoh.model_dump(), **update})
    except ValidationError as err:
        from afmctl.compensators.errortext import first_validation_error
        first, field = first_validation_error(err)
        flag = {"listen": "--zenoh-listen", "connect": "--zenoh-connect"}.get(field.split(".")[0], "zenoh")
        raise AfmctlError(f"{flag}: {first['msg'].removeprefix('Value error, ')}") from None


def run(args) -> int:
    from ..errors import AfmctlError
    settings = load_settings(args.config)
    if args.protocol:
        settings.amplifier.protocol = args.protocol
    if args.baud is not None:
        if not 300 <= args.baud <= 10_000_000:
            raise AfmctlError(f"--baud: {args.baud} must be between 300 and 10000000")
        settings.amplifier.baud = args.baud
    if args.link:
        settings.amplifier.link = args.link
    if args.sensor:
        settings.amplifier.sensor = args.sensor
    if args.tcp:
        from ..sim_backend.amplifiers.tcp_server import parse_endpoint
        try:
            parse_endpoint(args.tcp)
        except ValueError as err:
            raise AfmctlError(f"--tcp: {err}") from None
        settings.amplifier.tcp = args.tcp
    if args.duration is not None and not (args.duration > 0 and math.isfinite(args.duration)):
        raise AfmctlError(f"--duration: {args.duration} s must be a positive number of seconds")
    if args.publish_rate is not None:
        if not (0.1 <= args.publish_rate <= 10_000):
            raise AfmctlError(f"--publish-rate: {args.publish_rate} Hz must be between 0.1 and 10000")
        settings.sim.publish_rate_Hz = args.publish_rate
    _zenoh_overrides(settings, args)
    name = scanner_name(settings)
    tip_key = None
    if settings.zenoh.enabled:
        try:
            tip_key = settings.zenoh.key(name, "sim/tip")
        except ValueError as err:
            raise AfmctlError(f"--scanner / scanner.name: {err}") from None
    stop = threading.Event()

    def _on_signal(signum, frame):  # noqa: ARG001
        stop.set()

    old = {s: signal.signal(s, _on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    tips = None
    try:
        with contextlib.ExitStack() as stack:
            if settings.zenoh.enabled:            # first: a taken port fails before the pty opens
                from ..zenoh_api.sim_publisher import SimPublisher
                sim_pub = SimPublisher(settings.zenoh, name)
                stack.callback(sim_pub.close)
                publish = sim_pub.publish_tip if args.sample is None else image_publisher(sim_pub, args.sample)
                tips = TipPublisher(publish, rate_Hz=settings.sim.publish_rate_Hz,
                                    queue_size=settings.sim.publish_queue)
                stack.enter_context(tips)          # closed (drained) before sim_pub
            service = SimService(settings, on_tick=tips.offer if tips is not None else None,
                                 record=args.record)
            stack.enter_context(service)           # stopped first: no tick after this
            print(service.pty_path or service.port, flush=True)
            print(f"link: {service.port}", flush=True)
            link = ("TCP" if settings.amplifier.tcp else f"{settings.amplifier.baud} baud")
            print(f"protocol: {settings.amplifier.protocol} at {link}; "
                  f"load: {service.description}", flush=True)
            if tips is not None:
                rate = min(settings.sim.publish_rate_Hz, 1.0 / settings.sim.tick_s)
                where = ", ".join([f"listen {e}" for e in settings.zenoh.listen]
                                  + [f"connect {e}" for e in settings.zenoh.connect]) or "no endpoint"
                if args.sample is not None:
                    print(f"image: {args.sample} heights on {settings.zenoh.key(name, 'sim/image')}", flush=True)
                print(f"zenoh: publishing {tip_key} at up to {rate:g} Hz ({settings.zenoh.mode}, {where})",
                      flush=True)
            else:
                print("zenoh: off (use --zenoh to publish the true tip position)", flush=True)
            print("stop with Ctrl-C or SIGTERM", flush=True)
            wait_stopped(stop, args.duration)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    if tips is not None:
        print(f"afmctl sim: published {tips.published} tip positions"
              + (f", dropped {tips.dropped}" if tips.dropped else ""), file=sys.stderr, flush=True)
    print("afmctl sim: stopped", file=sys.stderr, flush=True)
    return 0
