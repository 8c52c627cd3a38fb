"""Serve a simulated serial amplifier on a pseudo-terminal (``os.openpty()``).

A pty does not enforce a baud rate, so the server throttles itself: bytes from the host
are taken off the wire no faster than ``baud / 10`` bytes per second (8N1 = 10 bits per
byte) and replies are sent at the same rate. Two threads (receive, transmit) do the
work; nothing here blocks the caller.

Stable path: :attr:`port` is a symlink (in a private temporary directory, or at ``link``)
to the current pty slave. :meth:`disappear` closes the pty (the host sees its port
vanish: reads and writes fail), :meth:`reappear` opens a new pty and points the same
symlink at it, so a driver can reconnect to the same path. :meth:`silence` makes the
device ignore everything (host reads time out) until :meth:`resume`. The device's state
(its output voltages) survives both, as a powered amplifier's would; only a partial
command line is discarded when the link drops.
"""
from __future__ import annotations

import logging
import os
import queue
import select
import shutil
import tempfile
import threading
import time
import tty
from pathlib import Path

log = logging.getLogger(__name__)

#: how long a reply waits for a host whose input buffer is full before it is dropped [s]
HOST_STALL_S = 5.0


class _WireClock:
    """When the last byte of a chunk of ``n`` bytes has crossed the wire [monotonic s].

    While bytes keep waiting (``continuous``), the clock may lag the present by up to
    ``slack_s`` (thread wake-up jitter) without losing link time; otherwise it restarts at
    the present. Either way the modelled wire is never faster than the baud rate."""

    def __init__(self, baud: int, slack_s: float = 0.002) -> None:
        self.s_per_byte = 10.0 / baud if baud > 0 else 0.0
        self.slack_s = slack_s
        self.t = 0.0

    def finish(self, n: int, continuous: bool) -> float:
        now = time.monotonic()
        start = max(self.t, now - self.slack_s) if continuous else max(self.t, now)
        self.t = start + n * self.s_per_byte
        return self.t


class PtyServer:
    """``PtyServer(device, baud=115200, link=None, latency_s=0.0)``: serve ``device`` (a
    sans-I/O simulator with ``feed(bytes) -> bytes``) on a pty. Use as a context manager
    or call :meth:`start` / :meth:`stop`. ``baud=0`` disables throttling. ``latency_s``
    holds every reply that long before it reaches the host, like the latency timer of a
    USB-serial adapter (FTDI default 16 ms)."""

    def __init__(self, device, *, baud: int = 115200, link: str | os.PathLike | None = None,
                 latency_s: float = 0.0) -> None:
        self.device = device
        self.baud = int(baud)
        self.latency_s = float(latency_s)
        self._tmpdir: str | None = None
        if link is None:
            self._tmpdir = tempfile.mkdtemp(prefix="afmctl-pty-")
            link = Path(self._tmpdir) / f"tty{getattr(device, 'protocol', 'amp').upper()}"
        self.port = str(link)
        self.pty_path: str | None = None
        self._master = self._slave = -1
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._txq: queue.Queue[tuple[float, bytes]] = queue.Queue()
        self._silent = threading.Event()
        self._running = False
        self._lock = threading.Lock()
        self.bytes_received = 0
        self.bytes_sent = 0
        self.bytes_dropped = 0
        # Receive and transmit chunks of about 4 ms of wire time keep the pacing smooth.
        self._chunk = max(1, int(self.baud / 10 * 0.004)) if self.baud > 0 else 4096

    # -- life --
    def start(self) -> "PtyServer":
        with self._lock:
            if self._running:
                return self
            self._open()
            self._running = True
        return self

    def stop(self) -> None:
        with self._lock:
            if self._running:
                self._close()
                self._running = False
            self._unlink()
            if self._tmpdir is not None:
                shutil.rmtree(self._tmpdir, ignore_errors=True)
                self._tmpdir = None

    def __enter__(self) -> "PtyServer":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def disappear(self) -> None:
        """Close the pty: the host's port fails, the path vanishes."""
        with self._lock:
            if self._running:
                self._close()
                self._unlink()
                if hasattr(self.device, "line_break"):
                    self.device.line_break()  # a partial command dies with the link

    def reappear(self) -> None:
        """Open a new pty behind the same :attr:`port` path."""
        with self._lock:
            if self._running and self._master < 0:
                self._open()

    def silence(self) -> None:
        """Ignore every byte from now on (no replies, nothing applied)."""
        self._silent.set()

    def resume(self) -> None:
        self._silent.clear()

    pause = silence  # the names of the interface notes

    @property
    def silent(self) -> bool:
        return self._silent.is_set()

    # -- internals --
    def _open(self) -> None:
        master, slave = os.openpty()
        try:
            tty.setraw(slave)  # no echo, no line editing on the device side
            os.set_blocking(master, False)
            pty_path = os.ttyname(slave)
            tmp = f"{self.port}.{os.getpid()}.tmp"
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
            os.symlink(pty_path, tmp)
            os.replace(tmp, self.port)
        except OSError:
            os.close(master)  # e.g. the link's directory does not exist: leak nothing
            os.close(slave)
            raise
        self._master, self._slave = master, slave
        self.pty_path = pty_path
        self._stop = threading.Event()
        self._txq = queue.Queue()
        self._threads = [threading.Thread(target=self._rx_loop, args=(self._stop, master), daemon=True,
                                          name=f"pty-rx-{self.pty_path}"),
                         threading.Thread(target=self._tx_loop, args=(self._stop, master, self._txq), daemon=True,
                                          name=f"pty-tx-{self.pty_path}")]
        for t in self._threads:
            t.start()
        log.info("serving %s on %s (link %s) at %d baud", getattr(self.device, "protocol", "?"),
                 self.pty_path, self.port, self.baud)

    def _close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1

    def _unlink(self) -> None:
        try:
            if os.path.islink(self.port):
                os.unlink(self.port)
        except OSError:
            pass

    def _rx_loop(self, stop: threading.Event, master: int) -> None:
        clock = _WireClock(self.baud)
        continuous = False
        poll = getattr(self.device, "poll", None)
        while not stop.is_set():
            try:
                ready, _, _ = select.select([master], [], [], 0.02)
                if not ready:
                    continuous = False
                    if poll is not None:
                        poll()  # a device with its own clock (a wave generator) plays on
                    continue
                data = os.read(master, self._chunk)
            except BlockingIOError:
                continue
            except OSError:  # no slave side open (EIO) or closed under us
                time.sleep(0.01)
                continue
            if not data:
                continue
            self.bytes_received += len(data)
            if self.baud > 0:
                wait = clock.finish(len(data), continuous) - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            # A full chunk means more bytes were already waiting: the line never went idle.
            continuous = len(data) == self._chunk
            if self._silent.is_set():
                continue
            try:
                reply = self.device.feed(data)
            except Exception:  # noqa: BLE001 - a simulator bug must not kill the server silently
                log.exception("simulated device failed on %r", data)
                continue
            if reply:
                self._txq.put((time.monotonic() + self.latency_s, reply))

    def _wait_writable(self, stop: threading.Event, master: int) -> bool:
        """Wait until the host has read some of its input (True), at most HOST_STALL_S."""
        deadline = time.monotonic() + HOST_STALL_S
        while not stop.is_set() and time.monotonic() < deadline:
            try:
                _, ready, _ = select.select([], [master], [], 0.02)
            except (OSError, ValueError):
                return False
            if ready:
                return True
        return False

    def _tx_loop(self, stop: threading.Event, master: int, txq: "queue.Queue[tuple[float, bytes]]") -> None:
        clock = _WireClock(self.baud)
        pending = b""
        continuous = False
        while not stop.is_set():
            if not pending:
                try:
                    due, pending = txq.get(timeout=0.02)
                except queue.Empty:
                    continuous = False
                    continue
                hold = due - time.monotonic()
                if hold > 0:
                    time.sleep(hold)
            chunk, rest = pending[: self._chunk], pending[self._chunk:]
            if self.baud > 0:
                wait = clock.finish(len(chunk), continuous) - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            continuous = bool(rest) or not txq.empty()
            try:
                n = os.write(master, chunk)
            except BlockingIOError:
                # The host's input buffer is full. The links these devices have (USB, TCP,
                # a UART with RTS/CTS) hold the sender until the host reads; a host that
                # reads nothing for HOST_STALL_S is gone and the reply is lost.
                if self._wait_writable(stop, master):
                    continue
                self.bytes_dropped += len(pending)
                pending = b""
                continue
            except OSError:
                pending = b""
                continue
            self.bytes_sent += n
            pending = chunk[n:] + rest
