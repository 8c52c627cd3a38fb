"""The CAN amplifier driver (frames of ``afm_amplifier.dbc``, see :mod:`afmctl.drivers.codec_can`).

Streaming: one SETPOINT_XYZ frame per 3-axis setpoint, SEQ counting up by one (mod 256);
axes not given keep their last value. Nothing waits for the amplifier while streaming;
:meth:`flush` sends a HEARTBEAT asking for STATUS and checks that the amplifier's
LAST_SEQ is the last one sent (no frame lost) and that no ERROR frame came back.
At connect the driver asks for LIMITS and STATUS and continues the sequence after the
amplifier's LAST_SEQ. Received frames are handled by a :class:`can.Notifier`; bus errors
arrive through the listener's ``on_error`` and put the driver in ``DISCONNECTED``.
The safety checks (limits, step limit, lock, state) are the template's
(:class:`afmctl.drivers.base.Amplifier`); this module fills in its hooks.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any

from . import codec_can as codec
from .base import Amplifier, ConnectionState, VoltageLimits
from .errors import AmplifierTimeout, LimitError, ProtocolError
from .transport_can import CanTransport

log = logging.getLogger(__name__)


class CANAmplifier(Amplifier):
    """``CANAmplifier(transport, timeout_s=0.5, host_limits=None, max_step_V=None,
    reconnect_timeout_s=5.0)``; axes x, y, z; voltages in V."""

    name = "can"
    default_baudrate = None
    sync_on_close = False  # a vanished amplifier would hold close() for timeout_s
    transport: CanTransport

    def __init__(self, transport: CanTransport, *, timeout_s: float = 0.5, **options: Any) -> None:
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
        self._ids = {name: codec.frame_id(name) for name in
                     (codec.SETPOINT, codec.HEARTBEAT, codec.STATUS, codec.ERROR, codec.LIMITS)}
        super().__init__(transport, **options)

    @classmethod
    def open(cls, port: str, *, baudrate: int | None = None, timeout_s: float = 0.5,
             write_timeout_s: float | None = None, **options: Any) -> "CANAmplifier":
        """Connect on ``INTERFACE:CHANNEL`` (python-can); ``baudrate`` is the bus bitrate."""
        return cls(CanTransport(port, **({"bitrate": baudrate} if baudrate else {})), timeout_s=timeout_s,
                   **options)

    @property
    def axes(self) -> tuple[str, ...]:
        return ("x", "y", "z")

    # -- receive side (notifier thread) --
    def _on_message(self, msg: Any) -> None:
        fid = msg.arbitration_id
        kind = {self._ids[codec.STATUS]: codec.STATUS, self._ids[codec.ERROR]: codec.ERROR,
                self._ids[codec.LIMITS]: codec.LIMITS}.get(fid)
        if kind is None:
            return
        try:
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
            else:
                self._errors.append(codec.error_from(sig, bytes(msg.data)))
            self._cond.notify_all()

    def _on_error(self, exc: Exception) -> None:
        self._bus_error = exc
        if self._state is ConnectionState.CONNECTED:
            self._state = ConnectionState.DISCONNECTED
            log.warning("can: bus error on %s: %s", self.transport.url, exc)

    # -- helpers --
    def _raise_pending(self) -> None:
        with self._cond:
            if self._errors:
                err = self._errors.pop(0)
                self._errors.clear()
                raise err

    def _heartbeat(self, req_state: int = 0, req_status: bool = False, req_info: bool = False) -> None:
        self._counter = (self._counter + 1) & 0xFF
        self.transport.send(self._ids[codec.HEARTBEAT],
                            codec.encode_heartbeat(self._counter, req_state, req_status, req_info), self.timeout_s)

    def _request_status(self, req_info: bool = False, req_state: int = 0) -> dict[str, float]:
        with self._cond:
            before = self._status_count
        self._heartbeat(req_state=req_state, req_status=True, req_info=req_info)
        deadline = time.monotonic() + self.timeout_s
        with self._cond:
            while self._status_count == before or (req_info and self._limits_frame is None):
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AmplifierTimeout(f"no STATUS from the CAN amplifier on {self.transport.url} "
                                           f"within {self.timeout_s:g} s")
                self._cond.wait(left)
            assert self._status is not None
            return dict(self._status)

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
