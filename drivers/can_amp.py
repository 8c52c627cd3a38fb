"""The CAN amplifier driver (frames of ``afm_amplifier.dbc``, see :mod:`afmctl.drivers.codec_can`).

Streaming: one SETPOINT_XYZ frame per 3-axis setpoint, SEQ counting up by one (mod 256);
axes not given keep their last value. Nothing waits for the amplifier while streaming;
:meth:`flush` sends a HEARTBEAT asking for STATUS and checks that the amplifier's
LAST_SEQ is the last one sent (no frame lost) and that no ERROR frame came back.
At connect the driver asks for LIMITS and STATUS and continues the sequence after the
amplifier's LAST_SEQ. Received frames are handled by a :class:`can.Notifier`; bus errors
arrive through the listener's ``on_error`` and put the driver in ``DISCONNECTED``.

Buffered stream (device-timed output): :meth:`start_stream` sets the amplifier playing
samples at ``rate_Hz`` on its own clock, :meth:`queue` sends a block of samples (each
checked first: limits and at most ``max_step_V`` between consecutive samples, i.e. the
slew limit times the sample period), :meth:`buffer_status` reads the FIFO level and
underruns, :meth:`flush_stream` empties the FIFO at once (estop) and reads the output it
left, :meth:`drain_stream` lets it play out.
The safety checks (limits, step limit, lock, state) are the template's
(:class:`afmctl.drivers.base.Amplifier`); this module fills in its hooks.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import codec_can as codec
from .base import Amplifier, ConnectionState, VoltageLimits
from .errors import AmplifierTimeout, LimitError, ProtocolError, RecordingCancelled, RecordingOverwritten
from .recording import Recording, RecorderSetup, time_axis
from .stream_safety import check_block
from .transport_can import CanTransport

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BufferStatus:
    """The amplifier's stream FIFO as its STREAM_STATUS frame reports it."""

    level: int  #: samples queued
    capacity: int  #: FIFO size [samples]
    underruns: int  #: ticks with an empty FIFO since the start (mod 65536)
    played_seq: int  #: SEQ of the last sample played
    state: str  #: idle, armed, playing, draining, fault
    overflows: int  #: samples refused by a full FIFO (mod 256)


class CANAmplifier(Amplifier):
    """``CANAmplifier(transport, timeout_s=0.5, host_limits=None, max_step_V=None,
    reconnect_timeout_s=5.0)``; axes x, y, z; voltages in V."""

    name = "can"
    has_recorder = True
    #: REC_READ / REC_READ_FD answer with points already recorded while the recorder records
    reads_while_recording = True
    #: an arm for more points than REC_STATUS CAPACITY records into a ring (afm_amplifier.dbc)
    records_ring = True
    #: REC_DATA points asked for with one REC_READ (bounds the frames queued at once); on a
    #: CAN FD bus :data:`~afmctl.drivers.codec_can.FD_REC_POINTS` times as many with one
    #: REC_READ_FD, as many frames
    REC_READ_CHUNK = 128
    default_baudrate = None
    sync_on_close = False  # a vanished amplifier would hold close() for timeout_s
    transport: CanTransport

    def __init__(self, transport: CanTransport, *, timeout_s: float = 0.5, **options: Any) -> None:
        self.timeout_s = float(timeout_s)
        self._cond = threading.Condition()
        self._status: dict[str, float] | None = None
        self._status_count = 0
        self._limits_frame: dict[str, float] | None = None
        self._stream_status: dict[str, float] | None = None
        self._stream_status_count = 0
        self._stream_seq = 0
        self.stream_rate_Hz: float | None = None
        #: stream samples go as STREAM_XYZ_FD frames (CAN FD, several per frame)
        self.stream_fd = False
        self._errors: list[ProtocolError] = []
        self._bus_error: Exception | None = None
        self._seq = 0
        self._last_sent_seq: int | None = None
        self._counter = 0
        self.sent = 0
        self._ids = {name: codec.frame_id(name) for name in
                     (codec.SETPOINT, codec.HEARTBEAT, codec.STATUS, codec.ERROR, codec.LIMITS,
                      codec.STREAM_CTRL, codec.STREAM_SAMPLE, codec.STREAM_STATUS, codec.REC_CTRL, codec.REC_READ,
                      codec.REC_STATUS, codec.REC_DATA, codec.REC_DATA_V, codec.REC_READ_FD, codec.REC_DATA_FD)}
        self._rx_kinds = {self._ids[k]: k for k in (codec.STATUS, codec.ERROR, codec.LIMITS, codec.STREAM_STATUS,
                                                    codec.REC_STATUS, codec.REC_DATA, codec.REC_DATA_V,
                                                    codec.REC_DATA_FD)}
        self._rec_status: dict[str, float] | None = None
        self._rec_status_count = 0
        #: REC_DATA frames received: (index, axis index) -> (y_nm, u_V)
        self._rec_data: dict[tuple[int, int], tuple[float, float]] = {}
        #: REC_DATA_V frames received: (index, axis index) -> piezo voltage [V]
        self._rec_v: dict[tuple[int, int], float] = {}
        super().__init__(transport, **options)

    @classmethod
    def open(cls, port: str, *, baudrate: int | None = None, timeout_s: float = 0.5,
             write_timeout_s: float | None = None, fd: bool = False, **options: Any) -> "CANAmplifier":
        """Connect on ``INTERFACE:CHANNEL`` (python-can); ``baudrate`` is the bus bitrate;
        ``fd``: a CAN FD bus — the stream then sends STREAM_XYZ_FD frames of up to
        :data:`~afmctl.drivers.codec_can.FD_SAMPLES` samples each, and the recorder is read back
        in REC_DATA_FD frames of up to :data:`~afmctl.drivers.codec_can.FD_REC_POINTS` points
        ([amplifier.options] fd = true)."""
        bus = {"bitrate": baudrate} if baudrate else {}
        if fd:
            bus["fd"] = True
        amp = cls(CanTransport(port, **bus), timeout_s=timeout_s, **options)
        amp.stream_fd = bool(fd)
        return amp

    @property
    def axes(self) -> tuple[str, ...]:
        return ("x", "y", "z")

    # -- receive side (notifier thread) --
    def _on_message(self, msg: Any) -> None:
        fid = msg.arbitration_id
        kind = self._rx_kinds.get(fid)
        if kind is None:
            return
        try:
            if kind == codec.REC_DATA_FD:
                self._on_rec_block(codec.decode_rec_block(msg.data))
                return
            sig = codec.decode(kind, msg.data)
        except ProtocolError as err:
            with self._cond:
                self._errors.append(err)
            return
        with self._cond:
            if kind == codec.STATUS:
                self._status = sig
                self._status_count += 1
            elif kind == codec.LIMITS:
                self._limits_frame = sig
            elif kind == codec.STREAM_STATUS:
                self._stream_status = sig
                self._stream_status_count += 1
            elif kind == codec.REC_STATUS:
                self._rec_status = sig
                self._rec_status_count += 1
            elif kind == codec.REC_DATA:
                self._rec_data[(int(sig["INDEX"]), int(sig["AXIS"]))] = (float(sig["Y_NM"]), float(sig["U_V"]))
            elif kind == codec.REC_DATA_V:
                self._rec_v[(int(sig["INDEX"]), int(sig["AXIS"]))] = float(sig["V_V"])
            else:
                self._errors.append(codec.error_from(sig, bytes(msg.data)))
            self._cond.notify_all()

    def _on_rec_block(self, block: tuple[int, int, list[tuple[float, float, float]]]) -> None:
        """A REC_DATA_FD frame's points, kept as REC_DATA and REC_DATA_V would keep them."""
        first, axis, points = block
        with self._cond:
            for k, (y, u, v) in enumerate(points):
                self._rec_data[(first + k, axis)] = (y, u)
                self._rec_v[(first + k, axis)] = v
            self._cond.notify_all()

    def _on_error(self, exc: Exception) -> None:
        self._bus_error = exc
        if self._state is ConnectionState.CONNECTED:
            self._state = ConnectionState.DISCONNECTED
            log.warning("can: bus error on %s: %s", self.transport.url, exc)

    # -- helpers --
    def _raise_pending(self) -> None:
        """Raise the first ERROR received (a recording overwritten before any other: the
        caller can play it again), forgetting the others."""
        with self._cond:
            if self._errors:
                err = next((e for e in self._errors if isinstance(e, RecordingOverwritten)), self._errors[0])
                self._errors.clear()
                raise err

    def _heartbeat(self, req_state: int = 0, req_status: bool = False, req_info: bool = False) -> None:
        self._counter = (self._counter + 1) & 0xFF
        self.transport.send(self._ids[codec.HEARTBEAT],
                            codec.encode_heartbeat(self._counter, req_state, req_status, req_info), self.timeout_s)

    def _request_status(self, req_info: bool = False, req_state: int = 0) -> dict[str, float]:
        def answered(before: int) -> bool:
            return self._status_count != before and not (req_info and self._limits_frame is None)

        self._send_and_await(lambda: self._heartbeat(req_state=req_state, req_status=True, req_info=req_info),
                             lambda: self._status_count, answered, "STATUS")
        with self._cond:
            assert self._status is not None
            return dict(self._status)

    def _send_and_await(self, send, count, answered, frame: str) -> None:
        """``send()``, then wait (up to ``timeout_s``) until ``answered(count before sending)``:
        a status frame newer than the request arrived (counts change under ``_cond``)."""
        with self._cond:
            before = count()
        send()
        deadline = time.monotonic() + self.timeout_s
        with self._cond:
            while not answered(before):
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AmplifierTimeout(f"no {frame} from the CAN amplifier on {self.transport.url} "
                                           f"within {self.timeout_s:g} s")
                self._cond.wait(left)

    # -- hooks of the template --
    def _open_link(self) -> None:
        with self._cond:
            self._limits_frame = None
            self._errors.clear()
        self._bus_error = None
        if not self.transport.is_open:
            self.transport.open(self._on_message, self._on_error)

    def _handshake(self) -> tuple[dict[str, VoltageLimits], dict[str, object]]:
        status = self._request_status(req_info=True)
        lim = self._limits_frame
        assert lim is not None
        device = {a: VoltageLimits(float(lim["MIN_V"]), float(lim[f"{a.upper()}_MAX_V"])) for a in self.axes}
        self._seq = (int(status["LAST_SEQ"]) + 1) & 0xFF
        self._last_sent_seq = None
        with self._cond:
            self._errors.clear()
        return device, {}

    def _read_voltages(self) -> dict[str, float]:
        if self._status is None:
            self._request_status()
        assert self._status is not None
        return {a: float(self._status[f"{a.upper()}_V"]) for a in self.axes}

    def _write_setpoint(self, values: dict[str, float]) -> dict[str, float]:
        full = {**self._last, **values}
        lim = self._limits
        # One frame carries all three axes: an axis not asked for is re-sent at its
        # held value, which must itself be inside the limits (the output at connect may
        # not be, e.g. 0 V under host limits of 10-50 V) — never clamp it silently.
        for a in self.axes:
            if a not in values and not lim[a].min_V <= full[a] <= lim[a].max_V:
                raise LimitError(
                    f"axis {a} holds {full[a]:g} V, outside the limits [{lim[a].min_V:g}, "
                    f"{lim[a].max_V:g}] V; a CAN setpoint carries every axis, so give {a} a value too")
        data = codec.encode_setpoint([full[a] for a in self.axes], self._seq,
                                     [lim[a].min_V for a in self.axes], [lim[a].max_V for a in self.axes])
        self.transport.send(self._ids[codec.SETPOINT], data, self.timeout_s)
        self._last_sent_seq = self._seq
        self._seq = (self._seq + 1) & 0xFF
        self.sent += 1
        return full

    def _sync(self) -> None:
        status = self._request_status()
        self._raise_pending()
        if self._last_sent_seq is not None and int(status["LAST_SEQ"]) != self._last_sent_seq:
            raise ProtocolError(f"amplifier applied SEQ {int(status['LAST_SEQ'])}, last sent "
                                f"{self._last_sent_seq}: setpoints lost", code="SEQ")

    def _set_enabled(self, enabled: bool) -> None:
        self._request_status(req_state=1 if enabled else 2)

    def _info_extra(self) -> dict[str, object]:
        st = self._status or {}
        return {"amplifier_state": codec.STATES.get(int(st.get("STATE", 2)), "unknown"),
                "dbc": codec.DBC_RESOURCE}

    # -- buffered stream --
    def _stream_command(self, cmd: int, rate_Hz: float = 0.0, prefill: int = 1) -> BufferStatus:
        """Send STREAM_CTRL and wait for the STREAM_STATUS that answers it."""
        data = codec.encode_stream_ctrl(cmd, rate_Hz, prefill)
        self._send_and_await(lambda: self.transport.send(self._ids[codec.STREAM_CTRL], data, self.timeout_s),
                             lambda: self._stream_status_count,
                             lambda before: self._stream_status_count != before, "STREAM_STATUS")
        with self._cond:
            assert self._stream_status is not None
            return _buffer_status(self._stream_status)

    def start_stream(self, rate_Hz: float, prefill: int = 1) -> BufferStatus:
        """Empty the amplifier's FIFO and arm it to play queued samples at ``rate_Hz`` [Hz]
        (a whole number) on its own clock; the clock starts once ``prefill`` samples are
        queued (or at :meth:`drain_stream`)."""
        with self._lock:
            self._guard()
            status = self._io(self._stream_command, codec.CMD_START, rate_Hz, prefill)
            self._stream_seq = 0
            self.stream_rate_Hz = float(rate_Hz)
            return status

    def queue(self, block_V: Sequence[Sequence[float]]) -> int:
        """Queue samples (rows of x, y, z [V]) for the stream; every sample, quantised to the
        frame's 2.5 mV step, is checked before the first is sent (limits, ``max_step_V`` from
        the previous sample). Returns the number queued."""
        with self._lock:
            self._guard()
            if self.stream_rate_Hz is None:
                raise ProtocolError("queue() before start_stream(): the amplifier is not streaming")
            # finite, inside the limits; then the step between the values as quantised (as sent)
            rows = check_block(block_V, self.axes, self._limits, self._last, self.max_step_V, codec.quantize_inside)
            self._io(self._send_samples, rows)
            return len(rows)

    def _send_samples(self, rows: list[tuple[float, ...]]) -> None:
        lim = self._limits
        lows, highs = [lim[a].min_V for a in self.axes], [lim[a].max_V for a in self.axes]
        if self.stream_fd:
            self._send_sample_blocks(rows, lows, highs)
            return
        fid = self._ids[codec.STREAM_SAMPLE]
        for row in rows:
            self.transport.send(fid, codec.encode_stream_sample(row, self._stream_seq, lows, highs), self.timeout_s)
            self._stream_seq = (self._stream_seq + 1) & 0xFFFF
            self._last.update(zip(self.axes, row))
            self.sent += 1

    def _send_sample_blocks(self, rows: list[tuple[float, ...]], lows: list[float], highs: list[float]) -> None:
        """The samples as STREAM_XYZ_FD frames of up to FD_SAMPLES each (CAN FD)."""
        fid = codec.frame_id(codec.STREAM_SAMPLE_FD)
        for k in range(0, len(rows), codec.FD_SAMPLES):
            chunk = rows[k:k + codec.FD_SAMPLES]
            self.transport.send(fid, codec.encode_stream_block(chunk, self._stream_seq, lows, highs), self.timeout_s)
            self._stream_seq = (self._stream_seq + len(chunk)) & 0xFFFF
            self._last.update(zip(self.axes, chunk[-1]))
            self.sent += len(chunk)

    def buffer_status(self) -> BufferStatus:
        """Ask the amplifier for its FIFO level and underrun count."""
        with self._lock:
            self._guard()
            return self._io(self._stream_command, codec.CMD_STATUS)

    def latest_buffer_status(self) -> BufferStatus | None:
        """The last STREAM_STATUS received (sent by a playing amplifier every 10 ms), no I/O."""
        with self._cond:
            return None if self._stream_status is None else _buffer_status(self._stream_status)

    def flush_stream(self) -> dict[str, float]:
        """Empty the FIFO and stop at once (estop); returns the output the amplifier holds
        [V], which becomes the reference for the next step or ramp."""
        with self._lock:
            # no _guard(): an estop must reach the amplifier even with an error pending
            self._io(self._stream_command, codec.CMD_FLUSH)
            self.stream_rate_Hz = None
            status = self._io(self._request_status)
            held = {a: float(status[f"{a.upper()}_V"]) for a in self.axes}
            self._last.update(held)
            return held

    def drain_stream(self) -> BufferStatus:
        """Let the amplifier play what is queued, then stop."""
        with self._lock:
            self._guard()
            status = self._io(self._stream_command, codec.CMD_DRAIN)
            self.stream_rate_Hz = None
            return status


    # ---- data recorder (REC_* frames; the Amplifier template's configure_recorder / read_recording) ----
    def _rec_command(self, cmd: int, axes_mask: int = 0, signals: int = 0, points: int = 0,
                     divider: int = 0) -> dict[str, float]:
        """Send REC_CTRL and wait for the REC_STATUS that answers it (an ERROR first is raised)."""
        data = codec.encode_rec_ctrl(cmd, axes_mask, signals, points, divider)
        self._send_and_await(lambda: self.transport.send(self._ids[codec.REC_CTRL], data, self.timeout_s),
                             lambda: self._rec_status_count,
                             lambda before: self._rec_status_count != before, "REC_STATUS")
        self._raise_pending()
        with self._cond:
            assert self._rec_status is not None
            return dict(self._rec_status)

    def _recorder_clock_s(self) -> float:
        if not self.stream_rate_Hz:
            raise LimitError("can: the recorder counts the stream's ticks: start_stream(rate_Hz) first, then "
                             "configure_recorder(), then queue the samples")
        return 1.0 / self.stream_rate_Hz

    def _recorder_capacity(self, axes: tuple[str, ...], signals: tuple[str, ...]) -> int:
        return min(int(self._rec_command(codec.REC_CMD_STATUS)["CAPACITY"]), 0xFFFF)

    def _recorder_max_points(self, axes: tuple[str, ...], signals: tuple[str, ...]) -> int:
        return 0xFFFF                    # REC_CTRL POINTS; past CAPACITY a ring read while it records

    def _configure_recorder(self, setup: RecorderSetup) -> RecorderSetup:
        if setup.divider > 0xFFFF:
            raise LimitError(f"recorder divider {setup.divider}: the CAN recorder takes 1..65535 ticks")
        axes_mask = sum(1 << self.axes.index(a) for a in setup.axes)
        signals = sum(codec.REC_SIGNAL_BITS[s] for s in setup.signals)
        status = self._rec_command(codec.REC_CMD_ARM, axes_mask, signals, setup.points, setup.divider)
        if codec.REC_STATES.get(int(status["REC_STATE"])) not in ("armed", "recording"):
            raise ProtocolError(f"can: the recorder is {codec.REC_STATES.get(int(status['REC_STATE']))} after arming")
        return setup

    def _recorded_points(self, setup: RecorderSetup) -> int:
        return int(self._rec_command(codec.REC_CMD_STATUS)["COUNT"])

    def _read_recording(self, setup: RecorderSetup, cancel: Callable[[], bool]) -> Recording:
        """The whole recording (:meth:`_read_points`); ``cancel()`` asked between two chunks."""
        return self._read_points(setup, 0, setup.points, cancel)

    def _read_points(self, setup: RecorderSetup, first: int, n: int,
                     cancel: Callable[[], bool] = lambda: False) -> Recording:
        """Points ``first`` .. ``first + n - 1`` (recorded already, also while the recorder
        records), in chunks of :meth:`_read_chunk_points`, each awaited before the next is
        asked for; ``cancel()`` true between two raises :class:`RecordingCancelled`."""
        chunk = self._read_chunk_points()
        parts = []
        for k in range(first, first + n, chunk):
            if cancel():
                raise RecordingCancelled(f"{self.name}: the read-back of the recording was cancelled")
            parts.append(self._read_chunk(setup, k, min(chunk, first + n - k)))
        return self._as_recording(setup, first, *(np.concatenate([p[j] for p in parts]) for j in range(3)))

    def _read_chunk_points(self) -> int:
        return self.REC_READ_CHUNK * (codec.FD_REC_POINTS if self.stream_fd else 1)

    def _read_chunk(self, setup: RecorderSetup, first: int, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One REC_READ (REC_READ_FD on a CAN FD bus) of ``count`` points from ``first``;
        its frames are awaited before it returns: (y [nm], u [V], v [V]) of shape (count, axes)."""
        idx = [self.axes.index(a) for a in setup.axes]
        need_v = "v_V" in setup.signals and not self.stream_fd
        want = count * len(idx)
        with self._cond:
            self._rec_data.clear()
            self._rec_v.clear()
        name, data = ((codec.REC_READ_FD, codec.encode_rec_read_fd(first, count)) if self.stream_fd
                      else (codec.REC_READ, codec.encode_rec_read(first, count)))
        keys = [(k, i) for k in range(first, first + count) for i in idx]

        def answered(_: int) -> bool:    # counted first: the keys are looked at once enough came
            if self._errors:
                return True
            if len(self._rec_data) < want or (need_v and len(self._rec_v) < want):
                return False
            return all(k in self._rec_data and (not need_v or k in self._rec_v) for k in keys)
        self._send_and_await(lambda: self.transport.send(self._ids[name], data, self.timeout_s), lambda: 0,
                             answered, codec.REC_DATA_FD if self.stream_fd else codec.REC_DATA)
        self._raise_pending()
        y, u, v = (np.empty((count, len(idx))) for _ in range(3))
        with self._cond:
            for k in range(count):
                for j, i in enumerate(idx):
                    y[k, j], u[k, j] = self._rec_data[(first + k, i)]
                    v[k, j] = self._rec_v.get((first + k, i), np.nan)
        return y, u, v

    def _as_recording(self, setup: RecorderSetup, first: int, y: np.ndarray, u: np.ndarray,
                      v: np.ndarray) -> Recording:
        t = time_axis(first + len(y), setup.period_s)[first:]
        ys = {a: y[:, j].copy() for j, a in enumerate(setup.axes)} if "y_nm" in setup.signals else {}
        us = {a: u[:, j].copy() for j, a in enumerate(setup.axes)} if "u_V" in setup.signals else {}
        vs = {a: v[:, j].copy() for j, a in enumerate(setup.axes)} if "v_V" in setup.signals else {}
        return Recording(t, ys, us, setup.period_s, "can REC_DATA_FD" if self.stream_fd else "can REC_DATA", vs)


def _buffer_status(sig: dict[str, float]) -> BufferStatus:
    return BufferStatus(level=int(sig["LEVEL"]), capacity=1 << int(sig["CAPACITY_LOG2"]),
                        underruns=int(sig["UNDERRUNS"]), played_seq=int(sig["PLAYED_SEQ"]),
                        state=codec.STREAM_STATES.get(int(sig["STREAM_STATE"]), "unknown"),
                        overflows=int(sig["OVERFLOWS"]))
