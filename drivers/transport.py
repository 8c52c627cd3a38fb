"""Transports: move bytes (pyserial) or frames (python-can), nothing else.

Every read and write has a timeout; pyserial's ``write_timeout`` is always set (its
default ``None`` blocks forever when a device stops reading). pyserial and OS errors are
mapped onto :mod:`afmctl.drivers.errors`: a lost port raises
:class:`~afmctl.drivers.errors.AmplifierConnectionError`, a stalled one
:class:`~afmctl.drivers.errors.AmplifierTimeout` carrying the bytes received so far.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from .errors import AmplifierConnectionError, AmplifierTimeout, ProtocolError

log = logging.getLogger(__name__)

#: granularity of blocking reads [s]; deadlines are enforced by the read loop
_POLL_S = 0.01
#: most bytes taken in one read of what has arrived [bytes]
_READ_CHUNK = 65536


class SerialTransport:
    """A byte link over any pyserial ``serial_for_url`` URL or device path
    (``/dev/ttyUSB0``, a pty path, ``loop://``, ``socket://host:port`` ...).

    ``timeout_s`` bounds every blocking read, ``write_timeout_s`` every write [s].
    The port is opened by :meth:`open` (drivers call it at connect and reconnect).

    Pacing without round trips: the transport knows when the bytes it has written will
    have left the wire at ``baudrate`` (8N1, 10 bits per byte) and keeps at most
    ``max_backlog_s`` of them queued in OS buffers (a write waits first), so streaming
    runs at the link rate with bounded latency. A read's timeout starts when the
    backlog has drained.
    """

    def __init__(self, url: str, *, baudrate: int = 115200, timeout_s: float = 0.5,
                 write_timeout_s: float | None = None, max_backlog_s: float = 0.02,
                 **serial_options: object) -> None:
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        self.url = url
        self.baudrate = int(baudrate)
        self.timeout_s = float(timeout_s)
        self.write_timeout_s = float(write_timeout_s if write_timeout_s is not None else timeout_s)
        self.max_backlog_s = float(max_backlog_s)
        # a TCP link (socket://, a controller's Ethernet port) has no baud rate to pace by
        paced = self.baudrate > 0 and not url.startswith("socket://")
        self._s_per_byte = 10.0 / self.baudrate if paced else 0.0
        self._wire_free_at = 0.0
        if "://" not in url:
            # two programs writing to one amplifier is never intended: lock the device
            serial_options.setdefault("exclusive", True)
        self._options = serial_options
        # pyserial's socket:// port says only whether a byte waits (in_waiting 0 or 1), not
        # how many: there, what has arrived is taken by a read that does not wait
        self._in_waiting_exact = not url.startswith("socket://")
        self._port: Any = None  # a pyserial port (pyserial ships no type information)
        self._buf = bytearray()

    # -- life --
    @property
    def is_open(self) -> bool:
        return self._port is not None and self._port.is_open

    def open(self) -> None:
        import serial
        self.close()
        try:
            self._port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=_POLL_S,
                                               write_timeout=self.write_timeout_s, **self._options)
            self._port.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as err:
            self.close()  # a port opened before the failure must not leak its fd
            raise AmplifierConnectionError(f"cannot open {self.url}: {err}") from None
        self._buf.clear()
        self._wire_free_at = 0.0
        log.debug("opened %s at %d baud", self.url, self.baudrate)

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except Exception:  # noqa: BLE001 - a vanished port may fail to close; it is gone anyway
                log.debug("close of %s failed", self.url, exc_info=True)

    def _require(self):
        if self._port is None:
            raise AmplifierConnectionError(f"{self.url} is not open")
        return self._port

    # -- bytes --
    def write(self, data: bytes) -> None:
        import serial
        port = self._require()
        now = time.monotonic()
        wait = self._wire_free_at - now - self.max_backlog_s
        if wait > 0:
            time.sleep(wait)
            now += wait
        self._wire_free_at = max(self._wire_free_at, now) + len(data) * self._s_per_byte
        try:
            n = port.write(data)
        except serial.SerialTimeoutException:
            raise AmplifierTimeout(f"write to {self.url} timed out after {self.write_timeout_s:g} s",
                                   data=data) from None
        except (serial.SerialException, OSError) as err:
            raise AmplifierConnectionError(f"write to {self.url} failed: {err}") from None
        if n is not None and n != len(data):
            raise AmplifierTimeout(f"write to {self.url}: {n} of {len(data)} bytes", data=data)

    def _read_some(self, block: bool) -> bytes:
        """What has arrived (all of it, up to :data:`_READ_CHUNK` bytes); with ``block``,
        first waiting up to one poll interval for a byte."""
        import serial
        port = self._require()
        try:
            n = port.in_waiting
            if n:
                data = port.read(n)
            elif block:
                data = port.read(1)
            else:
                return b""
            return data + self._read_arrived(port) if data else data
        except (serial.SerialException, OSError) as err:
            raise AmplifierConnectionError(f"read from {self.url} failed: {err}") from None

    def _read_arrived(self, port: Any) -> bytes:
        """The bytes that have arrived, without waiting for more."""
        if self._in_waiting_exact:
            n = port.in_waiting
            return port.read(n) if n else b""
        port.timeout = 0                 # socket://: read what is there and return at once
        try:
            return port.read(_READ_CHUNK)
        finally:
            port.timeout = _POLL_S

    def backlog_s(self) -> float:
        """Estimated wire time of the bytes written but not yet sent [s]."""
        return max(0.0, self._wire_free_at - time.monotonic())

    def discard_input(self) -> None:
        """Drop everything received so far (buffered and pending in the OS)."""
        port = self._require()
        import serial
        try:
            port.reset_input_buffer()
        except (serial.SerialException, OSError) as err:
            raise AmplifierConnectionError(f"{self.url}: {err}") from None
        self._buf.clear()

    def resync(self, terminator: bytes, probe: bytes, split: Callable[[bytearray], int],
               accept: Callable[[bytes], bool], timeout_s: float | None = None,
               max_frames: int = 64) -> bytes:
        """Start from a clean line, however late the device answers: drop what has
        arrived, send ``terminator`` (ends any partial command the device still holds from
        a lost link) and ``probe`` (one or more command lines with a known reply), then
        read frames, discarding every one (a late answer to the bare terminator, a reply
        still in flight from before) until ``accept(frame)`` is true; return that frame.
        Waits at most ``timeout_s`` [s] (default: twice the read timeout) for it, so a
        link whose replies arrive 100 ms late still connects; no fixed quiet window.
        Silence raises AmplifierTimeout; other frames but never the known one, ProtocolError."""
        self.discard_input()
        self.write(terminator + probe)
        wait = 2 * self.timeout_s if timeout_s is None else timeout_s
        deadline = max(time.monotonic(), self._wire_free_at) + wait
        skipped: list[bytes] = []
        while len(skipped) <= max_frames:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            try:
                frame = self.read_frame(split, timeout_s=left)
            except AmplifierTimeout:
                break
            if accept(frame):
                if skipped:
                    log.debug("%s: resynchronised after %d stale frame(s): %r", self.url, len(skipped), skipped[-3:])
                return frame
            skipped.append(frame)
        if skipped:  # it talks, but never the known reply: not the protocol we speak
            raise ProtocolError(f"{self.url} answered {len(skipped)} frame(s) but never the reply to "
                                f"{probe!r} within {wait:g} s", data=b"".join(skipped)[-200:])
        raise AmplifierTimeout(f"no reply to {probe!r} from {self.url} within {wait:g} s",
                               data=bytes(self._buf[-200:]))

    def take_frames(self, split: Callable[[bytearray], int]) -> list[bytes]:
        """Without blocking: read what has arrived and return every complete frame.
        ``split(buffer)`` returns the length of the first complete frame or -1."""
        self._buf += self._read_some(block=False)
        frames: list[bytes] = []
        while True:
            n = split(self._buf)
            if n < 0:
                return frames
            frames.append(bytes(self._buf[:n]))
            del self._buf[:n]

    def read_frame(self, split: Callable[[bytearray], int], timeout_s: float | None = None) -> bytes:
        """Block until one complete frame has arrived, at most ``timeout_s`` [s]."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        deadline = max(time.monotonic(), self._wire_free_at) + timeout
        while True:
            n = split(self._buf)
            if n >= 0:
                frame = bytes(self._buf[:n])
                del self._buf[:n]
                return frame
            if time.monotonic() >= deadline:
                raise AmplifierTimeout(f"no complete reply from {self.url} within {timeout:g} s",
                                       data=bytes(self._buf[-200:]))
            self._buf += self._read_some(block=True)


def parse_can_url(port: str) -> tuple[str, str]:
    """``"virtual:afm0"`` → ``("virtual", "afm0")``; ``"socketcan:can0"`` likewise."""
    interface, sep, channel = port.partition(":")
    if not sep or not interface or not channel:
        raise AmplifierConnectionError(
            f"CAN port {port!r} must look like INTERFACE:CHANNEL, e.g. virtual:afm0 or socketcan:can0")
    return interface, channel
