"""The CAN amplifier driver (frames of ``afm_amplifier.dbc``, see :mod:`afmctl.drivers.codec_can`).

Streaming: one SETPOINT_XYZ frame per 3-axis setpoint, SEQ counting up by one (mod 256);
axes not given keep their last value. Nothing waits for the amplifier while streaming;
:meth:`flush` sends a HEARTBEAT asking for STATUS and checks that the amplifier's
LAST_SEQ is the last one sent (no frame lost) and that no ERROR frame came back.
At connect the driver asks for LIMITS and STATUS and continues the sequence after the
amplifier's LAST_SEQ. Received frames are handled by a :class:`can.Notifier`; bus errors
arrive through the listener's ``on_error`` and put the driver in ``DISCONNECTED``.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Mapping

from . import codec_can as codec
from .base import ConnectionState, VoltageLimits
from .errors import AmplifierConnectionError, AmplifierError, AmplifierTimeout, LimitError, ProtocolError
from .serial_amp import HostLimits, LimitedAmplifier
from .transport_can import CanTransport

log = logging.getLogger(__name__)


class CANAmplifier(LimitedAmplifier):
    """``CANAmplifier(transport, timeout_s=0.5, host_limits=None, max_step_V=None,
    reconnect_timeout_s=5.0)``; axes x, y, z; voltages in V."""

    name = "can"
    default_baudrate = None

    def __init__(self, transport: CanTransport, *, timeout_s: float = 0.5, host_limits: HostLimits = None,
                 max_step_V: float | None = None, reconnect_timeout_s: float = 5.0,
                 backoff_s: tuple[float, float] = (0.05, 1.0), connect: bool = True) -> None:
        super().__init__(transport, host_limits=host_limits, max_step_V=max_step_V,
                         reconnect_timeout_s=reconnect_timeout_s, backoff_s=backoff_s)
        self.timeout_s = float(timeout_s)
        self._cond = threading.Condition()
        self._status: dict[str, float] | None = None
        self._status_count = 0
        self._limits_frame: dict[str, float] | None = None
        self._errors: list[ProtocolError] = []
        self._bus_error: Exception | None = None
        self._seq = 0
        self._last_sent_seq: int | None = None
        self._counter = 0
        self.sent = 0
        if connect:
            self.connect()

    @property
    def axes(self) -> tuple[str, ...]:
        return ("x", "y", "z")

    # -- receive side (notifier thread) --
    def _on_message(self, msg) -> None:
        fid = msg.arbitration_id
        if fid not in (codec.STATUS_ID, codec.ERROR_ID, codec.LIMITS_ID):
            return
        try:
            sig = codec.decode(fid, msg.data)
        except ProtocolError as err:
            with self._cond:
                self._errors.append(err)
            return
        with self._cond:
            if fid == codec.STATUS_ID:
                self._status = sig
                self._status_count += 1
            elif fid == codec.LIMITS_ID:
                self._limits_frame = sig
            else:
                self._errors.append(codec.error_from(sig, bytes(msg.data)))
            self._cond.notify_all()

    def _on_error(self, exc: Exception) -> None:
        self._bus_error = exc
        if self._state is ConnectionState.CONNECTED:
            self._state = ConnectionState.DISCONNECTED
            log.warning("can: bus error on %s: %s", self.transport.url, exc)

    # -- helpers --
    def _guard(self) -> None:
        if self._state is ConnectionState.CLOSED:
            raise AmplifierConnectionError(f"can amplifier on {self.transport.url} is closed")
        if self._state is not ConnectionState.CONNECTED:
            raise AmplifierConnectionError(
                f"can amplifier on {self.transport.url} is {self._state.value}; call reconnect()")
        self._raise_errors()

    def _raise_errors(self) -> None:
        with self._cond:
            if self._errors:
                err = self._errors.pop(0)
                self._errors.clear()
                raise err

    def _heartbeat(self, req_state: int = 0, req_status: bool = False, req_info: bool = False) -> None:
        self._counter = (self._counter + 1) & 0xFF
        self.transport.send(codec.HEARTBEAT_ID, codec.encode_heartbeat(self._counter, req_state, req_status, req_info),
                            self.timeout_s)

    def _request_status(self, req_info: bool = False, req_state: int = 0) -> dict[str, float]:
        with self._cond:
            before = self._status_count
        self._heartbeat(req_state=req_state, req_status=True, req_info=req_info)
        deadline = time.monotonic() + self.timeout_s
        with self._cond:
            while self._status_count == before or (req_info and self._limits_frame is None):
                left = deadline - time.monotonic()
                if left <= 0:
                    if self._state is ConnectionState.CONNECTED:
                        self._state = ConnectionState.FAULT
                    raise AmplifierTimeout(f"no STATUS from the CAN amplifier on {self.transport.url} "
                                           f"within {self.timeout_s:g} s")
                self._cond.wait(left)
            assert self._status is not None
            return dict(self._status)

    # -- life --
    def _open_and_handshake(self) -> None:
        with self._cond:
            self._limits_frame = None
            self._errors.clear()
        self._bus_error = None
        if not self.transport.is_open:
            self.transport.open(self._on_message, self._on_error)
        status = self._request_status(req_info=True)
        lim = self._limits_frame
        assert lim is not None
        device = {a: VoltageLimits(float(lim["MIN_V"]), float(lim[f"{a.upper()}_MAX_V"])) for a in self.axes}
        self._set_device_limits(device)
        self._last = {a: float(status[f"{a.upper()}_V"]) for a in self.axes}
        self._seq = (int(status["LAST_SEQ"]) + 1) & 0xFF
        self._last_sent_seq = None
        with self._cond:
            self._errors.clear()

    def connect(self) -> None:
        with self._lock:
            try:
                self._open_and_handshake()
            except AmplifierError:
                self.transport.close()
                raise
            self._state = ConnectionState.CONNECTED

    def close(self) -> None:
        with self._lock:
            if self._state is ConnectionState.CLOSED:
                return
            self.transport.close()
            self._state = ConnectionState.CLOSED

    # -- commands --
    def set_voltages(self, volts: Mapping[str, float]) -> None:
        with self._lock:  # validate under the lock: max_step_V is relative to the last output
            values = self.validate(volts)
            self._guard()
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
            self._io_send(codec.SETPOINT_ID, data)
            self._last_sent_seq = self._seq
            self._seq = (self._seq + 1) & 0xFF
            self.sent += 1
            self._last = full

    def _io_send(self, frame_id: int, data: bytes) -> None:
        try:
            self.transport.send(frame_id, data, self.timeout_s)
        except AmplifierConnectionError:
            self._state = ConnectionState.DISCONNECTED
            raise
        except AmplifierTimeout:
            self._state = ConnectionState.FAULT
            raise

    def flush(self) -> None:
        with self._lock:
            self._guard()
            status = self._request_status()
            self._raise_errors()
            if self._last_sent_seq is not None and int(status["LAST_SEQ"]) != self._last_sent_seq:
                raise ProtocolError(f"amplifier applied SEQ {int(status['LAST_SEQ'])}, last sent "
                                    f"{self._last_sent_seq}: setpoints lost")

    def check_errors(self) -> None:
        self.flush()

    def get_voltages(self) -> dict[str, float]:
        with self._lock:
            self.flush()
            assert self._status is not None
            values = {a: float(self._status[f"{a.upper()}_V"]) for a in self.axes}
            self._last = dict(values)
            return values

    def enable(self) -> None:
        with self._lock:
            self._guard()
            self._request_status(req_state=1)

    def disable(self) -> None:
        with self._lock:
            self._guard()
            self._request_status(req_state=2)

    def info(self) -> dict[str, object]:
        st = self._status or {}
        return {
            "driver": self.name,
            "port": self.transport.url,
            "state": self._state.value,
            "axes": list(self.axes),
            "device_limits_V": {a: [lim.min_V, lim.max_V] for a, lim in self._device_limits.items()},
            "limits_V": {a: [lim.min_V, lim.max_V] for a, lim in self._limits.items()},
            "amplifier_state": codec.STATES.get(int(st.get("STATE", 2)), "unknown"),
            "dbc": str(codec.DBC_PATH),
        }
