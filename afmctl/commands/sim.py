"""``afmctl sim``: a simulated scanner behind a simulated amplifier on a pty, as its own
process. The first line printed is the pty path to give to ``afmctl amp``/``afmctl run``."""
from __future__ import annotations

import argparse
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

--config FILE.toml (all sections optional):
  [amplifier]
  protocol = "mdt693b"      # mdt693b | mdt694b | gcs | nv200
  baud = 115200             # bits/s of the simulated link (8N1)
  link = "/tmp/afm-amp"     # also make this stable symlink to the pty
  [sim]
  tick_s = 0.01             # how often the plant is advanced to the wall clock [s]
  [scanner]                 # overrides of the default scanner (sim_backend ScannerConfig)
  dt_s = 1e-5
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
    p.set_defaults(func=run)


def _settings_model():
    from pydantic import BaseModel, ConfigDict, Field
    from typing import Literal

    class AmplifierSection(BaseModel):
        model_config = ConfigDict(extra="forbid")
        protocol: Literal["mdt693b", "mdt694b", "gcs", "nv200"] = "mdt693b"
        baud: int = Field(115200, ge=300, le=10_000_000)
        link: str | None = None

    class SimSection(BaseModel):
        model_config = ConfigDict(extra="forbid")
        tick_s: float = Field(0.01, gt=0, le=1.0)

    class SimSettings(BaseModel):
        model_config = ConfigDict(extra="forbid")
        amplifier: AmplifierSection = AmplifierSection()
        sim: SimSection = SimSection()
        scanner: dict[str, Any] = Field(default_factory=dict)

    return SimSettings


def load_settings(path: Path | None):
    """The ``afmctl sim`` settings from a TOML file (or defaults); errors name the field."""
    import tomllib

    from afmctl.errors import AfmctlError
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
    :mod:`sim_backend.scanner` is not available. Returns ``(sink, description)``."""
    try:
        from sim_backend.scanner import Scanner, ScannerConfig, default_scanner_config
    except ModuleNotFoundError as err:
        # Only a missing scanner module falls back (a stripped install): a scanner that is
        # there but fails to import is a bug to see, not to paper over.
        if err.name not in ("sim_backend.scanner", "sim_backend"):
            raise
        from sim_backend.amplifiers import RecordingSink
        log.warning("sim_backend.scanner unavailable (%s); the amplifier drives a recording sink, "
                    "no plant", err)
        return RecordingSink(max_history=10_000), f"recording sink (no scanner: {err})"
    from pydantic import ValidationError

    from afmctl.errors import AfmctlError
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

    ``SimService(settings, on_tick=None)``; ``on_tick(t_s, position_nm)`` is called every
    ``tick_s`` from the service thread after the plant advanced (the hook for publishing
    the true tip position, e.g. over zenoh). ``start()``, ``stop()``, ``port``,
    ``pty_path``, ``scanner``.
    """

    def __init__(self, settings, *, on_tick: Callable[[float, Any], None] | None = None) -> None:
        from sim_backend.amplifiers import make_device
        from sim_backend.amplifiers.base import elapsed_clock
        from sim_backend.amplifiers.pty_server import PtyServer
        self.settings = settings
        self.on_tick = on_tick
        self.scanner, self.description = make_scanner(settings.scanner)
        self.clock = elapsed_clock()
        amp = settings.amplifier
        self.device = make_device(amp.protocol, self.scanner, now=self.clock)
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
            from afmctl.errors import AfmctlError
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
                pos = self.scanner.position_nm() if hasattr(self.scanner, "position_nm") else None
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

    def __enter__(self) -> "SimService":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def run(args) -> int:
    from afmctl.errors import AfmctlError
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
    stop = threading.Event()

    def _on_signal(signum, frame):  # noqa: ARG001
        stop.set()

    old = {s: signal.signal(s, _on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        with SimService(settings) as service:
            print(service.pty_path, flush=True)
            print(f"link: {service.port}", flush=True)
            print(f"protocol: {settings.amplifier.protocol} at {settings.amplifier.baud} baud; "
                  f"load: {service.description}", flush=True)
            print("stop with Ctrl-C or SIGTERM", flush=True)
            stop.wait(args.duration)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    print("afmctl sim: stopped", file=sys.stderr, flush=True)
    return 0
