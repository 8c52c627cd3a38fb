"""The processes of the soak (benchmarks/soak.py) and the loopback TCP link between them.

* :class:`TcpProxy` — a loopback TCP forwarder between the driver (``socket://``) and the
  simulated amplifier; :meth:`TcpProxy.drop` cuts every open connection (the link lost) and
  :meth:`TcpProxy.retarget` points it at a restarted amplifier;
* :class:`Amp` — ``afmctl sim --protocol gcs --tcp 127.0.0.1:0 --record SEG.csv`` (the
  simulated E-727 in its own process); every start writes a new record segment;
* :class:`Leg` — ``afmctl run`` started again and again by a thread, with the RSS [kB] of
  the run process sampled every ``rss_every_s``;
* :class:`Peer` / :class:`Viewer` — a zenoh subscriber (benchmarks/soak_peer.py) and
  ``afmctl view``, both on loopback.
"""
from __future__ import annotations

import json
import os
import selectors
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

AFMCTL = [sys.executable, "-m", "afmctl"]
HERE = Path(__file__).resolve().parent


def free_port() -> int:
    """A free loopback TCP port (for the zenoh listeners)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def read_line_starting(proc: subprocess.Popen, prefix: str, timeout_s: float = 60.0) -> str:
    """The first stdout line of ``proc`` that starts with ``prefix`` (a process that exits or
    stays silent for ``timeout_s`` is an error)."""
    box: list[str] = []

    def _read() -> None:
        for line in proc.stdout:
            if line.startswith(prefix):
                box.append(line.strip())
                return

    t = threading.Thread(target=_read, daemon=True)
    t.start()
    t.join(timeout_s)
    if not box:
        raise RuntimeError(f"{proc.args[3:5]} printed no '{prefix}' line within {timeout_s:g} s (exit {proc.poll()})")
    return box[0]


def drain(stream, sink: list[str] | None = None, keep: int = 200) -> threading.Thread:
    """Read ``stream`` to its end on a thread (so a child never blocks on a full pipe);
    the last ``keep`` lines go to ``sink``."""
    def _run() -> None:
        for line in stream:
            if sink is not None:
                sink.append(line.rstrip("\n"))
                del sink[:-keep]
    t = threading.Thread(target=_run, daemon=True)
    t.start()
    return t


def stop_process(proc: subprocess.Popen | None, timeout_s: float = 10.0) -> int | None:
    """SIGTERM, then SIGKILL after ``timeout_s``; the exit status."""
    if proc is None:
        return None
    if proc.poll() is None:
        proc.send_signal(signal.SIGCONT)      # a stopped process cannot act on SIGTERM
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


class TcpProxy:
    """Forward ``127.0.0.1:port`` to ``127.0.0.1:target`` (both loopback), byte for byte."""

    def __init__(self, target: int | None = None) -> None:
        self._lsock = socket.create_server(("127.0.0.1", 0))
        self._lsock.setblocking(False)
        self.port = int(self._lsock.getsockname()[1])
        self.target = target
        self.drops = 0
        self._drop = threading.Event()
        self._stop = threading.Event()
        self._peer: dict[socket.socket, socket.socket] = {}
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._lsock, selectors.EVENT_READ, None)
        self._thread = threading.Thread(target=self._serve, name="soak-proxy", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    def retarget(self, target: int | None) -> None:
        """New connections go to ``target`` (None: refused — the amplifier is gone)."""
        self.target = target

    def drop(self) -> None:
        """Cut every open connection (the driver sees its link closed)."""
        self._drop.set()

    def _close_pair(self, s: socket.socket) -> None:
        other = self._peer.pop(s, None)
        for x in (s, other):
            if x is None:
                continue
            self._peer.pop(x, None)
            try:
                self._sel.unregister(x)
            except (KeyError, ValueError):
                pass
            x.close()

    def _accept(self) -> None:
        try:
            client, _ = self._lsock.accept()
        except OSError:
            return
        try:
            if self.target is None:
                raise OSError("no amplifier")
            up = socket.create_connection(("127.0.0.1", self.target), timeout=2.0)
        except OSError:
            client.close()
            return
        for s in (client, up):
            s.setblocking(True)
            s.settimeout(5.0)
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._peer[client], self._peer[up] = up, client
        self._sel.register(client, selectors.EVENT_READ, up)
        self._sel.register(up, selectors.EVENT_READ, client)

    def _serve(self) -> None:
        while not self._stop.is_set():
            if self._drop.is_set():
                self._drop.clear()
                for s in list(self._peer):
                    self._close_pair(s)
                self.drops += 1
            for key, _ in self._sel.select(0.05):
                if key.data is None:
                    self._accept()
                    continue
                src, dst = key.fileobj, key.data
                try:
                    data = src.recv(1 << 16)
                    if data:
                        dst.sendall(data)
                except OSError:
                    data = b""
                if not data:
                    self._close_pair(src)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        for s in list(self._peer):
            self._close_pair(s)
        self._sel.close()
        self._lsock.close()


class Amp:
    """The simulated E-727 (``afmctl sim --protocol gcs``) behind a :class:`TcpProxy`."""

    def __init__(self, work: Path, name: str, proxy: TcpProxy) -> None:
        self.work, self.name, self.proxy = work, name, proxy
        self.proc: subprocess.Popen | None = None
        self.segments: list[Path] = []
        self.starts_wall: list[float] = []     # wall time of each segment's clock 0 (when it printed its link)
        self.up = threading.Event()

    def start(self) -> None:
        path = self.work / f"{self.name}-amp{len(self.segments):03d}.csv"
        self.proc = subprocess.Popen(AFMCTL + ["sim", "--protocol", "gcs", "--tcp", "127.0.0.1:0",
                                               "--record", str(path)],
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        link = read_line_starting(self.proc, "link:")
        self.starts_wall.append(time.time())
        drain(self.proc.stdout)
        self.segments.append(path)
        self.proxy.retarget(int(link.rsplit(":", 1)[1]))
        self.up.set()

    def kill(self) -> None:
        """SIGKILL: the amplifier gone at once (its record loses the last unflushed ≤ 0.5 s)."""
        self.up.clear()
        self.proxy.retarget(None)
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()

    def record_bytes(self) -> int:
        """Size of the present record segment (grows while setpoints arrive; flushed every 0.5 s)."""
        try:
            return self.segments[-1].stat().st_size if self.segments else 0
        except OSError:
            return 0

    def close(self) -> None:
        self.up.clear()
        stop_process(self.proc)


@dataclass
class RunRecord:
    """One ``afmctl run`` process of a leg."""
    index: int
    log: Path
    pid: int
    start_wall: float
    end_wall: float | None = None
    rc: int | None = None
    summary: dict[str, Any] | None = None
    rss_kB: list[tuple[float, int]] = field(default_factory=list)
    stderr_tail: list[str] = field(default_factory=list)
    stop_s: float | None = None         # SIGTERM at the end of the soak -> exit [s]
    killed: bool = False                # did not end after SIGTERM: SIGKILLed


def rss_kB(pid: int) -> int | None:
    """VmRSS of a process [kB] (None once it is gone)."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


class Leg:
    """``afmctl run --config CFG`` again and again (a new process whenever one ends) while the
    soak lasts; each waits for its amplifier to be up before it starts."""

    def __init__(self, name: str, config: Path, work: Path, amp: Amp, seconds: float,
                 rss_every_s: float = 2.0) -> None:
        self.name, self.config, self.work, self.amp = name, config, work, amp
        self.seconds, self.rss_every_s = seconds, rss_every_s
        self.runs: list[RunRecord] = []
        self.proc: subprocess.Popen | None = None
        self.stopping = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=f"soak-leg-{name}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    @property
    def current(self) -> RunRecord | None:
        return self.runs[-1] if self.runs and self.runs[-1].rc is None else None

    def _loop(self) -> None:
        while not self.stopping.is_set():
            if not self.amp.up.wait(0.2):
                continue
            self._one_run()
            self.stopping.wait(0.5)

    def _one_run(self) -> None:
        log = self.work / f"{self.name}-run{len(self.runs):03d}.afmlog"
        cmd = AFMCTL + ["run", "--config", str(self.config), "--log", str(log), "--json", "--quiet",
                        "--seconds", f"{self.seconds:g}"]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        rec = RunRecord(len(self.runs), log, proc.pid, time.time())
        self.proc = proc
        self.runs.append(rec)
        err = drain(proc.stderr, rec.stderr_tail)
        out: list[str] = []
        out_t = drain(proc.stdout, out, keep=10_000)
        while proc.poll() is None:
            kb = rss_kB(proc.pid)
            if kb is not None:
                rec.rss_kB.append((time.time(), kb))
            try:
                proc.wait(self.rss_every_s)
            except subprocess.TimeoutExpired:
                pass
        out_t.join(5)
        err.join(5)
        rec.end_wall, rec.rc = time.time(), proc.returncode
        try:
            rec.summary = json.loads("\n".join(out)) if out else None
        except json.JSONDecodeError:
            rec.summary = None

    def stop(self, timeout_s: float) -> None:
        """End the leg: SIGTERM to the present run; it must exit within ``timeout_s``."""
        self.stopping.set()
        proc, rec = self.proc, self.current
        if proc is not None and proc.poll() is None and rec is not None:
            t0 = time.monotonic()
            proc.terminate()
            try:
                proc.wait(timeout_s)
                rec.stop_s = time.monotonic() - t0
            except subprocess.TimeoutExpired:
                rec.killed = True
                proc.kill()
                proc.wait()
        self._thread.join(timeout_s + 10)


class Peer:
    """A zenoh subscriber process (benchmarks/soak_peer.py) connected to the runs' endpoints."""

    def __init__(self, endpoints: list[str]) -> None:
        self.endpoints = endpoints
        self.proc: subprocess.Popen | None = None
        self.messages = 0
        self.starts = 0

    def start(self) -> None:
        self.proc = subprocess.Popen([sys.executable, str(HERE / "soak_peer.py"), *self.endpoints],
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        self.messages = 0
        self.starts += 1
        proc = self.proc

        def _read() -> None:
            for line in proc.stdout:
                if line.startswith("messages ") and proc is self.proc:
                    self.messages = int(line.split()[1])
        threading.Thread(target=_read, daemon=True).start()

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()

    def close(self) -> None:
        stop_process(self.proc)


class Viewer:
    """``afmctl view`` on loopback, connected to the runs' zenoh endpoints."""

    def __init__(self, endpoints: list[str]) -> None:
        cmd = AFMCTL + ["view", "--http", "127.0.0.1:0"]
        for e in endpoints:
            cmd += ["--connect", e]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        self.url = read_line_starting(self.proc, "afmctl view: http").split()[-1]
        drain(self.proc.stdout)

    def sigstop(self) -> None:
        os.kill(self.proc.pid, signal.SIGSTOP)

    def sigcont(self) -> None:
        os.kill(self.proc.pid, signal.SIGCONT)

    def serves(self, timeout_s: float = 10.0) -> bool:
        """The page answers (HTTP 200) within ``timeout_s``."""
        try:
            with urllib.request.urlopen(self.url, timeout=timeout_s) as r:
                return r.status == 200
        except OSError:
            return False

    def close(self) -> None:
        stop_process(self.proc)
