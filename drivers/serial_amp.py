"""What the serial drivers (MDT69xB, GCS, NV200) add to the :class:`~afmctl.drivers.base.Amplifier`
template: a :class:`~afmctl.drivers.transport.SerialTransport` built from a URL, opened at
connect and reconnect, and a pipeline of outstanding replies that is forgotten on reopen.
"""
from __future__ import annotations

from typing import Any

from .base import Amplifier
from .transport import SerialTransport


class SerialAmplifier(Amplifier):
    """Base of the serial drivers; subclasses implement the protocol hooks of
    :class:`~afmctl.drivers.base.Amplifier`."""

    #: default baud rate of the protocol
    default_baudrate = 115200
    transport: SerialTransport

    @classmethod
    def open(cls, port: str, *, baudrate: int | None = None, timeout_s: float = 0.5,
             write_timeout_s: float | None = None, **options: Any) -> "SerialAmplifier":
        """Connect over any pyserial URL or device path (``/dev/ttyUSB0``, a pty,
        ``socket://host:port``); ``timeout_s`` bounds every read/write [s]."""
        transport = SerialTransport(port, baudrate=baudrate or cls.default_baudrate, timeout_s=timeout_s,
                                    write_timeout_s=write_timeout_s)
        try:
            return cls(transport, **options)
        except BaseException:
            transport.close()
            raise

    def _reset_pipeline(self) -> None:
        """Forget outstanding replies (after reopen)."""

    def _open_link(self) -> None:
        if not self.transport.is_open:
            self.transport.open()
        self._reset_pipeline()

    def _info_extra(self) -> dict[str, object]:
        if self.transport.url.startswith("socket://"):
            return {"link": "TCP (no baud rate)"}
        return {"baudrate": self.transport.baudrate}
