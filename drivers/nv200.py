"""piezosystem jena NV200 in open-loop voltage mode over serial.

Connect: the driver resynchronises on the reply to ``avmin`` (whatever the unit answered
to the bare line end before it — its device type — and however late), reads the voltage
range (``avmin``/``avmax``) and the status word ``stat``. Settings the unit stores in the
actuator's memory are not written silently: ``cl`` (loop mode) and ``modsrc`` (setpoint
source) are read, and only if they are not 0 (open loop, setpoint from the serial link)
they are set to 0, with a warning naming the old values; they are written back at
:meth:`close` when ``restore_settings=True`` (default False, because restoring closed
loop or the analog input moves the actuator after we let go).

Read-back: ``meas`` is the piezo voltage only on an actuator without a position sensor;
with one (``stat`` bits 1–2 name the sensor) it is the position in µm or mrad. The driver
then reads the output voltage the way the unit provides it, through the data recorder
(channel A recording the piezo voltage, ``recsrc,0,2``; one sample, ``recrun,1`` then
``recout,0,0,1``); the recorder settings are volatile. Setpoints ``set,<V>`` are written back to back;
error frames (``error,<n>``) are raised as :class:`~afmctl.drivers.errors.ProtocolError`
with the device code at the next call; a read (``set``) is the synchronisation point of
:meth:`flush`.
"""
from __future__ import annotations

import logging
import time
from typing import Any, cast

from collections.abc import Callable, Sequence

import numpy as np

from . import codec_gcs_wave
from . import codec_nv200 as codec
from . import codec_nv200_rec as rcodec
from . import codec_nv200_wave as wcodec
from .base import VoltageLimits
from .errors import AmplifierError, LimitError, ProtocolError, RecorderUnavailable
from .recording import Recording, RecorderSetup, time_axis
from .serial_amp import SerialAmplifier
from .transport import SerialTransport
from .wave_check import WaveStatus, check_table

log = logging.getLogger(__name__)

#: frames other than the awaited reply or an error tolerated while waiting for a reply
_MAX_SKIPPED = 64
#: ``stat`` bits 1-2: position sensor type
SENSORS = {0: "none", 1: "strain gauge", 2: "capacitive", 3: "LVDT"}
#: stored settings the driver needs at 0 while it drives the unit (open loop, serial setpoint)
_STORED = ("cl", "modsrc")
#: data recorder source code of the piezo voltage
_RECSRC_PIEZO_VOLTAGE = 2


def sensor_of(status_word: int) -> str:
    """Position sensor named by bits 1-2 of the ``stat`` word."""
    return SENSORS[(int(status_word) >> 1) & 0b11]


class NV200(SerialAmplifier):
    """``NV200(transport, host_limits=None, max_step_V=None, restore_settings=False, ...)``;
    one axis ``x``; voltages in V."""

    name = "nv200"
    has_recorder = True

    def __init__(self, transport: SerialTransport, *, restore_settings: bool = False, **options: Any) -> None:
        self.restore_settings = bool(restore_settings)
        self.sensor = "none"
        #: stored settings changed at connect: name -> value found
        self.changed_settings: dict[str, int] = {}
        self._table: np.ndarray | None = None
        self._wave_run = (0.0, 0, 0)
        self._playing = False
        #: a recording read back before the driver reused the recorder (sensored units read
        #: their output voltage through it)
        self._rec_cache: Recording | None = None
        self._rec_pending = False
        self._rec_dirty = False
        self._rec_triggered = False
        super().__init__(transport, **options)

    @property
    def axes(self) -> tuple[str, ...]:
        return ("x",)

    def _reply_to(self, command: str) -> bytes:
        """Write a read command and return its reply frame (skipping unrelated frames)."""
        self.transport.write(codec.encode(command))
        name = command.split(",")[0].encode()
        for _ in range(_MAX_SKIPPED):
            reply = self.transport.read_frame(codec.split_reply)
            if codec.is_error(reply):
                raise codec.error_from(reply)
            if codec.frame_fields(reply)[0] == name:
                return reply
        raise ProtocolError(f"no reply to {command!r} among {_MAX_SKIPPED} frames", data=reply)

    def _read(self, command: str) -> float:
        return codec.parse_value(command, self._reply_to(command))

    def _handshake(self):
        self.changed_settings = {}
        reply = self.transport.resync(codec.TERMINATOR, codec.encode("avmin"), codec.split_reply,
                                      lambda f: codec.last_line(f).startswith(b"avmin,"))
        device_type = codec.device_type(reply)
        lo = codec.parse_value("avmin", codec.last_line(reply) + codec.XON)
        hi = self._read("avmax")
        if not lo <= hi:
            raise ProtocolError(f"device voltage range is empty: [{lo}, {hi}] V")
        stat = int(self._read("stat"))
        self.sensor = sensor_of(stat)
        self._take_control()
        if self.sensor != "none":
            self.transport.write(b"".join(codec.encode(c) for c in (
                "recast,0", f"recsrc,0,{_RECSRC_PIEZO_VOLTAGE}", "recstr,1", "reclen,1")))
        identity = {"status_word": stat, "sensor": self.sensor, "changed_settings": dict(self.changed_settings)}
        if device_type:
            identity["device_type"] = device_type
        return {"x": VoltageLimits(lo, hi)}, identity

    def _take_control(self) -> None:
        """Set ``cl`` and ``modsrc`` to 0 only where they are not, and say so."""
        for name in _STORED:
            value = int(self._read(name))
            if value != 0:
                self.changed_settings[name] = value
                self.transport.write(codec.encode(f"{name},0"))
        if self.changed_settings:
            log.warning("nv200 on %s: stored settings %s changed to 0 (open loop, setpoint from the "
                        "serial link); %s", self.transport.url,
                        ", ".join(f"{k} was {v}" for k, v in self.changed_settings.items()),
                        "restored at close" if self.restore_settings else "left so after close")

    def _read_voltages(self) -> dict[str, float]:
        if self.sensor == "none":
            return {"x": self._read("meas")}  # without a sensor meas is the piezo voltage
        if self._rec_pending:          # the recorder is about to be reused: keep the recording
            self._fetch_recording()
        if self._rec_dirty:            # a recording changed the set-up the read-back relies on
            self.transport.write(b"".join(codec.encode(c) for c in (
                "recast,0", f"recsrc,0,{_RECSRC_PIEZO_VOLTAGE}", "recstr,1", "reclen,1")))
            self._rec_dirty = False
        self.transport.write(codec.encode("recrun,1"))
        fields = codec.frame_fields(self._reply_to("recout,0,0,1"))
        if len(fields) != 4:
            raise ProtocolError("reply to 'recout,0,0,1' does not hold channel, index and value",
                                data=b",".join(fields))
        return {"x": codec.parse_number(fields[3], "recout", b",".join(fields))}

    def _drain(self) -> None:
        for reply in self.transport.take_frames(codec.split_reply):
            if codec.is_error(reply):
                raise codec.error_from(reply)

    def _write_setpoint(self, values: dict[str, float]) -> None:
        if self._playing:
            raise LimitError("axis x: the waveform generator runs; stop_wave(), or wait until "
                             "wave_status() reports its end, before setting voltages")
        lim = self._limits["x"]
        data = codec.encode_set(values["x"], lim.min_V, lim.max_V)
        self._drain()
        self.transport.write(data)

    def _sync(self) -> None:
        self._read("set")

    def _on_close(self) -> None:
        if self.restore_settings and self.changed_settings:
            try:
                self._sync()
                self.transport.write(b"".join(codec.encode(f"{k},{v}") for k, v in self.changed_settings.items()))
                now = {k: int(self._read(k)) for k in self.changed_settings}  # read back: applied?
                if now != self.changed_settings:
                    raise ProtocolError(f"settings read back as {now} after restoring")
                log.info("nv200 on %s: restored %s", self.transport.url, self.changed_settings)
            except AmplifierError as err:
                log.warning("nv200 on %s: could not restore %s: %s", self.transport.url, self.changed_settings, err)

    # ---- arbitrary waveform generator (codec_nv200_wave) ----
    def servo_cycle_s(self) -> float:
        """The waveform generator's base sample time [s] (50 us)."""
        return wcodec.BASE_SAMPLE_S

    def wave_capacity(self, axis: str = "x") -> int:
        """The most samples the waveform buffer takes (1024)."""
        return wcodec.BUFFER_SIZE

    def upload_wave(self, axis: str, table_V: Sequence[float]) -> int:
        """Write ``table_V`` [V] (at most 1024 samples) into the waveform buffer; every sample
        is checked (limits, ``max_step_V``) before anything is sent. Returns the samples written."""
        if axis != "x":
            raise LimitError(f"axis {axis!r}: the NV200 drives x only")
        with self._lock:
            self._guard()
            v = check_table(axis, table_V, self._limits["x"], max_step_V=self.max_step_V,
                            start_V=self._last.get("x"))
            if len(v) > wcodec.BUFFER_SIZE:
                raise LimitError(f"wave table of axis x: {len(v)} samples, the NV200 buffer holds "
                                 f"{wcodec.BUFFER_SIZE}; nothing was sent")
            dev, lim = self._device_limits["x"], self._limits["x"]
            lines = wcodec.encode_buffer(v, dev.min_V, dev.max_V, lim.min_V, lim.max_V)
            self._io(self._send_synced, *lines)
            self._table = v
            return len(v)

    def _send_synced(self, *chunks: bytes) -> None:
        self._drain()
        for data in chunks:
            self.transport.write(data)
        self._read("grun")  # every write before it was taken (errors come back as frames first)

    def start_wave(self, rate_Hz: float | None = None, *, divider: int | None = None, cycles: int = 1,
                   axes: Sequence[str] | None = None) -> WaveStatus:
        """Play the uploaded buffer ``cycles`` times (0 = until :meth:`stop_wave`) at ``rate_Hz``
        (20 kHz over a whole number) or a sample every ``divider`` x 50 us."""
        if self._table is None or (axes is not None and list(axes) != ["x"]):
            raise LimitError("start_wave: upload a table for axis x first (upload_wave)")
        if not (isinstance(cycles, int) and 0 <= cycles <= 65535):
            raise LimitError(f"cycles: {cycles!r} must be a whole number 0..65535 (0 = endless)")
        if divider is None:
            try:
                divider = codec_gcs_wave.divider_for(float(rate_Hz or 0) or -1.0, wcodec.BASE_SAMPLE_S)
            except (ValueError, ZeroDivisionError) as err:
                raise LimitError(f"rate_Hz: {err}") from None
        if not (isinstance(divider, int) and 1 <= divider <= wcodec.MAX_FACTOR):
            raise LimitError(f"divider: {divider!r} must be a whole number 1..65535 of 50 us")
        with self._lock:
            self._guard()
            check_table("x", self._table, self._limits["x"], max_step_V=self.max_step_V,
                        start_V=self._last.get("x"), wraps=cycles != 1)
            self._io(self._send_synced, wcodec.encode_start(len(self._table), divider, cycles))
            self._wave_run = (1.0 / (divider * wcodec.BASE_SAMPLE_S), divider, cycles)
            self._playing = True
            self._rec_triggered = self._rec_pending   # an armed recording starts with it (recast 2)
        return self.wave_status()

    def wave_status(self) -> WaveStatus:
        """``grun``: is the generator running? Once it has stopped, the serial setpoint takes
        the output's last value and becomes the source again (``modsrc,0``)."""
        with self._lock:
            self._guard()
            running = bool(self._io(self._read, "grun"))
            if self._playing and not running:
                self._io(self._hand_back)
        rate, div, cyc = self._wave_run
        return WaveStatus({"x": running}, rate, div, cyc, {"x": len(self._table) if self._table is not None else 0})

    def _hand_back(self) -> None:
        v = self._read_voltages()["x"]  # the end of the table, or wherever stop_wave left it
        lim = self._limits["x"]
        v = min(max(float(v), lim.min_V), lim.max_V)
        self.transport.write(wcodec.encode_hand_back(v, lim.min_V, lim.max_V))
        self._read("set")
        self._last["x"] = v
        self._measured.add("x")
        self._playing = False

    def stop_wave(self) -> WaveStatus:
        """Stop the generator now (``grun,0``); the output holds where it was."""
        with self._lock:
            self._guard()
            self._io(self._send_synced, codec.encode("grun,0"))
        return self.wave_status()

    # ---- data recorder (the Amplifier template's configure_recorder / read_recording) ----
    def _recorder_clock_s(self) -> float:
        return rcodec.BASE_SAMPLE_S

    def _recorder_capacity(self, axes: tuple[str, ...], signals: tuple[str, ...]) -> int:
        if "y_nm" in signals and self.sensor == "none":
            raise RecorderUnavailable(
                "nv200: this actuator has no position sensor, so the recorder has no position to record; "
                "record u_V only, or measure the motion with an external sensor and give it as a file "
                "(t,y in nm; docs/DRIVERS.md, 'Recording the motion')")
        if len(signals) > rcodec.CHANNELS:
            raise LimitError(f"nv200: the recorder has {rcodec.CHANNELS} channels; {len(signals)} signals "
                             f"({', '.join(signals)}) do not fit one recording")
        return rcodec.BUFFER_SIZE

    def _configure_recorder(self, setup: RecorderSetup) -> RecorderSetup:
        channels = {sig: ch for ch, sig in enumerate(setup.signals)}
        sources = {ch: rcodec.SOURCES[sig] for sig, ch in channels.items()}
        self._drain()
        self.transport.write(rcodec.encode_configure(sources, setup.divider, setup.points))
        self._read("recrun")                # every write taken (an error comes back first)
        self._rec_cache, self._rec_pending, self._rec_dirty = None, True, True
        self._rec_triggered = False
        return RecorderSetup(setup.axes, setup.signals, setup.points, setup.divider, setup.clock_s,
                             {"channels": channels})

    def _recorded_points(self, setup: RecorderSetup) -> int:
        """The unit does not count its points: ``recrun`` reads 0 once it holds them all."""
        if self._rec_cache is not None:
            return len(self._rec_cache)
        return setup.points if not self._read("recrun") else 0

    def _fetch_recording(self) -> None:
        """Before the read-back reuses the recorder: a recording the waveform generator
        started is waited for (``recrun`` 0; at most its length + 2 s) and read into the
        cache; one never started (or not ending) is stopped and dropped, with a warning."""
        setup = self._recorder_setup
        self._rec_pending = False
        if setup is None:
            return
        deadline = time.monotonic() + setup.points * setup.period_s + 2.0
        while self._rec_triggered and self._read("recrun"):
            if time.monotonic() > deadline:
                break
            time.sleep(0.01)
        else:
            if self._rec_triggered:
                self._rec_cache = self._read_channels(setup)
                return
        self.transport.write(codec.encode("recrun,0"))
        self._recorder_setup = None
        log.warning("nv200 on %s: the armed recording %s; it was stopped and dropped to read the output",
                    self.transport.url, "did not end" if self._rec_triggered else "was never started by a wave")

    def _read_channels(self, setup: RecorderSetup) -> Recording:
        values = {}
        channels = cast("dict[str, int]", setup.extra["channels"])
        for sig, ch in channels.items():
            self._drain()
            self.transport.write(codec.encode(f"recoutf,{ch}"))
            values[sig] = rcodec.parse_recoutf(self.transport.read_frame(rcodec.split_recoutf, timeout_s=max(
                self.transport.timeout_s, 2.0)), ch)
        n = min(len(v) for v in values.values())
        y = {"x": values["y_nm"][:n] * 1000.0} if "y_nm" in values else {}   # µm -> nm
        u = {"x": values["u_V"][:n]} if "u_V" in values else {}
        v = {"x": values["v_V"][:n]} if "v_V" in values else {}
        return Recording(time_axis(n, setup.period_s), y, u, setup.period_s, "nv200 recoutf", v)

    def _read_recording(self, setup: RecorderSetup, cancel: Callable[[], bool]) -> Recording:
        """Both channels with one ``recoutf`` each (at most 6144 points: a few seconds at
        115200 baud; not cancelled mid-way)."""
        if self._rec_cache is None:
            self._rec_cache = self._read_channels(setup)
            self._rec_pending = False
        return self._rec_cache
