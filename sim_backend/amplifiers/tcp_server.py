"""A simulated amplifier on a TCP port of the loopback, the way controllers with an Ethernet
port are reached: PI's E-727 speaks GCS on TCP port 50000, the piezosystem jena NV200/D NET
its command set over a raw TCP (telnet) connection. The host's driver connects with the
pyserial URL ``socket://HOST:PORT`` (no baud rate: the link is not the bottleneck).

:class:`TcpServer` serves one client at a time (like the controllers); a client that closes
its connection frees the port for the next. The device is the same sans-I/O simulator the
pty server feeds (``feed(bytes) -> bytes``), so every protocol behaves alike on both links.
"""
from __future__ import annotations

import logging
import select
import socket
import threading

log = logging.getLogger(__name__)

_POLL_S = 0.1
#: how often a device with its own clock plays what fell due while the link is idle [s]
_IDLE_POLL_S = 0.02
#: how long one reply may wait for the client to read it [s]
_SEND_TIMEOUT_S = 10.0


def parse_endpoint(text: str) -> tuple[str, int]:
    """``HOST:PORT`` → (host, port); ValueError with the allowed form otherwise. Only
    loopback hosts are served (a simulator is not a network service)."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"{text!r}: need HOST:PORT with PORT 0..65535, e.g. 127.0.0.1:50000")
    if host not in ("127.0.0.1", "localhost", "::1", "[::1]"):
        raise ValueError(f"{text!r}: the simulator serves the loopback only (127.0.0.1, localhost, ::1)")
    return host.strip("[]"), int(port)


class TcpServer:
    """``TcpServer(device, host="127.0.0.1", port=0)``: serve ``device`` on ``host:port``
    (0: a free port). :attr:`port` is the URL a driver opens (``socket://127.0.0.1:N``);
    ``pty_path`` is None. Context manager, or :meth:`start` / :meth:`stop`."""

    def __init__(self, device, *, host: str = "127.0.0.1", port: int = 0) -> None:
        self.device = device
        self.host, self._want_port = host, int(port)
        self.port = ""
        self.pty_path: str | None = None
        self.bytes_received = 0
        self.bytes_sent = 0
        self._listener: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> "TcpServer":
        if self._thread is not None:
            return self
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        lst = socket.socket(family, socket.SOCK_STREAM)
        lst.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            lst.bind((self.host, self._want_port))
        except OSError:
            lst.close()
            raise
        lst.listen(1)
        lst.settimeout(_POLL_S)
        self._listener = lst
        host = f"[{self.host}]" if family == socket.AF_INET6 else self.host
        self.port = f"socket://{host}:{lst.getsockname()[1]}"
        self._stop.clear()
        self._thread = threading.Thread(target=self._accept_loop, name=f"tcp-amp-{self.port}", daemon=True)
        self._thread.start()
        log.info("serving %s on %s", getattr(self.device, "protocol", "?"), self.port)
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._listener is not None:
            self._listener.close()
            self._listener = None

    def __enter__(self) -> "TcpServer":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _accept_loop(self) -> None:
        assert self._listener is not None
        while not self._stop.is_set():
            try:
                conn, peer = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            log.info("%s: client %s connected", self.port, peer)
            with conn:
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                conn.settimeout(_POLL_S)
                self._serve(conn)
            if hasattr(self.device, "line_break"):
                self.device.line_break()    # a partial command dies with the connection
            log.info("%s: client %s gone", self.port, peer)

    def _serve(self, conn: socket.socket) -> None:
        """Bytes in → the device → its reply out, until the client closes or we stop. While
        no byte arrives, a device with its own clock (a wave generator) plays on every
        :data:`_IDLE_POLL_S`, as on the pty server (else the scanner, advanced by the
        simulator's clock meanwhile, would hold the old voltage through the table)."""
        poll = getattr(self.device, "poll", None)
        conn.settimeout(_SEND_TIMEOUT_S)         # a long reply (DRR?) waits for a slow reader
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([conn], [], [], _IDLE_POLL_S if poll is not None else _POLL_S)
                if not ready:
                    if poll is not None:
                        poll()
                    continue
                data = conn.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                return
            self.bytes_received += len(data)
            try:
                reply = self.device.feed(data)
            except Exception:  # noqa: BLE001 - a simulator bug must not kill the server silently
                log.exception("simulated device failed on %r", data)
                continue
            if reply:
                try:
                    conn.sendall(reply)
                except OSError:
                    return
                self.bytes_sent += len(reply)
