"""The simulated scanner as a service: a simulated amplifier on a pty driving a
:class:`afmctl.sim_backend.scanner.Scanner` that advances on the wall clock
(:class:`SimService`), and the decimating, never-blocking publisher of its true tip position
(:class:`TipPublisher`). ``afmctl sim`` (:mod:`afmctl.commands.sim`) is the command line around
them; tests and programs use them directly."""
from __future__ import annotations

import collections
import logging
import math
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from afmctl.compensators.errortext import validation_error_line
from afmctl.compensators.textfiles import read_text_file

from ..config import format_validation_error, parse_toml
from ..errors import AfmctlError
from ..zenoh_api.settings import ZenohSettings

log = logging.getLogger(__name__)

#: how often a ``--record`` file is flushed while the simulator runs [s]
RECORD_FLUSH_S = 0.5
#: how far the simulator's clock loop keeps the scanner behind the wall clock when the
#: device plays samples on its own clock (handed over on its polls: the server's and the
#: clock loop's own) [s]
DEVICE_CLOCK_LAG_S = 0.25


class AmplifierSection(BaseModel):
    """``[amplifier]``: the protocol the simulated amplifier speaks on its pty."""
    model_config = ConfigDict(extra="forbid")
    protocol: Literal["mdt693b", "mdt694b", "gcs", "nv200"] = "mdt693b"
    baud: int = Field(115200, ge=300, le=10_000_000)
    link: str | None = None
    #: serve on this loopback TCP endpoint HOST:PORT instead of a pty (an Ethernet port: gcs, nv200)
    tcp: str | None = None
    #: the NV200's actuator's position sensor ("none": an actuator without one, whose recorder
    #: records voltages only; another: the recorder records the simulated scanner's position)
    sensor: Literal["none", "strain gauge", "capacitive", "LVDT"] | None = None

    @field_validator("tcp")
    @classmethod
    def _loopback_endpoint(cls, v: str | None) -> str | None:
        if v is not None:
            from afmctl.sim_backend.amplifiers.tcp_server import parse_endpoint
            parse_endpoint(v)
        return v


class SimSection(BaseModel):
    """``[sim]``: the plant's wall-clock tick [s] and the tip publisher's rate [Hz] and queue."""
    model_config = ConfigDict(extra="forbid")
    tick_s: float = Field(0.01, gt=0, le=1.0)
    publish_rate_Hz: float = Field(100.0, ge=0.1, le=10_000.0)
    publish_queue: int = Field(64, ge=1, le=100_000)


class SimSettings(BaseModel):
    """The ``afmctl sim`` settings file: ``[amplifier]``, ``[sim]``, ``[scanner]`` (fields of
    :class:`afmctl.sim_backend.config.ScannerConfig`) and ``[zenoh]``."""
    model_config = ConfigDict(extra="forbid")
    amplifier: AmplifierSection = AmplifierSection()
    sim: SimSection = SimSection()
    scanner: dict[str, Any] = Field(default_factory=dict)
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)


def load_settings(path: Path | None):
    """The ``afmctl sim`` settings from a TOML file (or defaults); errors name the field."""
    data: dict[str, Any] = {}
    if path is not None:
        data = parse_toml(read_text_file(path, "simulator settings", AfmctlError), str(path))
    try:
        return SimSettings.model_validate(data)
    except ValidationError as err:
        raise AfmctlError(format_validation_error(err, str(path or "defaults"), SimSettings)) from None


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def make_scanner(overrides: dict[str, Any]):
    """The default simulated scanner with ``overrides`` (``[scanner]`` fields) merged in.
    Returns ``(scanner, description)``."""
    from afmctl.sim_backend.scanner import Scanner, ScannerConfig, default_scanner_config
    config = default_scanner_config()
    if overrides:
        try:
            config = ScannerConfig.model_validate(_merge(config.model_dump(), overrides))
        except ValidationError as err:
            raise AfmctlError(validation_error_line(err, "scanner.")) from None
    return Scanner(config), f"scanner {config.name} (dt_s={config.dt_s:g})"


class SimService:
    """A simulated amplifier on a pty driving a scanner that advances on the wall clock.

    ``SimService(settings, on_tick=None, record=None)``; ``on_tick(t_s, position_nm)`` is called every
    ``tick_s`` from the service thread after the plant advanced (the hook for publishing
    the true tip position, e.g. over zenoh). ``start()``, ``stop()``, ``port``,
    ``pty_path``, ``scanner``.
    """

    def __init__(self, settings, *, on_tick: Callable[[float, Any], object] | None = None,
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
                raise AfmctlError(f"--record {record}: cannot write ({err.strerror})") from None
        options = {} if amp.sensor is None else {"sensor": amp.sensor}
        if options and amp.protocol != "nv200":
            raise AfmctlError(f"amplifier.sensor: only the simulated nv200 has one to choose (protocol {amp.protocol})")
        self.device = make_device(amp.protocol, sink, now=self.clock, **options)
        if amp.tcp is not None:
            from afmctl.sim_backend.amplifiers.tcp_server import TcpServer, parse_endpoint
            host, port = parse_endpoint(amp.tcp)
            self.server: TcpServer | PtyServer = TcpServer(self.device, host=host, port=port)
        else:
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
            self.server.stop()
            raise AfmctlError(f"cannot serve the simulated amplifier on {self.server.port}: "
                              f"{err.strerror or err}") from None
        self._thread = threading.Thread(target=self._loop, name="afmctl-sim-clock", daemon=True)
        self._thread.start()
        return self

    def _loop(self) -> None:
        tick = self.settings.sim.tick_s
        advance = getattr(self.scanner, "advance", None)
        # a device with its own clock (a wave generator) hands its samples to the scanner
        # when polled (on the server's idle polls and before every command): the scanner
        # stays DEVICE_CLOCK_LAG_S behind here, so that those samples are never in its past
        # (they would be dropped: the table unplayed). A server busy sending a long reply
        # does not poll: when a point older than the scanner's next time is still unplayed,
        # this thread plays what fell due itself, under the device's lock, before it moves
        # the scanner. (Playing on every tick instead, it waited for the lock that the
        # server's thread takes again and again, and the tip went out a third as often:
        # tests/test_view_live.py 30 -> 90 s.)
        has_clock = hasattr(self.device, "poll")
        lag = DEVICE_CLOCK_LAG_S if has_clock else 0.0
        next_flush = self.clock() + RECORD_FLUSH_S
        while not self._stop.wait(tick):
            t = self.clock()
            if has_clock:
                due = self.device.next_due_s()
                if due is not None and due <= t - lag:
                    self.device.play_due(t)
            if advance is not None:
                advance(t - lag)
            if self.recorder is not None and t >= next_flush:
                self.recorder.flush()             # the record grows while the simulator runs
                next_flush = t + RECORD_FLUSH_S
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
    is the slow part (e.g. :meth:`afmctl.zenoh_api.sim_publisher.SimPublisher.publish_tip`, which uses
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


def scanner_name(settings) -> str:
    """The ``<scanner>`` key chunk: ``[scanner] name`` / ``--scanner``, else the default's."""
    name = settings.scanner.get("name")
    if name is None:
        from afmctl.sim_backend.config import ScannerConfig
        name = ScannerConfig.model_fields["name"].default
    return str(name)
