"""``afmctl sim``: a simulated scanner behind a simulated amplifier on a pty, as its own
process. The first line printed is the pty path to give to ``afmctl amp``/``afmctl run``.

With ``--zenoh`` (off by default) the true tip position [nm] is published on
``<prefix>/<scanner>/sim/tip`` through :class:`TipPublisher` (decimated, own thread,
drop-oldest queue) and :class:`afmctl.zenoh_api.SimPublisher`."""
from __future__ import annotations

import argparse
import contextlib
import logging
import math
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

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

Port 7447 is also the default of `afmctl run`; when both run on one machine give the
simulator another port with --zenoh-listen (or, with --zenoh-connect ENDPOINT alone,
connect it to a peer or router and listen on nothing). Publishing is decimated to publish_rate_Hz
(at most one sample per tick, i.e. 1/tick_s) and runs in its own thread with a small
drop-oldest queue, so a slow subscriber never stalls the simulated plant.

--config FILE.toml (all sections optional):
  [amplifier]
  protocol = "mdt693b"      # mdt693b | mdt694b | gcs | nv200
  baud = 115200             # bits/s of the simulated link (8N1)
  link = "/tmp/afm-amp"     # also make this stable symlink to the pty
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
    height [nm] under it on ``sim/image`` (:class:`afmctl.messages.SimImageMsg`)."""
    from afmctl.sim_backend import samples
    sample = getattr(samples, SAMPLES[sample_key])()

    def publish(t_s: float, position_nm: Any) -> None:
        sim_pub.publish_tip(t_s, position_nm)
        x, y = float(position_nm[0]), float(position_nm[1])
        h = float(sample.height_nm(x, y))
        sim_pub.publish_json("image", {"t_s": float(t_s), "position_nm": [float(v) for v in position_nm[:3]],
                                       "height_nm": h, "sample": sample.name})
    return publish


def _settings_model():
    from pydantic import BaseModel, ConfigDict, Field
    from typing import Literal

    class AmplifierSection(BaseModel):
        model_config = ConfigDict(extra="forbid")
        protocol: Literal["mdt693b", "mdt694b", "gcs", "nv200"] = "mdt693b"
        baud: int = Field(115200, ge=300, le=10_000_000)
        link: str | None = None

    from ..zenoh_config import ZenohSettings

    class SimSection(BaseModel):
        model_config = ConfigDict(extra="forbid")
        tick_s: float = Field(0.01, gt=0, le=1.0)
        publish_rate_Hz: float = Field(100.0, ge=0.1, le=10_000.0)
        publish_queue: int = Field(64, ge=1, le=100_000)

    class SimSettings(BaseModel):
        model_config = ConfigDict(extra="forbid")
        amplifier: AmplifierSection = AmplifierSection()
        sim: SimSection = SimSection()
        scanner: dict[str, Any] = Field(default_factory=dict)
        zenoh: ZenohSettings = Field(default_factory=ZenohSettings)

    return SimSettings


def load_settings(path: Path | None):
    """The ``afmctl sim`` settings from a TOML file (or defaults); errors name the field."""
    import tomllib

    from ..errors import AfmctlError
    data: dict[str, Any] = {}
    if path is not None:
        try:
            data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
        except OSError as err:
            raise AfmctlError(f"{path}: cannot read ({err.strerror})") from None
        except tomllib.TOMLDecodeError as err:
            raise AfmctlError(f"{path}: not valid TOML ({err})") from None
    return _settings_model().model_validate(data)


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def make_scanner(overrides: dict[str, Any]):
    """The default simulated scanner with ``overrides`` merged in; a recording sink when
    :mod:`afmctl.sim_backend.scanner` is not available. Returns ``(sink, description)``."""
    try:
        from afmctl.sim_backend.scanner import Scanner, ScannerConfig, default_scanner_config
    except ModuleNotFoundError as err:
        # Only a missing scanner module falls back (a stripped install): a scanner that is
        # there but fails to import is a bug to see, not to paper over.
        if err.name not in ("afmctl.sim_backend.scanner", "sim_backend"):
            raise
        from afmctl.sim_backend.amplifiers import RecordingSink
        log.warning("afmctl.sim_backend.scanner unavailable (%s); the amplifier drives a recording sink, "
                    "no plant", err)
        return RecordingSink(max_history=10_000), f"recording sink (no scanner: {err})"
    from pydantic import ValidationError

    from ..errors import AfmctlError
    config = default_scanner_config()
    if overrides:
        try:
            config = ScannerConfig.model_validate(_merge(config.model_dump(), overrides))
        except ValidationError as err:
            first = err.errors()[0]
            loc = ".".join(str(p) for p in first["loc"])
            raise AfmctlError(f"field scanner.{loc}: {first['msg']}") from None
    return Scanner(config), f"scanner {config.name} (dt_s={config.dt_s:g})"


class SimService:
    """A simulated amplifier on a pty driving a scanner that advances on the wall clock.

    ``SimService(settings, on_tick=None, record=None)``; ``on_tick(t_s, position_nm)`` is called every
    ``tick_s`` from the service thread after the plant advanced (the hook for publishing
    the true tip position, e.g. over zenoh). ``start()``, ``stop()``, ``port``,
    ``pty_path``, ``scanner``.
    """

    def __init__(self, settings, *, on_tick: Callable[[float, Any], None] | None = None,
                 record: Path | None = None) -> None:
        from afmctl.sim_backend.amplifiers import make_device
        from afmctl.sim_backend.amplifiers.base import CsvRecorder, elapsed_clock
        from afmctl.sim_backend.amplifiers.pty_server import PtyServer
        self.settings = settings
        self.on_tick = on_tick
        self.scanner, self.description = make_scanner(settings.scanner)
        self.clock = elapsed_clock()
        amp = settings.amplifier
        self.recorder: CsvRecorder | None = None
        sink = self.scanner
        if record is not None:
            try:
                self.recorder = sink = CsvRecorder(str(record), inner=self.scanner)
            except OSError as err:
                from ..errors import AfmctlError
                raise AfmctlError(f"--record {record}: cannot write ({err.strerror})") from None
        self.device = make_device(amp.protocol, sink, now=self.clock)
        self.server = PtyServer(self.device, baud=amp.baud, link=amp.link)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> str:
        return self.server.port

    @property
    def pty_path(self) -> str | None:
        return self.server.pty_path

    def start(self) -> "SimService":
        try:
            self.server.start()
        except OSError as err:
            from ..errors import AfmctlError
            self.server.stop()
            raise AfmctlError(f"cannot serve the simulated amplifier on {self.server.port}: "
                              f"{err.strerror or err}") from None
        self._thread = threading.Thread(target=self._loop, name="afmctl-sim-clock", daemon=True)
        self._thread.start()
        return self

    def _loop(self) -> None:
        tick = self.settings.sim.tick_s
        advance = getattr(self.scanner, "advance", None)
        while not self._stop.wait(tick):
            t = self.clock()
            if advance is not None:
                advance(t)
            if self.on_tick is not None:
                pos = None
                if hasattr(self.scanner, "snapshot"):
                    # the plant's own time with its position, read together: another thread
                    # (the amplifier's apply()) may advance the plant between these lines
                    t, pos = self.scanner.snapshot()
                try:
                    self.on_tick(t, pos)
                except Exception:  # noqa: BLE001 - a publisher failure must not stop the plant
                    log.exception("on_tick callback failed")

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self.server.stop()
        if self.recorder is not None:
            self.recorder.close()

    def __enter__(self) -> "SimService":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


class TipPublisher:
    """Decimates the simulator's ticks and publishes them from its own thread.

    ``TipPublisher(publish, rate_Hz=100.0, queue_size=64)``: ``publish(t_s, position_nm)``
    is the slow part (e.g. :meth:`afmctl.zenoh_api.SimPublisher.publish_tip`, which uses
    blocking congestion control). :meth:`offer` is what the simulator's loop calls on each
    tick: it keeps at most one sample per ``1/rate_Hz`` seconds of simulated time ``t_s``
    [s] (consecutive samples at least ``1/rate_Hz`` apart), copies the position [nm] into a bounded queue and returns at once; when the queue
    is full the OLDEST sample is dropped (counted in ``dropped``), so a stalled subscriber
    can never stall the plant. Sequence numbers are given by ``publish``, so the published
    stream has no seq gaps even when samples were dropped here. ``start()``, ``close()``
    (publishes what is queued, up to ``drain_s``), counters ``offered``, ``queued``,
    ``published``, ``dropped``, ``errors``.
    """

    def __init__(self, publish: Callable[[float, Any], None], *, rate_Hz: float = 100.0,
                 queue_size: int = 64) -> None:
        import collections
        if not (rate_Hz > 0 and math.isfinite(rate_Hz)):
            raise ValueError(f"rate_Hz: {rate_Hz} must be a positive number of Hz")
        if queue_size < 1:
            raise ValueError(f"queue_size: {queue_size} must be at least 1")
        self._publish = publish
        self.period_s = 1.0 / rate_Hz
        self._queue: collections.deque = collections.deque(maxlen=queue_size)
        self._cond = threading.Condition()
        self._closed = False
        self._next_t: float | None = None
        self._thread: threading.Thread | None = None
        self.offered = self.queued = self.published = self.dropped = self.errors = 0

    def start(self) -> "TipPublisher":
        self._thread = threading.Thread(target=self._run, name="afmctl-sim-publish", daemon=True)
        self._thread.start()
        return self

    def offer(self, t_s: float, position_nm: Any) -> bool:
        """Queue ``(t_s, position_nm)`` if it is due; never blocks. True if it was queued."""
        self.offered += 1
        if position_nm is None:
            return False
        if self._next_t is not None and t_s < self._next_t:
            return False
        self._next_t = t_s + self.period_s    # consecutive samples >= 1/rate_Hz apart
        import numpy as np
        sample = (float(t_s), np.array(position_nm, dtype=float).reshape(3))
        with self._cond:
            if self._closed:
                return False
            if len(self._queue) == self._queue.maxlen:
                self.dropped += 1          # deque(maxlen) drops the oldest on append
            self._queue.append(sample)
            self.queued += 1
            self._cond.notify()
        return True

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closed:
                    self._cond.wait()
                if not self._queue:
                    return                      # closed and drained
                t_s, pos = self._queue.popleft()
            try:
                self._publish(t_s, pos)
                self.published += 1
            except Exception:  # noqa: BLE001 - keep publishing; the plant does not care
                self.errors += 1
                if self.errors <= 3:
                    log.exception("publishing the tip position failed")

    def close(self, drain_s: float = 2.0) -> None:
        """Stop accepting samples, publish what is queued (for at most ``drain_s`` [s])."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=drain_s)
            if self._thread.is_alive():
                with self._cond:
                    self.dropped += len(self._queue)
                    self._queue.clear()
                log.warning("tip publisher still busy after %.1f s; %d samples dropped", drain_s,
                            self.dropped)
            self._thread = None
        if self.dropped:
            log.warning("tip publisher dropped %d of %d samples (publisher slower than %.0f Hz)",
                        self.dropped, self.queued, 1.0 / self.period_s)

    def __enter__(self) -> "TipPublisher":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


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
        first = err.errors()[0]
        flag = {"listen": "--zenoh-listen", "connect": "--zenoh-connect"}.get(str(first["loc"][0]), "zenoh")
        raise AfmctlError(f"{flag}: {first['msg'].removeprefix('Value error, ')}") from None


def scanner_name(settings) -> str:
    """The ``<scanner>`` key chunk: ``[scanner] name`` / ``--scanner``, else the default's."""
    name = settings.scanner.get("name")
    if name is None:
        try:
            from afmctl.sim_backend.config import ScannerConfig
            name = ScannerConfig.model_fields["name"].default
        except ModuleNotFoundError:
            name = "sim0"
    return str(name)


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
                from ..zenoh_api import SimPublisher
                sim_pub = SimPublisher(settings.zenoh, name)
                stack.callback(sim_pub.close)
                publish = sim_pub.publish_tip if args.sample is None else image_publisher(sim_pub, args.sample)
                tips = TipPublisher(publish, rate_Hz=settings.sim.publish_rate_Hz,
                                    queue_size=settings.sim.publish_queue)
                stack.enter_context(tips)          # closed (drained) before sim_pub
            service = SimService(settings, on_tick=tips.offer if tips is not None else None,
                                 record=args.record)
            stack.enter_context(service)           # stopped first: no tick after this
            print(service.pty_path, flush=True)
            print(f"link: {service.port}", flush=True)
            print(f"protocol: {settings.amplifier.protocol} at {settings.amplifier.baud} baud; "
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
            stop.wait(args.duration)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    if tips is not None:
        print(f"afmctl sim: published {tips.published} tip positions"
              + (f", dropped {tips.dropped}" if tips.dropped else ""), file=sys.stderr, flush=True)
    print("afmctl sim: stopped", file=sys.stderr, flush=True)
    return 0
