"""CAN transport: a python-can bus plus a :class:`can.Notifier` whose listener hands
frames (and bus errors, via ``on_error``) to the driver's callbacks."""
from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import can

from .errors import AmplifierConnectionError, AmplifierTimeout
from .transport import parse_can_url

log = logging.getLogger(__name__)


class CanTransport:
    """``CanTransport("virtual:afm0", **bus_options)``: the port is ``INTERFACE:CHANNEL``
    (any python-can interface). :meth:`open` creates the bus and the notifier."""

    def __init__(self, port: str, **bus_options: Any) -> None:
        self.url = port
        self.interface, self.channel = parse_can_url(port)
        self._options = bus_options
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None

    @property
    def is_open(self) -> bool:
        return self._bus is not None

    def open(self, on_message: Callable[[object], None], on_error: Callable[[Exception], None]) -> None:
        import can

        class _Listener(can.Listener):
            def on_message_received(self, msg: can.Message) -> None:
                on_message(msg)

            def on_error(self, exc: Exception) -> None:
                on_error(exc)
                time.sleep(0.05)  # a dead bus raises on every recv; do not spin

        self.close()
        try:
            self._bus = can.Bus(interface=self.interface, channel=self.channel, **self._options)
        except (can.CanError, OSError, ValueError, ImportError) as err:
            self._bus = None
            raise AmplifierConnectionError(f"cannot open CAN bus {self.url}: {err}") from None
        try:
            self._notifier = can.Notifier(self._bus, [_Listener()], timeout=0.05)
        except Exception:
            self.close()  # shut the bus down again
            raise

    def send(self, frame_id: int, data: bytes, timeout_s: float) -> None:
        import can
        if self._bus is None:
            raise AmplifierConnectionError(f"CAN bus {self.url} is not open")
        msg = can.Message(arbitration_id=frame_id, data=data, is_extended_id=False, is_fd=len(data) > 8)
        try:
            self._bus.send(msg, timeout=timeout_s)
        except can.CanOperationError as err:
            raise AmplifierTimeout(f"CAN send on {self.url} failed: {err}", data=data) from None
        except (can.CanError, OSError) as err:
            raise AmplifierConnectionError(f"CAN bus {self.url}: {err}") from None

    def close(self) -> None:
        notifier, self._notifier = self._notifier, None
        bus, self._bus = self._bus, None
        if notifier is not None:
            notifier.stop(timeout=1.0)
        if bus is not None:
            try:
                bus.shutdown()
            except Exception:  # noqa: BLE001
                log.debug("CAN shutdown failed", exc_info=True)
