"""Physik Instrumente GCS controllers, open-loop subset (``SVO``, ``SVA``, ``VOL?``,
``VMI``/``VMA``, ``ERR?``) over serial.

Streaming: ``SVA`` has no reply, so setpoints are written back to back; every
``check_every`` setpoints the driver appends ``ERR?`` to the same write and reads that
reply when it has arrived (at most one check outstanding) — an error latched by the
device is raised as :class:`~afmctl.drivers.errors.ProtocolError` with its GCS code.
Connect resynchronises on the reply to ``*IDN?`` (no fixed quiet window), so replies that
arrive 100 ms late are fine.

Wave tables (:mod:`.codec_gcs_wave`): :meth:`GCSAmplifier.upload_wave` checks a whole table
(limits, ``max_step_V`` between samples and from the present output) before its first byte
is sent, then writes it back to back with one ``ERR?`` at the end; :meth:`~GCSAmplifier.start_wave`
plays the uploaded tables on the controller's servo clock (axis k on generator and table k).
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any, cast

import numpy as np

from . import codec_gcs as codec
from . import codec_gcs_rec as rcodec
from . import codec_gcs_wave as wcodec
from .base import VoltageLimits
from .errors import LimitError, ProtocolError, RecordingCancelled
from .recording import Recording, RecorderSetup, time_axis
from .wave_check import WaveStatus, check_table
from .serial_amp import SerialAmplifier
from .transport import SerialTransport

log = logging.getLogger(__name__)

_AXES = ("x", "y", "z")


#: longest wait for one line of a data recorder's buffered reply (``DRR?``) [s]
RECORD_LINE_TIMEOUT_S = 5.0
#: a read-back goes in ``DRR?`` chunks of about this much wire time [s] (a cancel waits at
#: most one), of RECORD_CHUNK_MIN .. RECORD_CHUNK_MAX points
RECORD_CHUNK_S, RECORD_CHUNK_MIN, RECORD_CHUNK_MAX = 0.5, 256, 8192

class GCSAmplifier(SerialAmplifier):
    """``GCSAmplifier(transport, n_axes=3, check_every=50, host_limits=None, ...)``.
    Axes x, y, z map onto the first ``n_axes`` GCS axis identifiers reported by ``SAI?``
    (and the voltage channels 1..n)."""

    name = "gcs"
    has_recorder = True

    def __init__(self, transport: SerialTransport, *, n_axes: int = 3, check_every: int = 50, **options) -> None:
        if not 1 <= n_axes <= 3:
            raise ValueError("n_axes must be 1..3")
        self._axes = _AXES[:n_axes]
        self.check_every = max(1, int(check_every))
        self._ids: dict[str, str] = {}
        self._check_outstanding = False
        self._since_check = 0
        self._tables: dict[str, np.ndarray] = {}
        self._servo_cycle_s: float | None = None
        self._capacity: dict[str, int] = {}
        self._wave_run = (0.0, 0, 0)
        self._playing: set[str] = set()
        super().__init__(transport, **options)

    @property
    def axes(self) -> tuple[str, ...]:
        return self._axes

    def _reset_pipeline(self) -> None:
        self._check_outstanding = False
        self._since_check = 0

    def _query(self, command: str) -> bytes:
        self._settle()
        self.transport.write(codec.encode(command))
        return self.transport.read_frame(codec.split_reply)

    def _settle(self) -> None:
        """Take the replies already here and wait for the one to a pipelined ``ERR?`` still
        on its way, so that the next query's reply is the next frame (a ``#9`` answered
        with that ``ERR?``'s ``0`` would read as "no generator runs")."""
        self._drain()
        if self._check_outstanding:
            reply = self.transport.read_frame(codec.split_reply)
            self._check_outstanding = False
            codec.check_error_reply(reply)

    def _check(self) -> None:
        codec.check_error_reply(self._query("ERR?"))

    def _handshake(self):
        # resynchronise on *IDN? (its reply holds commas, no other reply here does), then
        # read and clear an error latched before we came
        idn = self.transport.resync(codec.TERMINATOR, codec.encode("*IDN?"), codec.split_reply,
                                    lambda frame: b"," in frame).decode("ascii", "replace").strip()
        codec.parse_error_code(self._query("ERR?"))
        ids = codec.parse_axes(self._query("SAI?"))
        if len(ids) < len(self._axes):
            raise ProtocolError(f"controller has {len(ids)} axes, {len(self._axes)} needed", data=",".join(ids).encode())
        self._ids = dict(zip(self._axes, ids))
        id_list = " ".join(self._ids.values())
        self.transport.write(codec.encode("SVO " + " ".join(f"{i} 0" for i in self._ids.values())))
        self._check()
        chans = [str(k + 1) for k in range(len(self._axes))]
        vmi = codec.parse_items(self._query("VMI? " + " ".join(chans)), chans)
        vma = codec.parse_items(self._query("VMA? " + " ".join(chans)), chans)
        limits = {}
        for a, ch in zip(self._axes, chans):
            if not vmi[ch] <= vma[ch]:
                raise ProtocolError(f"device limits of axis {a} are empty: [{vmi[ch]}, {vma[ch]}] V")
            limits[a] = VoltageLimits(vmi[ch], vma[ch])
        return limits, {"identity": idn, "gcs_axes": id_list}

    def _read_voltages(self) -> dict[str, float]:
        chans = [str(k + 1) for k in range(len(self._axes))]
        items = codec.parse_items(self._query("VOL? " + " ".join(chans)), chans)
        return {a: items[ch] for a, ch in zip(self._axes, chans)}

    def _drain(self) -> None:
        for reply in self.transport.take_frames(codec.split_reply):
            if not self._check_outstanding:
                raise ProtocolError("unsolicited reply from GCS controller", data=reply)
            self._check_outstanding = False
            codec.check_error_reply(reply)

    def _write_setpoint(self, values: dict[str, float]) -> None:
        playing = sorted(self._playing.intersection(values))
        if playing:
            raise LimitError(f"axis {playing[0]}: its wave generator runs; stop_wave(), or wait until "
                             "wave_status() reports its end, before setting voltages")
        by_id = {self._ids[a]: v for a, v in values.items()}
        lows = {self._ids[a]: self._limits[a].min_V for a in values}
        highs = {self._ids[a]: self._limits[a].max_V for a in values}
        data = codec.encode_sva(by_id, lows, highs)
        self._drain()
        self._since_check += 1
        if self._since_check >= self.check_every and not self._check_outstanding:
            data += codec.encode("ERR?")
            self._check_outstanding = True
            self._since_check = 0
        self.transport.write(data)

    def _sync(self) -> None:
        self._check()       # settles a pipelined ERR? first
        self._since_check = 0

    # ---- wave generator ----
    def _gen(self, axis: str) -> int:
        if axis not in self._axes:
            raise LimitError(f"axis {axis!r}: not one of {', '.join(self._axes)}")
        return self._axes.index(axis) + 1

    def servo_cycle_s(self) -> float:
        """The controller's servo update time [s] (parameter 0x0E000200, read once)."""
        with self._lock:
            self._guard()
            if self._servo_cycle_s is None:
                reply = self._io(self._query, f"SPA? 1 {wcodec.SERVO_UPDATE_TIME_PARAM}")
                self._servo_cycle_s = wcodec.parse_servo_cycle_s(reply)
            return self._servo_cycle_s

    def wave_capacity(self, axis: str) -> int:
        """The most points the wave table of ``axis`` takes (``WMS?``, read once)."""
        gen = self._gen(axis)
        with self._lock:
            self._guard()
            if axis not in self._capacity:
                reply = self._io(self._query, f"WMS? {gen}")
                self._capacity[axis] = wcodec.parse_table_capacity(reply, gen)
            return self._capacity[axis]

    def upload_wave(self, axis: str, table_V: Sequence[float]) -> int:
        """Write ``table_V`` [V] as the wave table of ``axis``; returns the points written.
        Every sample is checked (limits, ``max_step_V`` from the previous one and from the
        present output) and the length against :meth:`wave_capacity` before anything is
        sent: :class:`LimitError` names the sample or the capacity."""
        gen = self._gen(axis)
        with self._lock:        # re-entrant: wave_capacity() takes it too
            self._guard()
            v = check_table(axis, table_V, self._limits[axis], max_step_V=self.max_step_V,
                            start_V=self._last.get(axis))
            capacity = self.wave_capacity(axis)
            if len(v) > capacity:
                raise LimitError(f"wave table of axis {axis}: {len(v)} points, the controller's table holds "
                                 f"{capacity} (WMS?); nothing was sent")
            lim = self._limits[axis]
            lines = wcodec.encode_wav_pnt(gen, v, lim.min_V, lim.max_V)
            self._io(self._send_checked, *lines)
            self._tables[axis] = v
            return len(v)

    def _send_checked(self, *chunks: bytes) -> None:
        """Write ``chunks`` back to back (one write each: the transport paces them to the
        link, so no write outlasts its timeout), then one ``ERR?``."""
        self._drain()
        for data in chunks:
            self.transport.write(data)
        self._check()

    def start_wave(self, rate_Hz: float | None = None, *, divider: int | None = None, cycles: int = 1,
                   axes: Sequence[str] | None = None) -> WaveStatus:
        """Play the uploaded tables of ``axes`` (default: all uploaded) ``cycles`` times
        (0 = until :meth:`stop_wave`) at ``rate_Hz`` points/s — which must be the servo rate
        over a whole number — or every ``divider`` servo cycles. The step from the present
        output to sample 0, and the wrap when it plays more than once, are checked first."""
        axes = list(axes if axes is not None else self._tables)
        if not axes or any(a not in self._tables for a in axes):
            raise LimitError("start_wave: upload a table for every axis first (upload_wave)")
        if not (isinstance(cycles, int) and 0 <= cycles <= 2**31 - 1):
            raise LimitError(f"cycles: {cycles!r} must be a whole number 0..2147483647 (0 = endless)")
        cycle_s = self.servo_cycle_s()
        if divider is None:
            if rate_Hz is None:
                raise LimitError("start_wave: give rate_Hz or divider")
            try:
                divider = wcodec.divider_for(rate_Hz, cycle_s)
            except ValueError as err:
                raise LimitError(f"rate_Hz: {err}") from None
        if not (isinstance(divider, int) and 1 <= divider <= 2**31 - 1):
            raise LimitError(f"divider: {divider!r} must be a whole number of servo cycles >= 1")
        with self._lock:
            self._guard()
            for a in axes:
                check_table(a, self._tables[a], self._limits[a], max_step_V=self.max_step_V,
                            start_V=self._last.get(a), wraps=cycles != 1)
            self._check_no_offset(axes)
            self._io(self._send_checked, wcodec.encode_start([self._gen(a) for a in axes], divider, cycles))
            self._wave_run = (1.0 / (divider * cycle_s), divider, cycles)
            self._playing = set(axes)
        return self.wave_status()

    def _check_no_offset(self, axes: Sequence[str]) -> None:
        """Refuse to start when a generator adds an output offset (``WOS``): the tables were
        checked against the limits as they are. The driver does not change the setting (it
        may be stored in the controller); the user sets it to 0 (``WOS <gen> 0``)."""
        gens = [self._gen(a) for a in axes]
        offsets = wcodec.parse_offsets(self._io(self._query, "WOS? " + " ".join(map(str, gens))), gens)
        for a, g in zip(axes, gens):
            if offsets[g] != 0.0:
                raise LimitError(f"wave generator {g} (axis {a}) adds an output offset WOS of {offsets[g]:g} V to "
                                 "every table value, so the checked table would not be what plays; set it to 0 "
                                 f"(WOS {g} 0) first; nothing was started")

    def wave_status(self) -> WaveStatus:
        """Ask the controller (``#9``) which generators run; once an axis's generator has
        stopped, its output is read back (``VOL?``) as the reference of the next step check."""
        with self._lock:
            self._guard()
            mask = wcodec.parse_running(self._io(self._running_reply))
            running = {a: bool(mask >> (self._gen(a) - 1) & 1) for a in self._axes}
            done = [a for a in self._playing if not running[a]]
            if done:
                volts = self._io(self._read_voltages)
                self._last.update({a: volts[a] for a in done})
                self._measured.update(done)
                self._playing -= set(done)
        rate, div, cyc = self._wave_run
        return WaveStatus(running, rate, div, cyc, {a: len(t) for a, t in self._tables.items()})

    def _running_reply(self) -> bytes:
        self._settle()
        self.transport.write(wcodec.RUNNING)
        return self.transport.read_frame(codec.split_reply)

    def stop_wave(self) -> WaveStatus:
        """Stop every wave generator now (``WGO g 0``); the outputs hold where they were."""
        with self._lock:
            # no _guard() and the stop written first: an estop must reach the generators even
            # with an error latched or a stray reply waiting
            self._io(self.transport.write, wcodec.encode_stop([self._gen(a) for a in self._axes]))
            self._io(self._check)
        return self.wave_status()

    # ---- data recorder (the Amplifier template's configure_recorder / read_recording) ----
    reads_while_recording = True

    def _recorder_clock_s(self) -> float:
        return self.servo_cycle_s()

    def _recorder_capacity(self, axes: tuple[str, ...], signals: tuple[str, ...]) -> int:
        """Points per record table: the controller's points over its tables (SPA?
        0x16000200 / 0x16000300, as PIPython reads them); 0 when it has too few tables."""
        tables = self._record_tables()
        if tables < len(axes) * len(signals):
            raise LimitError(f"the controller has {tables} record tables (TNR?); {len(axes) * len(signals)} "
                             "are needed for these axes and signals")
        total = rcodec.parse_param(self._query(f"SPA? 1 {rcodec.MAX_POINTS_PARAM}"), rcodec.MAX_POINTS_PARAM)
        chans = rcodec.parse_param(self._query(f"SPA? 1 {rcodec.CHAN_NUMBER_PARAM}"), rcodec.CHAN_NUMBER_PARAM)
        if not (total >= 1 and chans >= 1):
            raise ProtocolError(f"data recorder size {total:g} points / {chans:g} tables is not usable")
        return int(total // chans)

    def _record_tables(self) -> int:
        return rcodec.parse_int(self._query("TNR?"), "TNR?")

    def _set_record_tables(self, n: int) -> int | None:
        """``SPA 1 0x16000300 n`` (Data Recorder Chan Number, volatile memory; PI's E-727
        manual: the points go in equal shares to the tables, whose number may be chosen); a
        controller that refuses it (an error code) keeps its tables."""
        try:
            self._send_checked(codec.encode(f"SPA 1 {rcodec.CHAN_NUMBER_PARAM} {int(n)}"))
        except ProtocolError as err:
            log.info("%s: the recorder keeps its tables (SPA 1 %s %d refused: %s)", self.name,
                     rcodec.CHAN_NUMBER_PARAM, n, err)
        return self._record_tables()

    def _configure_recorder(self, setup: RecorderSetup) -> RecorderSetup:
        tables: list[tuple[int, str, int]] = []
        where: dict[tuple[str, str], int] = {}
        for a in setup.axes:
            for sig in setup.signals:
                t = len(tables) + 1
                if sig == "y_nm":
                    tables.append((t, self._ids[a], rcodec.OPTION_ACTUAL_POSITION))
                elif sig == "u_V":
                    tables.append((t, self._ids[a], rcodec.OPTION_OPENLOOP_CONTROL))
                else:
                    tables.append((t, str(self._axes.index(a) + 1), rcodec.OPTION_PIEZO_VOLTAGE))
                where[(a, sig)] = t
        self._send_checked(*rcodec.encode_configure(tables, setup.divider))
        return RecorderSetup(setup.axes, setup.signals, setup.points, setup.divider, setup.clock_s,
                             {"tables": where})

    def _recorded_points(self, setup: RecorderSetup) -> int:
        tables = sorted(cast("dict[Any, int]", setup.extra["tables"]).values())
        counts = rcodec.parse_counts(self._query("DRL? " + " ".join(map(str, tables))), tables)
        return min(counts.values())

    def _read_recording(self, setup: RecorderSetup, cancel: Callable[[], bool]) -> Recording:
        """``DRR? <first> <n> <tables>`` in chunks of :meth:`_read_chunk` points (each read
        line by line: header, then one line a point); ``cancel()`` is asked between chunks."""
        where: dict = setup.extra["tables"]  # type: ignore[assignment]
        tables = sorted(where.values())
        chunk = self._read_chunk(len(tables))
        parts: list[np.ndarray] = []
        header: dict[str, str] = {}
        for first in range(0, setup.points, chunk):
            if cancel():
                raise RecordingCancelled(f"{self.name}: the read-back of the recording was cancelled")
            n = min(chunk, setup.points - first)
            header, data = self._read_part(tables, first + 1, n)
            if len(data) != n:
                raise ProtocolError(f"DRR? {first + 1} {n}: {len(data)} points came back")
            parts.append(data)
        data = np.concatenate(parts) if parts else np.zeros((0, len(tables)))
        return self._recording(setup, header, data)

    def _read_points(self, setup: RecorderSetup, first: int, n: int) -> Recording:
        """``DRR? <first + 1> <n> <tables>`` of points already recorded (the E-727 answers
        while it records; ``DRL?`` says how far it is)."""
        tables = sorted(cast("dict[Any, int]", setup.extra["tables"]).values())
        header, data = self._read_part(tables, first + 1, n)
        if len(data) != n:
            raise ProtocolError(f"DRR? {first + 1} {n}: {len(data)} points came back")
        rec = self._recording(setup, header, data)
        return Recording(rec.t_s + first * setup.period_s, rec.y_nm, rec.u_V, rec.period_s, rec.source, rec.v_V)

    def _read_chunk(self, tables: int) -> int:
        """Points per ``DRR?`` (a power of two): about :data:`RECORD_CHUNK_S` of the link's
        wire time (a TCP link has no baud rate: the most), so a cancel waits at most that."""
        if self._s_per_byte() == 0.0:
            return RECORD_CHUNK_MAX
        fit = RECORD_CHUNK_S / (12 * tables * self._s_per_byte())    # "-12.345678 " per table
        return int(min(RECORD_CHUNK_MAX, max(RECORD_CHUNK_MIN, 2 ** int(np.log2(max(fit, 1.0))))))

    def _s_per_byte(self) -> float:
        """Wire time of a byte [s] (8N1; 0 on a link without a baud rate)."""
        if self.transport.url.startswith("socket://") or self.transport.baudrate <= 0:
            return 0.0
        return 10.0 / self.transport.baudrate

    def _read_part(self, tables: list[int], first: int, points: int) -> tuple[dict[str, str], np.ndarray]:
        """One ``DRR?`` answer: its header and its rows (points, tables)."""
        self._settle()
        self.transport.write(rcodec.encode_read(tables, points, first))
        # the controller assembles a long buffered reply while it sends it: allow each line
        # more than a short reply's timeout (a loaded host or a slow link stretches it)
        wait = max(RECORD_LINE_TIMEOUT_S, self.transport.timeout_s)
        head: list[bytes] = []
        while True:
            line = self.transport.read_frame(rcodec.split_line, wait)
            if not line.lstrip().startswith(b"#"):
                raise ProtocolError("DRR? answer: a data line before # END_HEADER", data=line)
            head.append(line)
            if line.strip().upper().startswith(b"# END_HEADER") or rcodec.is_last_line(line):
                break
        data_lines: list[bytes] = []
        if not rcodec.is_last_line(head[-1]):   # the data lines in one read: through the last one
            block = self.transport.read_frame(rcodec.split_answer, wait + points * 12 * len(tables) * self._s_per_byte())
            data_lines = block[:-1].split(b"\n")
        header = rcodec.parse_header(head)
        data = rcodec.parse_data(header, data_lines, len(tables))
        self._check()
        return header, data

    def _recording(self, setup: RecorderSetup, header: dict[str, str], data: np.ndarray) -> Recording:
        """The rows read back as a :class:`Recording` (µm → nm; the sample time checked)."""
        where: dict = setup.extra["tables"]  # type: ignore[assignment]
        col = {t: k for k, t in enumerate(sorted(where.values()))}
        y = {a: data[:, col[t]] * 1000.0 for (a, sig), t in where.items() if sig == "y_nm"}  # µm -> nm
        u = {a: data[:, col[t]].copy() for (a, sig), t in where.items() if sig == "u_V"}
        v = {a: data[:, col[t]].copy() for (a, sig), t in where.items() if sig == "v_V"}
        period = float(header.get("SAMPLE_TIME", setup.period_s))
        if abs(period - setup.period_s) > 1e-9 * max(period, 1.0):
            raise ProtocolError(f"DRR? SAMPLE_TIME {period:g} s differs from the armed {setup.period_s:g} s")
        return Recording(time_axis(len(data), setup.period_s), y, u, setup.period_s, "gcs DRR?", v)
