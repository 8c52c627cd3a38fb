"""piezosystem jena NV200 in open-loop voltage mode over serial.

At connect: ``cl,0`` (open loop), ``modsrc,0`` (setpoint from the serial link), voltage
range from ``avmin``/``avmax``. Setpoints ``set,<V>`` are written back to back; error
frames (``error,<n>``) that arrive are raised as
:class:`~afmctl.drivers.errors.ProtocolError` with the device code at the next call; a read
(``set``) serves as the synchronisation point of :meth:`flush`.
"""
from __future__ import annotations

from . import codec_nv200 as codec
from .base import VoltageLimits
from .errors import ProtocolError
from .serial_amp import SerialAmplifier
from .transport import SerialTransport

#: frames other than the awaited reply or an error tolerated while waiting for a reply
_MAX_SKIPPED = 64


class NV200(SerialAmplifier):
    """``NV200(transport, host_limits=None, max_step_V=None, ...)``; one axis ``x``."""

    name = "nv200"

    def __init__(self, transport: SerialTransport, **options) -> None:
        super().__init__(transport, **options)

    @property
    def axes(self) -> tuple[str, ...]:
        return ("x",)

    def _read(self, command: str) -> float:
        self.transport.write(codec.encode(command))
        for _ in range(_MAX_SKIPPED):
            reply = self.transport.read_frame(codec.split_reply)
            if codec.is_error(reply):
                raise codec.error_from(reply)
            if codec.frame_fields(reply)[0] == command.encode():
                return codec.parse_value(command, reply)
        raise ProtocolError(f"no reply to {command!r} among {_MAX_SKIPPED} frames", data=reply)

    def _handshake(self):
        self.transport.discard_input()
        self.transport.settle(codec.TERMINATOR)
        self.transport.write(codec.encode("cl,0") + codec.encode("modsrc,0"))
        lo = self._read("avmin")
        hi = self._read("avmax")
        if not lo <= hi:
            raise ProtocolError(f"device voltage range is empty: [{lo}, {hi}] V")
        stat = int(self._read("stat"))
        return {"x": VoltageLimits(lo, hi)}, {"status_word": stat}

    def _read_voltages(self) -> dict[str, float]:
        return {"x": self._read("meas")}

    def _drain(self) -> None:
        for reply in self.transport.take_frames(codec.split_reply):
            if codec.is_error(reply):
                raise codec.error_from(reply)

    def _write_setpoint(self, values: dict[str, float]) -> None:
        lim = self._limits["x"]
        data = codec.encode_set(values["x"], lim.min_V, lim.max_V)
        self._drain()
        self.transport.write(data)

    def _sync(self) -> None:
        self._read("set")
