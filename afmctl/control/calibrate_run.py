"""``afmctl calibrate`` on a device: play voltage tables piece by piece on the amplifier's
clock and record each through the device's own data recorder (the position, the output
voltage, and the piezo voltage where the device records it).

Each piece (:mod:`afmctl.control.calibrate_pieces`) is played exactly as ``afmctl run``
plays a wave table (:class:`afmctl.control.controller.Controller`, ``output = "wave"``):
every row checked against the limits and the slew limit before anything is sent, the
upload while the output rests, the approach ramp and the settle hold
(``amplifier.settle_s``, unset: :data:`~afmctl.config.LEARN_SETTLE_S`) before the first
piece, the table on the device's clock, the device's recorder armed once the table is
on it (it starts with the table). Between pieces the output *holds* its last voltage
(the next piece starts there: no approach, no hold of its own), so the scanner's
hysteresis memory runs on unbroken; :func:`calibrate_pieces.join` puts the holds back.
On a device that reads its recorder while it records (the E-727, the CAN amplifier) each
piece is read back while it plays (:class:`LiveReadback`), so a hold lasts the upload, the
start and the last chunk of the read-back rather than the whole read-back. A device whose
recorder records a longer recording into a ring (the CAN amplifier: 8192 points) plays
pieces of up to :data:`RING_SPAN` rings, read in step; a piece whose read-back fell behind
(points overwritten) is played again in parts that do not go round the ring
(:func:`unringed_rows`), read back however late.

Requests: :meth:`CalibrationRun.stop` (Ctrl-C, zenoh ``stop``) stops the piece playing at
once (wave generator stopped / FIFO flushed, the output holds), then :func:`return_to_safe`
ramps every driven axis to its safe value at ``safety.ramp_V_per_s`` and stops anything
the device still plays. A lost link ends the run with :class:`CalibrationFault`; what was
recorded so far stays in :attr:`CalibrationRun.pieces`.

Units: V, nm, s.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config import LEARN_SETTLE_S, CompensationSection
from ..errors import AfmctlError
from .calibrate_pieces import PieceRecord, cut_points, follow_table, ramp_priorities
from .controller import Controller, State
from .learned_table import LearnedSource, LearnedTable
from .safety import SafetyLayer
from .wave_plan import WaveTable, table_capacity

log = logging.getLogger(__name__)

#: the signals a calibration asks a recorder for, best first (the NV200 records two)
SIGNAL_SETS = (("y_nm", "u_V", "v_V"), ("y_nm", "v_V"), ("y_nm", "u_V"))
#: recorded output voltages must equal the table within this [V] (the devices' resolution)
OUTPUT_TOL_V = 0.01
#: a return ramp that has not arrived after this [s] is given up (logged)
RETURN_TIMEOUT_S = 30.0
#: the longest read-back of one piece a stop may have to wait for [s] (see readback_rows)
UNCANCELLED_READBACK_S = 0.5
#: the NV200's serial line (also behind its Ethernet adapter) [baud], and the bytes of one
#: recorded value in its ``recoutf`` reply ("123.456,")
NV200_UART_BAUD, NV200_BYTES_PER_VALUE = 115200, 8
#: share of the recorder a streamed piece leaves free: the ticks a FIFO that ran empty held
#: the output are recorded too (the scanner saw them), after which the table goes on
STREAM_SLACK = 0.25
#: a piece on a ring (:func:`rings`) records at most this many times what the ring holds
#: (its table 75 % of that, :data:`STREAM_SLACK`): the read-back keeps within the ring while
#: it reads well over half as fast as the recorder records (the simulated CAN amplifier in
#: the calibrating process shares one core's worth of Python with the stream, the read-back
#: and the scanner's simulation: four rings fell behind there, two never did)
RING_SPAN = 2
#: points read past a streamed piece's last row (its tick: the rows plus the device's
#: underruns) — the recorder goes on recording the held output until its armed points are
#: in, which the read-back does not wait for
STREAM_TAIL = 16


class CalibrationFault(AfmctlError):
    """The link was lost (or the device faulted) during the calibration; what was recorded
    before is kept (:attr:`CalibrationRun.pieces`)."""


class CalibrationStopped(AfmctlError):
    """A stop request ended the calibration (the output was ramped to the safe value)."""


class TableSource(LearnedSource):
    """A planned table as the controller's trajectory (played as ``afmctl run`` plays a
    learned table), with its own settle hold [s]."""

    def __init__(self, table: WaveTable, settle_s: float, name: str) -> None:
        super().__init__(LearnedTable(table, {}, ""), name)
        self._settle_s = float(settle_s)

    def settle_s(self, config: Any) -> float:
        return self._settle_s

    def blocks_at(self, dt_s: float, block_samples: int = 256):
        from ..inputs.trajectories import blocks_of
        return blocks_of(self.targets_nm(), block_samples)

    def table_for(self, config: Any) -> WaveTable:
        return self.learned.table


def calibration_config(config: Any) -> Any:
    """``config`` as a calibration plays it: no compensation (the model is what it makes),
    the output held at the end of each piece, no reconnect (a lost link ends it), no run log
    per piece, the targets handed over in large blocks, the settle hold of
    ``amplifier.settle_s`` (unset: :data:`~afmctl.config.LEARN_SETTLE_S`)."""
    cfg = config.model_copy(deep=True)
    cfg.compensation = CompensationSection()
    cfg.safety.on_finish = "hold"
    cfg.safety.max_reconnects = 0       # a lost link ends the calibration (what was recorded is kept)
    cfg.runlog.enabled = False
    cfg.zenoh.enabled = False
    # a wave run collects a piece's targets whole before it plays: in 256-row blocks, eight
    # ahead, the hand-over took 0.09 s at the first row of an 87,381-row piece
    cfg.loop.block_samples, cfg.loop.prefetch_blocks = 65536, 1024
    if cfg.amplifier.settle_s is None:
        cfg.amplifier.settle_s = LEARN_SETTLE_S
    return cfg


def fifo_margins(config: Any, amp: Any) -> Any:
    """``config`` with the stream FIFO kept as full as the device allows (CAN: the FIFO
    filled to 90 % of its capacity, topped up below half). A table streamed into a FIFO must
    play without a gap — an underrun holds the output, and the recording no longer follows
    the table — so a calibration keeps the most margin a busy host can have."""
    status = getattr(amp, "buffer_status", None)
    if status is None:
        return config
    seconds = status().capacity / float(config.loop.rate_Hz)
    config.amplifier.high_water_s = max(config.amplifier.high_water_s, 0.9 * seconds)
    config.amplifier.low_water_s = max(config.amplifier.low_water_s, min(0.5 * seconds,
                                                                          0.8 * config.amplifier.high_water_s))
    return config


def recorder_signals(amp: Any, axis: str) -> tuple[str, ...]:
    """The richest of :data:`SIGNAL_SETS` the device records for ``axis``; one line when it
    records no position."""
    from afmctl.drivers.errors import AmplifierError
    if not getattr(amp, "has_recorder", False):
        raise AfmctlError(f"amplifier.driver = '{amp.name}' has no data recorder this driver reads: record the motion "
                          "with an external sensor (afmctl excite, then afmctl identify --data)")
    last: Exception | None = None
    for sig in SIGNAL_SETS:
        try:
            amp.recorder_capacity([axis], sig)
            return sig
        except AmplifierError as err:
            last = err
    raise AfmctlError(f"afmctl calibrate: the {amp.name} records no position of axis {axis}: {last}")


def readback_rows(amp: Any, signals: tuple[str, ...]) -> int | None:
    """The most rows a piece may have so that reading it back takes at most
    :data:`UNCANCELLED_READBACK_S` of wire time, for a device whose read-back cannot be
    cancelled mid-way (the NV200: its wave hands the output back by reading the recorder,
    ``recoutf`` of every point, at 115200 baud even behind an Ethernet adapter — a stop
    waits for it); None for the others (GCS reads in cancellable chunks, CAN frame by frame)."""
    if getattr(amp, "name", "") != "nv200":
        return None
    transport = getattr(amp, "transport", None)
    baud = getattr(transport, "baudrate", 0) if not str(getattr(transport, "url", "")).startswith("socket://") else 0
    bytes_per_s = (baud if baud > 0 else NV200_UART_BAUD) / 10.0
    return max(1, int(UNCANCELLED_READBACK_S * bytes_per_s / (NV200_BYTES_PER_VALUE * len(signals))))


def share_recorder(amp: Any, tables: int) -> Callable[[], None] | None:
    """The recorder's memory shared among ``tables`` tables (one per signal a piece records)
    where the device shares its memory among its tables and lets the host choose how many
    (the E-727: 262,144 points; 8 tables hold 32,768 each, 3 hold 87,381). Fewer, longer
    pieces: less time between them and fewer joins. Returns what puts the device's tables
    back as they were (a link lost by then is logged), None when nothing changed."""
    from afmctl.drivers.errors import AmplifierError
    before = amp.record_tables()
    if before is None or before <= tables:
        return None
    now = amp.set_record_tables(tables)
    if now == before:
        return None
    log.info("%s: the recorder's memory shared among %s tables (was %d) for the calibration", amp.name, now, before)

    def restore() -> None:
        try:
            amp.set_record_tables(before)
        except AmplifierError as err:
            log.warning("%s: the recorder's %d tables were not restored: %s", amp.name, before, err)
    return restore


def streams(amp: Any) -> bool:
    """Whether ``amp`` plays a table by streaming it into a FIFO (CAN) rather than from a
    wave table on the device (GCS, NV200)."""
    return table_capacity(amp, ["x"] if "x" in amp.axes else list(amp.axes)[:1]) is None


def device_capacity(amp: Any, axis: str, signals: tuple[str, ...]) -> int:
    """The most rows one piece may have on ``amp`` for ``axis``: its recorder's points per
    signal (:func:`recording_points`: on a ring, the most one arm takes), and its wave
    table's size (a wave generator); a streamed table (:func:`streams`) leaves
    :data:`STREAM_SLACK` of the recording for the holds of a FIFO that runs empty."""
    rec = int(recording_points(amp, axis, signals))
    table = table_capacity(amp, [axis])
    if table is None:
        return max(1, int(rec * (1.0 - STREAM_SLACK)))
    return min(rec, table)


def rings(amp: Any) -> bool:
    """Whether a piece on ``amp`` may be longer than its recorder holds: a ring read back
    while it records, faster than it records (the CAN amplifier on a CAN FD bus,
    :attr:`~afmctl.drivers.base.Amplifier.records_ring`; on a classic bus each point comes
    back as two frames, at 0.3–0.4× the play: its pieces fit the recorder)."""
    return bool(getattr(amp, "records_ring", False) and getattr(amp, "reads_while_recording", False)
                and getattr(amp, "stream_fd", False) and READ_WHILE_PLAYING)


def recording_points(amp: Any, axis: str, signals: tuple[str, ...]) -> int:
    """The most points one piece's recording may have: what the recorder holds, or on a
    device that :func:`rings`, the most one arm takes."""
    held = int(amp.recorder_capacity([axis], signals))
    if rings(amp):
        return min(int(amp.recorder_max_points([axis], signals)), RING_SPAN * held)
    return held


def unringed_rows(amp: Any, axis: str, signals: tuple[str, ...]) -> int:
    """The most rows a streamed piece may have for its recording (its rows and
    :data:`STREAM_SLACK`'s room for holds, :meth:`CalibrationRun._arm`) to stay within what
    ``amp``'s recorder holds: never round a ring, nothing overwritten however late it is read."""
    held = int(amp.recorder_capacity([axis], signals))
    return max(1, int((held - 1) * (1.0 - STREAM_SLACK)))


def live_chunk(amp: Any, axis: str, signals: tuple[str, ...], points: int) -> int:
    """Points a :class:`LiveReadback` reads at a time: :data:`LIVE_CHUNK`, or an eighth of a
    shorter piece; on a ring an eighth of what the ring holds (each chunk is read long before
    it is overwritten)."""
    chunk = min(LIVE_CHUNK, max(256, points // 8))
    if rings(amp):
        chunk = min(chunk, max(1, int(amp.recorder_capacity([axis], signals)) // 8))
    return chunk


#: points per read of a recording read back while it is taken (:class:`LiveReadback`): a
#: ``DRR?`` of 8192 points of three tables takes 0.2–0.4 s on loopback TCP, the longest a
#: stop or the controller's poll of the wave generator waits for it; a shorter piece reads
#: an eighth of its points at a time (so that most of it is read while it plays)
LIVE_CHUNK = 8192
#: read a piece's recording while it plays (:class:`LiveReadback`) on a device that
#: ``reads_while_recording`` (the simulated E-727 plays its tables from the simulator's
#: clock thread, so a long ``DRR?`` reply holding its server no longer stalls the table)
READ_WHILE_PLAYING = True
#: chunks one :meth:`LiveReadback.step` reads at most (a reader behind the recorder catches up)
LIVE_CATCH_UP = 8


class LiveReadback:
    """A piece's recording read back while the table plays, on a device that
    ``reads_while_recording`` (the E-727: ``DRR?`` answers with what ``DRL?`` says is
    recorded): :meth:`step`, called while the piece plays, reads :data:`LIVE_CHUNK` points
    once that many more are recorded; :meth:`rest` reads what remains once the table has
    played. Reading overlaps the play, so a piece costs its play and the last chunk rather
    than its play and a whole read-back. A link error while the table plays ends the live
    reading (the controller's own poll meets the same link and ends the piece)."""

    def __init__(self, amp: Any, points: int, chunk: int = LIVE_CHUNK) -> None:
        self.amp, self.points, self.chunk = amp, int(points), int(chunk)
        self.parts: list[Any] = []
        self.got = 0
        self.failed: Exception | None = None

    def step(self, t_start: float | None, rate_Hz: float) -> None:
        """Read the chunks of new points recorded (never waits for them; at most
        :data:`LIVE_CATCH_UP` of them, so that a reader that fell behind catches up); the
        device is asked (``DRL?``) only once the host clock since the table's start
        ``t_start`` (``time.monotonic()``, None: not started) at ``rate_Hz`` says they are."""
        from afmctl.drivers.errors import AmplifierError
        if self.failed is not None or t_start is None:
            return
        try:
            for _ in range(LIVE_CATCH_UP):
                want = min(self.chunk, self.points - self.got)
                if want <= 0 or (time.monotonic() - t_start) * rate_Hz < self.got + want:
                    return
                ready = min(self.amp.recorded_points(), self.points) - self.got
                if ready < want:
                    return
                self._read(want)
                time.sleep(0.001)       # the link to the player (a FIFO topped up) between two reads
        except AmplifierError as err:
            self.failed = err

    def _read(self, n: int) -> None:
        self.parts.append(self.amp.read_recorded(self.got, n))
        self.got += n

    def rest(self, timeout_s: float, cancel: Callable[[], bool]) -> Any:
        """The rest of the recording once recorded (at most ``timeout_s`` [s] of waiting),
        in chunks (``cancel()`` asked between them: :class:`RecordingCancelled`), joined with
        what :meth:`step` read."""
        from afmctl.drivers.errors import AmplifierTimeout, RecordingCancelled
        from afmctl.drivers.recording import joined_recording
        if cancel():
            raise RecordingCancelled(f"{self.amp.name}: the read-back of the recording was cancelled")
        if self.failed is not None:
            raise self.failed
        deadline = time.monotonic() + timeout_s
        while self.got < self.points:
            if cancel():
                raise RecordingCancelled(f"{self.amp.name}: the read-back of the recording was cancelled")
            ready = min(self.amp.recorded_points(), self.points) - self.got
            if ready > 0:
                self._read(min(ready, self.chunk))
                continue
            if time.monotonic() > deadline:
                raise AmplifierTimeout(f"{self.amp.name}: the recording holds {self.got} of {self.points} points "
                                       f"after {timeout_s:g} s")
            time.sleep(0.02)
        return joined_recording(self.parts)


@dataclass
class Progress:
    """Where a calibration is: ``what`` (``excite x``, ``validate x``), piece ``k`` of
    ``n``, seconds of excitation to go ``left_s``."""

    what: str
    k: int
    n: int
    left_s: float


class CalibrationRun:
    """Plays tables on one open amplifier and records them (module docstring).
    ``config``: a run configuration (``output = "wave"``); ``on_progress``: called before
    each piece."""

    def __init__(self, config: Any, amp: Any, on_progress: Callable[[Progress], None] | None = None,
                 record_timeout_s: float = 30.0) -> None:
        if config.amplifier.output != "wave":
            raise AfmctlError("amplifier.output: afmctl calibrate plays the excitation on the amplifier's clock; "
                              "set output = 'wave'")
        self.config = fifo_margins(calibration_config(config), amp)
        self.amp = amp
        self.on_progress = on_progress
        self.record_timeout_s = record_timeout_s
        self.axes = [a for a in config.scanner.axes if a in amp.axes]
        self.hold_V = {a: config.safety.safe_value(a) for a in self.axes}
        #: every piece recorded so far, per what was played (``excite x`` ...)
        self.pieces: dict[str, list[PieceRecord]] = {}
        self._stop = threading.Event()
        self._ctl: Controller | None = None
        self._first = True
        self._axis_configs: dict[str, Any] = {}

    @property
    def dt_s(self) -> float:
        return float(self.config.dt_s)

    def play(self, what: str, axis: str, signals: tuple[str, ...], tables: list[np.ndarray],
             starts: list[int], left_s: Callable[[int], float],
             priorities: list[np.ndarray] | None = None) -> list[PieceRecord]:
        """Play ``tables`` (voltages of ``axis`` [V], one piece each) in turn, recording
        ``signals``; the other axes hold :attr:`hold_V` (ramped there before the first
        piece; only ``axis``'s table is uploaded). ``priorities``: each table's cut
        priorities (:mod:`.calibrate_pieces`; default its ramps' turning points), for a piece
        that has to be played again in parts. Raises :class:`CalibrationStopped` on a stop,
        :class:`CalibrationFault` on a lost link."""
        got = self.pieces.setdefault(what, [])
        if self._first and not self._stop.is_set():
            self._to_safe()
        for k, (u, start) in enumerate(zip(tables, starts)):
            if self._stop.is_set():
                raise CalibrationStopped("afmctl calibrate: stopped")
            if self.on_progress is not None:
                self.on_progress(Progress(what, k, len(tables), left_s(k)))
            prio = priorities[k] if priorities is not None else ramp_priorities(u)
            got.extend(self._played_piece(axis, signals, u, start, prio))
        return got

    def _played_piece(self, axis: str, signals: tuple[str, ...], u: np.ndarray, start: int,
                      priority: np.ndarray) -> list[PieceRecord]:
        """:meth:`_piece`; when its read-back fell behind a ring recorder (:func:`rings`: a
        host too busy to read in step), the piece is played again in parts the recorder holds
        without going round its ring (:func:`unringed_rows`, cut by ``priority``), whose
        points stay until they are read however late (what was recorded before is kept)."""
        from afmctl.drivers.errors import RecordingOverwritten
        try:
            return [self._piece(axis, signals, u, start)]
        except RecordingOverwritten as err:
            if self._stop.is_set():
                raise CalibrationStopped("afmctl calibrate: stopped") from None
            most = unringed_rows(self.amp, axis, signals)
            log.warning("%s: the read-back fell behind the recorder (%s); playing the piece at sample %d again in "
                        "parts of at most %d rows", self.amp.name, err, start, most)
        try:
            parts = cut_points(priority, most)
        except ValueError as err:
            raise CalibrationFault(f"afmctl calibrate: the read-back fell behind the {self.amp.name}'s recorder and "
                                   f"the piece at sample {start} cannot be cut to fit it ({err}): the host is too "
                                   "busy to read in step; calibrate again on a quieter machine") from None
        try:
            return [self._piece(axis, signals, u[a:b], start + a) for a, b in parts]
        except RecordingOverwritten:
            raise CalibrationFault(f"afmctl calibrate: the read-back fell behind the {self.amp.name}'s recorder twice "
                                   "(points overwritten before they were read): the host is too busy to read in "
                                   "step; calibrate again on a quieter machine") from None

    def _rows(self, axis: str, u: np.ndarray) -> np.ndarray:
        rows = np.zeros((len(u), 3))
        for a in self.axes:
            rows[:, "xyz".index(a)] = self.hold_V[a]
        rows[:, "xyz".index(axis)] = u
        return rows

    def _axis_config(self, axis: str) -> Any:
        """The calibration's configuration driving ``axis`` alone (its table is the only one
        uploaded and played; the other outputs hold)."""
        if axis not in self._axis_configs:
            cfg = self.config.model_copy(deep=True)
            cfg.scanner.axes = [axis]
            self._axis_configs[axis] = cfg
        return self._axis_configs[axis]

    def _to_safe(self) -> None:
        """Every driven axis to its safe value before anything plays (a lost link here is a
        fault as during a piece)."""
        from afmctl.drivers.errors import AmplifierConnectionError, AmplifierTimeout
        try:
            for note in return_to_safe(self.config, self.amp):
                log.info("before the calibration: %s", note)
        except (AmplifierTimeout, AmplifierConnectionError) as err:
            raise CalibrationFault(f"afmctl calibrate: the link failed before the first piece: {err}") from None

    def _piece(self, axis: str, signals: tuple[str, ...], u: np.ndarray, start: int) -> PieceRecord:
        """One table played and recorded (module docstring)."""
        n = len(u)
        table = WaveTable(np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), self._rows(axis, u),
                          np.full(n, float(self.config.compensation.temperature.T_C)), 0)
        settle = float(self.config.amplifier.settle_s) if self._first else 0.0
        armed: list[Any] = []
        ctl = Controller(self._axis_config(axis), self.amp)
        live = (LiveReadback(self.amp, n, live_chunk(self.amp, axis, signals, n))
                if READ_WHILE_PLAYING and getattr(self.amp, "reads_while_recording", False) else None)

        def arm() -> None:
            armed.append(self._arm(axis, signals, n))
            if live is not None:            # a stream's recording has room for its holds
                live.points = int(armed[-1].points)
        ctl.before_wave_start = arm
        self._ctl = ctl
        try:
            ctl.start(TableSource(table, settle, f"calibration piece at sample {start}"))
            if self._stop.is_set():
                ctl.stop()
            while not ctl.wait(0.05):
                if live is not None and armed and not self._stop.is_set():
                    live.step(ctl.wave_times.get("start"), self.config.loop.rate_Hz)   # read back while it plays
            stats = ctl.stats()
        finally:
            ctl.close()
            self._ctl = None
        self._first = False
        played = int((stats.get("wave") or {}).get("played", 0))
        if ctl.trajectory_error is not None:
            raise AfmctlError(f"afmctl calibrate: the table cannot be played: {ctl.trajectory_error}")
        if ctl.state is not State.STOPPED:
            raise CalibrationFault(f"afmctl calibrate: the link failed during the play ({ctl.state.value}: "
                                   f"{stats.get('last_error') or 'see the log'})")
        if played != n or not armed:
            raise CalibrationStopped(f"afmctl calibrate: stopped during a piece ({played} of {n} samples played)")
        if live is not None and streams(self.amp):     # the table's last row is at tick n - 1 + underruns
            underruns = int((stats.get("stream") or {}).get("underruns") or 0)
            live.points = min(live.points, n + underruns + STREAM_TAIL)
        return self._read(axis, table, start, float(ctl.wave_times.get("start", time.monotonic())), live)

    def _arm(self, axis: str, signals: tuple[str, ...], points: int) -> Any:
        clock = self.amp.recorder_clock_s()
        divider = max(1, round(self.dt_s / clock))
        if abs(divider * clock - self.dt_s) > 1e-9 * self.dt_s + 1e-12:
            raise AfmctlError(f"loop.rate_Hz: {self.config.loop.rate_Hz:g} Hz is not a whole number of the "
                              f"recorder's {clock:g} s ticks")
        if streams(self.amp):      # room for the holds of a FIFO that runs empty (STREAM_SLACK)
            points = max(points, min(recording_points(self.amp, axis, signals),
                                     int(points / (1.0 - STREAM_SLACK)) + 1))
        return self.amp.configure_recorder([axis], points=points, divider=divider, signals=signals)

    def _read(self, axis: str, table: WaveTable, start: int, t_start: float,
              live: "LiveReadback | None" = None) -> PieceRecord:
        from afmctl.drivers.errors import (AmplifierConnectionError, AmplifierTimeout, ProtocolError,
                                           RecordingCancelled, RecordingOverwritten)
        from afmctl.drivers.recording import RecordingMismatch, align_to_table
        u = table.u_V[:, "xyz".index(axis)]
        try:
            if live is not None:
                rec = live.rest(self.record_timeout_s, self._stop.is_set)
            else:
                rec = self.amp.read_recording(timeout_s=self.record_timeout_s, cancel=self._stop.is_set)
        except RecordingCancelled:
            raise CalibrationStopped("afmctl calibrate: stopped while the recording was read back") from None
        except RecordingOverwritten:
            raise                       # _played_piece plays the piece again
        except (AmplifierTimeout, AmplifierConnectionError, ProtocolError) as err:
            raise CalibrationFault(f"afmctl calibrate: reading the recording failed: {err}") from None
        if streams(self.amp) and axis in rec.u_V:
            return self._streamed(axis, rec, u, start, t_start)
        try:
            rec = align_to_table(rec, {axis: u.tolist()}, tol_V=OUTPUT_TOL_V)
        except RecordingMismatch as err:
            raise CalibrationFault(f"afmctl calibrate: {err}") from None
        v = rec.v_V.get(axis)
        return PieceRecord(start, u.copy(), np.asarray(rec.y_nm[axis], dtype=float),
                           None if v is None else np.asarray(v, dtype=float), t_start)

    def _streamed(self, axis: str, rec: Any, u: np.ndarray, start: int, t_start: float) -> PieceRecord:
        """A streamed piece: the output the recorder saw (the table with the holds of a FIFO
        that ran empty: what the scanner was driven with) up to the table's last row."""
        played = np.asarray(rec.u_V[axis], dtype=float)
        try:
            n = follow_table(played, u, OUTPUT_TOL_V)
        except ValueError as err:
            raise CalibrationFault(f"afmctl calibrate: axis {axis}: {err}") from None
        if n > len(u):
            log.info("axis %s: the stream held the output for %d ticks of a %d-row piece", axis, n - len(u), len(u))
        v = rec.v_V.get(axis)
        return PieceRecord(start, played[:n].copy(), np.asarray(rec.y_nm[axis][:n], dtype=float),
                           None if v is None else np.asarray(v[:n], dtype=float), t_start)

    # ------------------------------------------------------------------ requests
    def stop(self) -> None:
        """End the calibration: the piece playing stops at once (the output holds), then
        :meth:`finish` ramps to the safe value."""
        self._stop.set()
        ctl = self._ctl
        if ctl is not None:
            ctl.stop()

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    def finish(self) -> list[str]:
        """Stop anything the device still plays and ramp every driven axis to its safe value
        (:func:`return_to_safe`); one line per thing done."""
        return return_to_safe(self.config, self.amp)


def return_to_safe(config: Any, amp: Any, timeout_s: float = RETURN_TIMEOUT_S) -> list[str]:
    """Stop what ``amp`` plays on its own clock (wave generator, FIFO), read the output back
    and ramp every driven axis of ``config`` to ``safety.safe_V`` at ``safety.ramp_V_per_s``
    within the limits and the slew limit."""
    axes = [a for a in config.scanner.axes if a in amp.axes]
    dt = max(float(config.dt_s), 0.002)
    safety = SafetyLayer(amp, axes, {a: config.limits(a) for a in axes}, config.slew_V_per_s(), dt,
                         {a: config.safety.safe_value(a) for a in axes})
    notes = safety.stop_leftover_playback()
    notes += safety.sync_from_device()
    target = [config.safety.safe_value(a) for a in axes]
    deadline = time.monotonic() + timeout_s
    while not safety.ramp_step(target, config.safety.ramp_V_per_s):
        if time.monotonic() > deadline:
            notes.append(f"the return to the safe value did not arrive within {timeout_s:g} s")
            break
        time.sleep(dt)
    amp.flush()
    notes.append("the output ramped to the safe value")
    return notes
