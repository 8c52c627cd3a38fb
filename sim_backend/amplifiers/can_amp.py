"""Simulated CAN amplifier answering the frames of ``drivers/afm_amplifier.dbc``.

sim_backend must not import :mod:`afmctl.drivers` code, so the DBC is read as package
data with :mod:`importlib.resources` and loaded with cantools; frame ids and signals are
looked up by message name (``dbc_path`` overrides the file).

Behaviour: outputs are enabled at power-up. A SETPOINT_XYZ inside the range is applied;
outside it answers ERROR code 1 (nothing applied); while disabled ERROR code 3. SEQ must
count up by one (mod 256) from the last frame: otherwise ERROR code 2 with DETAIL = the
expected SEQ (the setpoint is still applied — the newest one is the best). FLAGS bit0 or
a HEARTBEAT with REQ_STATUS asks for a STATUS frame; REQ_INFO for LIMITS. LAST_SEQ
starts at 255, so a host continues at 0.

Buffered stream (STREAM_CTRL, STREAM_XYZ, STREAM_STATUS): samples fill a FIFO of
``2**fifo_log2`` entries that a player thread plays on the amplifier's clock, sample k at
exactly t0 + k / rate (see :mod:`.can_stream`); the scanner sink receives those computed
times, so the tip's timing does not depend on when the host sent the frames. A sample
outside the range or while disabled stops the stream (ERROR 1 or 3, FIFO emptied, output
holds); a full FIFO refuses a sample (ERROR 5). STREAM_STATUS answers every STREAM_CTRL
and is sent every ``STATUS_PERIOD_S`` of play. While the stream is armed (primed, the
output held) the scanner's simulation is kept up to the present. On a CAN FD bus the host may send
STREAM_XYZ_FD frames instead: up to 10 samples each (SEQ, SEQ+1, ...), played as if they
came one STREAM_XYZ each.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import can

from .base import Sink, elapsed_clock
from .can_recorder import CAPACITY as REC_CAPACITY, RecState, TickRecorder
from .can_stream import StreamPlayer, StreamState

log = logging.getLogger(__name__)

#: the DBC's messages this amplifier receives and sends
_MESSAGES = ("SETPOINT_XYZ", "HEARTBEAT", "STATUS", "ERROR", "LIMITS", "STREAM_CTRL", "STREAM_XYZ",
             "STREAM_XYZ_FD", "STREAM_STATUS", "REC_CTRL", "REC_READ", "REC_STATUS", "REC_DATA", "REC_DATA_V",
             "REC_READ_FD", "REC_DATA_FD")
#: how often a playing stream reports its FIFO [s of the amplifier clock]
STATUS_PERIOD_S = 0.01
#: stream samples wait for the sink until the oldest is this old [s] (see _run_stream)
SINK_BATCH_S = 0.02


def read_dbc_text() -> str:
    """Text of ``afm_amplifier.dbc``, the package data of ``afmctl.drivers``."""
    return resources.files("afmctl.drivers").joinpath("afm_amplifier.dbc").read_text(encoding="utf-8")


def load_database(dbc_path: str | Path | None = None):
    """The cantools database of the amplifier frames (``dbc_path`` or the shipped DBC)."""
    import cantools
    if dbc_path is not None:
        return cantools.database.load_file(str(dbc_path))
    return cantools.database.load_string(read_dbc_text(), database_format="dbc")


class SimCANAmplifier:
    """``SimCANAmplifier(channel="afm0", sink=None, interface="virtual", now=None,
    min_V=0.0, max_V=150.0, dbc_path=None, record_seq=False)``.

    Use as a context manager or :meth:`start`/:meth:`stop`. Counters: ``received``
    (setpoint frames), ``gaps`` (SEQ discontinuities), ``rejected``; ``seq_log`` holds
    every SEQ when ``record_seq``. Fault hooks: :meth:`silence`/:meth:`resume`,
    :meth:`disappear`/:meth:`reappear`, :meth:`inject_error`.
    """

    protocol = "can"
    axes = ("x", "y", "z")

    def __init__(self, channel: str = "afm0", sink: Sink | None = None, *, interface: str = "virtual",
                 now: Callable[[], float] | None = None, min_V: float = 0.0, max_V: float = 150.0,
                 dbc_path: str | Path | None = None, record_seq: bool = False, fifo_log2: int = 12,
                 **bus_options: Any) -> None:
        self.channel = channel
        self.interface = interface
        self.sink = sink
        self.now = now or elapsed_clock()
        self.min_V = float(min_V)
        self.max_V = {a: float(max_V) for a in self.axes}
        self.db = load_database(dbc_path)
        self._msg = {name: self.db.get_message_by_name(name) for name in _MESSAGES}
        #: frame id -> message name, for the frames this amplifier receives
        self._rx = {self._msg[n].frame_id: n for n in ("SETPOINT_XYZ", "HEARTBEAT", "STREAM_CTRL", "STREAM_XYZ",
                                                       "STREAM_XYZ_FD", "REC_CTRL", "REC_READ",
                                                       "REC_READ_FD")}
        self._bus_options = bus_options
        #: sample slots of one STREAM_XYZ_FD frame (from the DBC: its X<k>_V signals)
        self._fd_samples = sum(1 for sg in self._msg["STREAM_XYZ_FD"].signals if sg.name[0] == "X")
        #: recorded points one REC_DATA_FD frame carries (from the DBC: its Y<k>_NM signals)
        self._fd_rec_points = sum(1 for sg in self._msg["REC_DATA_FD"].signals if sg.name[0] == "Y")
        #: the ranges a recorded point's position [nm] and voltages [V] are sent in (the DBC's)
        y_sig = self._msg["REC_DATA"].get_signal_by_name("Y_NM")
        v_sig = self._msg["REC_DATA_V"].get_signal_by_name("V_V")
        self._rec_y_nm = (float(y_sig.minimum), float(y_sig.maximum))
        self._rec_v_V = (float(v_sig.minimum), float(v_sig.maximum))
        self.outputs = {a: 0.0 for a in self.axes}
        self.enabled = True
        self.last_seq = 255
        self.last_error = 0
        self.received = 0
        self.gaps = 0
        self.rejected = 0
        self.record_seq = record_seq
        self.seq_log: list[int] = []
        #: every stream sample received (x, y, z) [V], when ``record_seq``
        self.stream_log: list[tuple[float, float, float]] = []
        self.requested_min_V = math.inf
        self.requested_max_V = -math.inf
        #: per axis: (smallest, largest) voltage ever requested by a host [V]
        self.requested_V: dict[str, tuple[float, float]] = {}
        self._silent = False
        self._inject: int | None = None
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        #: guards the stream player (notifier thread pushes, player thread plays)
        self._stream_lock = threading.Condition()
        self.stream = StreamPlayer(self._play, capacity_log2=fifo_log2)
        #: the data recorder (REC_* frames; :mod:`.can_recorder`), guarded by the stream lock
        self.recorder = TickRecorder(self._sensor_capture)
        self._played_t: list[float] = []
        self._played_V: list[tuple[float, float, float]] = []
        self._player: threading.Thread | None = None
        self._running = False
        self._last_stream_status_s = 0.0

    # -- life --
    def start(self) -> "SimCANAmplifier":
        import can

        sim = self

        class _Listener(can.Listener):
            def on_message_received(self, msg: can.Message) -> None:
                sim.handle(msg.arbitration_id, bytes(msg.data))

            def on_error(self, exc: Exception) -> None:
                log.warning("simulated CAN amplifier: bus error %s", exc)
                time.sleep(0.05)

        with self._lock:
            if self._bus is None:
                self._bus = can.Bus(interface=self.interface, channel=self.channel, **self._bus_options)
                self._notifier = can.Notifier(self._bus, [_Listener()], timeout=0.05)
                self._running = True
                self._player = threading.Thread(target=self._player_loop, name="sim-can-stream", daemon=True)
                self._player.start()
        return self

    def stop(self) -> None:
        with self._lock:
            notifier, self._notifier = self._notifier, None
            bus, self._bus = self._bus, None
            player, self._player = self._player, None
        with self._stream_lock:
            self._running = False
            self._stream_lock.notify_all()
        if player is not None:
            player.join(timeout=1.0)
        if notifier is not None:
            notifier.stop(timeout=1.0)
        if bus is not None:
            bus.shutdown()

    def __enter__(self) -> "SimCANAmplifier":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    disappear = stop

    def reappear(self) -> None:
        self.start()

    def silence(self) -> None:
        self._silent = True

    def resume(self) -> None:
        self._silent = False

    def inject_error(self, code: int | None = None) -> None:
        """The next setpoint is refused with an ERROR frame of ``code`` (default 4, hardware fault)."""
        self._inject = 4 if code is None else int(code)

    # -- protocol --
    def _send(self, name: str, signals: dict) -> None:
        import can
        bus = self._bus
        if bus is None:
            return
        msg = self._msg[name]
        with self._send_lock:
            data = msg.encode(signals)
            bus.send(can.Message(arbitration_id=msg.frame_id, data=data, is_extended_id=False, is_fd=len(data) > 8))

    def _error(self, code: int, detail: int, seq: int) -> None:
        self.last_error = code
        self._send("ERROR", {"CODE": code, "DETAIL": detail & 0xFFFF, "SEQ": seq & 0xFF})

    def send_status(self) -> None:
        self._send("STATUS", {"X_V": self.outputs["x"], "Y_V": self.outputs["y"], "Z_V": self.outputs["z"],
                               "LAST_SEQ": self.last_seq, "STATE": 1 if self.enabled else 0,
                               "ERROR_CODE": min(self.last_error, 15)})

    def send_limits(self) -> None:
        self._send("LIMITS", {"MIN_V": self.min_V, "X_MAX_V": self.max_V["x"], "Y_MAX_V": self.max_V["y"],
                               "Z_MAX_V": self.max_V["z"]})

    def handle(self, fid: int, data: bytes) -> None:
        """One received frame (called from the notifier thread)."""
        if self._silent:
            return
        name = self._rx.get(fid)
        if name is None or len(data) != self._msg[name].length:
            return
        sig = self._msg[name].decode(data, decode_choices=False)
        if name == "SETPOINT_XYZ":
            self._setpoint(sig)
        elif name == "STREAM_XYZ":
            self._stream_sample(sig)
        elif name == "STREAM_XYZ_FD":     # CAN FD: COUNT samples, SEQ, SEQ+1, ...
            seq, n = int(sig["SEQ"]), int(sig["COUNT"])
            if not 1 <= n <= self._fd_samples:
                self.rejected += 1
                return
            for k in range(n):
                self._stream_sample({"SEQ": (seq + k) & 0xFFFF, "X_V": sig[f"X{k}_V"], "Y_V": sig[f"Y{k}_V"],
                                     "Z_V": sig[f"Z{k}_V"]})
        elif name == "STREAM_CTRL":
            self._stream_ctrl(sig)
        elif name == "REC_CTRL":
            self._rec_ctrl(sig)
        elif name == "REC_READ":
            self._rec_read(sig)
        elif name == "REC_READ_FD":
            self._rec_read(sig, fd=True)
        else:
            if sig["REQ_STATE"] == 1:
                self.enabled = True
            elif sig["REQ_STATE"] == 2:
                self.enabled = False
                with self._stream_lock:  # disabled outputs stop a stream where it stands
                    self._run_stream(self.now(), flush=True)
                    if self.stream.state is not StreamState.IDLE:
                        self.stream.flush()
            if sig["REQ_INFO"]:
                self.send_limits()
            if sig["REQ_STATUS"]:
                self.send_status()

    def _setpoint(self, sig: dict) -> None:
        seq = int(sig["SEQ"])
        self.received += 1
        if self.record_seq:
            self.seq_log.append(seq)
        expected = (self.last_seq + 1) & 0xFF
        if seq != expected:
            self.gaps += 1
            self._error(2, expected, seq)
        self.last_seq = seq
        values = {"x": float(sig["X_V"]), "y": float(sig["Y_V"]), "z": float(sig["Z_V"])}
        for a, v in values.items():
            self.requested_min_V = min(self.requested_min_V, v)
            self.requested_max_V = max(self.requested_max_V, v)
            lo, hi = self.requested_V.get(a, (v, v))
            self.requested_V[a] = (min(lo, v), max(hi, v))
        if self._inject is not None:
            code, self._inject = self._inject, None
            self.rejected += 1
            self._error(code, 0, seq)
        elif not self.enabled:
            self.rejected += 1
            self._error(3, 0, seq)
        elif any(not self.min_V <= v <= self.max_V[a] for a, v in values.items()):
            self.rejected += 1
            self._error(1, 0, seq)
        else:
            changed = values != self.outputs
            self.outputs = values
            if changed and self.sink is not None:
                with self._stream_lock:      # what the stream played reaches the sink first
                    self._run_stream(self.now(), flush=True)
                self.sink.apply(dict(values), self.now())
        if int(sig["FLAGS"]) & 1:
            self.send_status()

    # -- buffered stream --
    def _play(self, values: tuple[float, float, float], t_s: float) -> None:
        """One sample played by the stream at its tick time ``t_s`` (under the stream lock);
        handed to the sink with the others of the same clock update by :meth:`_run_stream`."""
        self.outputs = dict(zip(self.axes, values))
        self.recorder.played(values, t_s, self.stream.rate_Hz)
        self._played_t.append(t_s)
        self._played_V.append(values)

    def _run_stream(self, now_s: float, flush: bool = False) -> None:
        """Play every tick due by ``now_s`` and hand the samples to the sink in blocks
        (``sink.play(t_s, rows_V)`` where the sink has it — the simulated scanner simulates a
        block in one call, which 10 kHz needs — else one ``apply`` per sample): the samples
        wait until the oldest is :data:`SINK_BATCH_S` old, the stream stops, or ``flush``
        (the sink must be current: its sensor read, a setpoint applied). A block per frame
        received costs the simulation more than real time on a busy host."""
        self.stream.run_until(now_s)
        if not self._played_t:
            return
        if not flush and self.stream.state is not StreamState.IDLE and now_s - self._played_t[0] < SINK_BATCH_S:
            return
        t, rows = self._played_t, self._played_V
        self._played_t, self._played_V = [], []
        if self.sink is None:
            return
        play = getattr(self.sink, "play", None)
        if play is not None:
            play(t, rows)
        else:
            for t_k, row in zip(t, rows):
                self.sink.apply(dict(zip(self.axes, row)), t_k)

    def _keep_sink_current(self, now_s: float) -> None:
        """While the stream is armed (the host primes the FIFO, the output holds), time
        passes for the scanner too: advance the sink's simulation to ``now_s``, so that the
        clock's first tick does not first simulate the whole wait in one call (under the
        stream lock, which then sent no STREAM_STATUS for ~75 ms after a 2 s settle hold and
        the host refilled too late)."""
        advance = getattr(self.sink, "advance", None)
        if advance is not None:
            advance(now_s)

    # -- data recorder --
    def _sensor_capture(self, t0_s: float, period_s: float, n: int):
        capture = getattr(self.sink, "capture_sensor", None)
        return capture(t0_s, period_s, n) if capture is not None else None

    def _rec_sync(self) -> None:
        """Play what is due, bring the sink's simulation (its sensor) and the recorder to now
        (under the stream lock)."""
        now = self.now()
        self._run_stream(now, flush=True)
        advance = getattr(self.sink, "advance", None)
        if advance is not None and getattr(self.sink, "capture_sensor", None) is not None:
            advance(now)
        self.recorder.sync(now)

    def send_rec_status(self) -> None:
        r = self.recorder
        self._send("REC_STATUS", {"REC_STATE": int(r.state), "AXES": r.axes_mask, "SIGNALS": r.signals,
                                  "COUNT": r.count(), "CAPACITY": REC_CAPACITY, "DIVIDER": r.divider & 0xFFFF})

    def _rec_ctrl(self, sig: dict) -> None:
        cmd = int(sig["CMD"])
        with self._stream_lock:
            self._rec_sync()
            if cmd == 1:
                detail = self.recorder.arm(int(sig["AXES"]), int(sig["SIGNALS"]), int(sig["POINTS"]),
                                           int(sig["DIVIDER"]))
                if detail:
                    self._error(6, detail, 0)
            elif cmd == 2:
                self.recorder.stop()
            self.send_rec_status()

    def _rec_read(self, sig: dict, fd: bool = False) -> None:
        """REC_READ (``fd``: REC_READ_FD): the points asked for, as REC_DATA (+ REC_DATA_V)
        frames, one per point and axis, or as REC_DATA_FD frames of up to
        :attr:`_fd_rec_points` points of one axis."""
        first, count = int(sig["FIRST"]), int(sig["COUNT"])
        with self._stream_lock:
            self._rec_sync()
            r = self.recorder
            refused = r.held(first, count)
            if refused:
                self._error(6, refused, 0)
                return
            axes = [i for i in range(3) if r.axes_mask >> i & 1]
            points = {i: [self._rec_point(k, i) for k in range(first, first + count)] for i in axes}
        if fd:
            self._send_rec_blocks(first, points)
            return
        monitor = bool(r.signals & 4)
        for j in range(count):
            for i in axes:
                y, u, v = points[i][j]
                self._send("REC_DATA", {"INDEX": first + j, "AXIS": i, "Y_NM": y, "U_V": u})
                if monitor:
                    self._send("REC_DATA_V", {"INDEX": first + j, "AXIS": i, "V_V": v})

    def _rec_point(self, k: int, axis: int) -> tuple[float, float, float]:
        """Recorded point ``k`` of axis index ``axis`` inside its frame signals' ranges (DBC)."""
        y, u, v = self.recorder.point(k, axis)
        (y_lo, y_hi), (v_lo, v_hi) = self._rec_y_nm, self._rec_v_V
        return min(max(y, y_lo), y_hi), u, min(max(v, v_lo), v_hi)

    def _send_rec_blocks(self, first: int, points: dict[int, list[tuple[float, float, float]]]) -> None:
        """REC_DATA_FD frames: blocks of up to :attr:`_fd_rec_points` points, in index then axis order."""
        per = self._fd_rec_points
        count = len(next(iter(points.values())))
        for start in range(0, count, per):
            for i, pts in points.items():
                block = pts[start:start + per]
                sig: dict[str, float] = {"INDEX": (first + start) & 0xFFFF, "AXIS": i, "COUNT": len(block)}
                for k in range(per):
                    sig[f"Y{k}_NM"], sig[f"U{k}_V"], sig[f"V{k}_V"] = block[k] if k < len(block) else (0.0, 0.0, 0.0)
                self._send("REC_DATA_FD", sig)

    def send_stream_status(self) -> None:
        st = self.stream.status()
        self._send("STREAM_STATUS", {"LEVEL": min(st.level, 0xFFFF), "UNDERRUNS": st.underruns & 0xFFFF,
                                     "PLAYED_SEQ": st.played_seq, "STREAM_STATE": int(st.state),
                                     "CAPACITY_LOG2": st.capacity_log2, "OVERFLOWS": st.overflows & 0xFF})

    def _stream_ctrl(self, sig: dict) -> None:
        cmd = int(sig["CMD"])
        with self._stream_lock:
            self._run_stream(self.now(), flush=True)
            if cmd == 1:
                rate = float(sig["RATE_HZ"])
                if rate < 1:
                    self._error(1, 0, 0)
                else:
                    self.stream.start(rate, int(sig["PREFILL"]))
            elif cmd == 2:
                self.stream.flush()
            elif cmd == 3:
                self.stream.drain(self.now())
            self.send_stream_status()
            self._stream_lock.notify_all()

    def _stream_sample(self, sig: dict) -> None:
        seq = int(sig["SEQ"])
        values = (float(sig["X_V"]), float(sig["Y_V"]), float(sig["Z_V"]))
        with self._stream_lock:
            now = self.now()
            self._run_stream(now)
            self.received += 1
            if self.record_seq:
                self.seq_log.append(seq)
                self.stream_log.append(values)
            if not self.enabled or any(not self.min_V <= v <= self.max_V[a] for a, v in zip(self.axes, values)):
                self.rejected += 1
                if self.stream.state is not StreamState.FAULT:
                    self.stream.fault()
                    self._error(3 if not self.enabled else 1, 0, seq)
                return
            expected = self.stream.expected_seq
            outcome = self.stream.push(seq, values, now)
            if outcome == "gap":
                self.gaps += 1
                self._error(2, expected, seq)
            elif outcome == "overflow":
                self._error(5, seq, seq)
            elif outcome == "idle":
                self.rejected += 1
            self._stream_lock.notify_all()

    def _player_loop(self) -> None:
        """The amplifier's own clock: plays due ticks, reports the FIFO every STATUS_PERIOD_S."""
        with self._stream_lock:
            while self._running:
                now = self.now()
                self._run_stream(now)
                nxt = self.stream.next_tick_s()
                if nxt is not None and now - self._last_stream_status_s >= STATUS_PERIOD_S:
                    self._last_stream_status_s = now
                    self.send_stream_status()
                if self.stream.state is StreamState.ARMED:
                    self._keep_sink_current(now)
                # wake for the next tick, but at most every 1 ms (ticks are played late in
                # batches with their own computed times; the sink never sees the wake-up time)
                wait = 0.05 if nxt is None else min(max(nxt - now, 0.0), 0.001)
                self._stream_lock.wait(wait if wait > 0 else 0.0005)
