"""A lab of scanners behind one zenoh router, as real processes, for tests and benchmarks
(docs/ZENOH.md, *A lab*): ``afmctl router`` with the lab's ACL, per scanner an
``afmctl sim`` (a PI E-727 on a loopback TCP port) and an ``afmctl run --serve`` driving it,
all clients of the router, and ``afmctl view``. The configuration files are the lab's own
(``examples/lab/``); only the ports are chosen here (free loopback ports), given on the
command line or in ``AFMCTL_*`` variables.

Also :class:`TcpRelay`: a TCP relay on loopback between two routers (two rooms), whose
link can be cut and joined again while both routers run."""
from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import threading
from pathlib import Path

from ..testing import wait_for
from ..zenoh_api.settings import free_loopback_endpoint
from .testing import ChildProcess


def _py(*args: str) -> list[str]:
    return [sys.executable, "-m", "afmctl", *args]


class LabStack:
    """``LabStack(workdir, lab_dir, scanners=("stage1", "stage2", "stage3"))``: the files of
    ``lab_dir`` (``router.toml``, ``sim<N>.toml``, ``stage<N>.toml``, ``view.toml``) run
    from ``workdir``. ``start_router()``, ``start_scanners()``, ``start_view()``;
    ``kill(name)`` SIGKILLs a process, ``stop()`` ends every one (SIGTERM) and returns the
    exit statuses. ``endpoint``: the router's."""

    def __init__(self, workdir: Path, lab_dir: Path, scanners: tuple[str, ...] = ("stage1", "stage2", "stage3")) -> None:
        self.workdir, self.lab_dir, self.scanners = Path(workdir), Path(lab_dir), scanners
        self.procs: dict[str, ChildProcess] = {}
        self.endpoint = free_loopback_endpoint()
        self.url = ""

    def _number(self, scanner: str) -> str:
        return scanner.removeprefix("stage")

    def start_router(self, timeout_s: float = 60.0) -> ChildProcess:
        """(Re)start the router on :attr:`endpoint` with ``router.toml`` (its ACL and users)."""
        router = self.procs["router"] = ChildProcess(_py(
            "router", "--config", str(self.lab_dir / "router.toml"), "--listen", self.endpoint),
            self.workdir, "router")
        router.wait_line("afmctl router: listening", timeout_s)
        return router

    def start_scanners(self, names: tuple[str, ...] | None = None, timeout_s: float = 120.0) -> None:
        """``afmctl sim`` and ``afmctl run --serve`` of each scanner (default: all), clients
        of the router, started side by side; returns once every run serves (idle, its
        presence declared)."""
        names = names or self.scanners
        sims = {name: self._start_sim(name) for name in names}
        for name, sim in sims.items():
            sim.wait_line("zenoh:", timeout_s)
            link = next(s for s in sim.seen if s.startswith("link: "))[len("link: "):]
            self._start_run(name, link)
        for name in names:
            run = self.procs[f"run-{name}"]
            if not wait_for(lambda: run.proc.poll() is not None or "afmctl: serving" in run.stderr(), timeout_s, 0.1) \
                    or run.proc.poll() is not None:
                raise RuntimeError(f"afmctl run {name} did not start (exit {run.proc.poll()}): {run.stderr()[-2000:]}")

    def _start_sim(self, name: str) -> ChildProcess:
        sim = self.procs[f"sim-{name}"] = ChildProcess(_py(
            "sim", "--config", str(self.lab_dir / f"sim{self._number(name)}.toml"), "--protocol", "gcs",
            "--tcp", "127.0.0.1:0", "--zenoh-connect", self.endpoint), self.workdir, f"sim-{name}")
        return sim

    def _start_run(self, name: str, link: str) -> ChildProcess:
        env = {"AFMCTL_ZENOH__CONNECT": f'["{self.endpoint}"]', "AFMCTL_RUNLOG__DIR": str(self.workdir / f"runs-{name}")}
        run = self.procs[f"run-{name}"] = ChildProcess(_py(
            "run", "--config", str(self.lab_dir / f"stage{self._number(name)}.toml"), "--port", link, "--serve",
            "--quiet"), self.workdir, f"run-{name}", env=env)
        return run

    def run_logs(self, name: str) -> list[Path]:
        """The run logs scanner ``name``'s service has written, oldest first."""
        return sorted((self.workdir / f"runs-{name}").glob("*.afmlog"))

    def start_view(self, timeout_s: float = 120.0) -> str:
        view = self.procs["view"] = ChildProcess(_py(
            "view", "--config", str(self.lab_dir / "view.toml"), "--connect", self.endpoint,
            "--http", "127.0.0.1:0"), self.workdir, "view")
        self.url = view.wait_line("afmctl view: http://", timeout_s).split(": ", 1)[1]
        return self.url

    def kill(self, name: str) -> None:
        """SIGKILL process ``name`` (``router``, ``sim-stage1``, ``run-stage1``, ``view``)."""
        proc = self.procs[name].proc
        proc.kill()
        proc.wait(10.0)

    def stop(self) -> dict[str, int]:
        """SIGTERM every process still running (the view and the runs first, the router
        last); the exit status of each (negative: killed by that signal)."""
        order = sorted(self.procs, key=lambda k: (k == "router", k.startswith("sim-")))
        return {name: self.procs[name].stop() for name in order}

    def __enter__(self) -> "LabStack":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class TcpRelay:
    """Relays TCP connections from a loopback port to ``target`` (``HOST:PORT``), so that
    a link between two routers can be cut (:meth:`cut`: every relayed connection closed,
    new ones refused) and joined again (:meth:`join`) while both routers keep running.
    ``endpoint``: ``tcp/127.0.0.1:PORT`` to connect to instead of the target."""

    def __init__(self, target: str) -> None:
        host, port = target.rsplit(":", 1)
        self.target = (host, int(port))
        self.endpoint = free_loopback_endpoint()
        self.port = int(self.endpoint.rsplit(":", 1)[1])
        self._socks: list[socket.socket] = []
        self._lock = threading.Lock()
        self._server: socket.socket | None = None
        self._threads: list[threading.Thread] = []
        self.join()

    def join(self) -> None:
        """Accept and relay connections (again)."""
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind(("127.0.0.1", self.port))
        server.listen(8)
        self._server = server
        self._spawn(self._accept, server)

    def _spawn(self, target, *args) -> None:
        t = threading.Thread(target=target, args=args, name="lab-relay", daemon=True)
        t.start()
        self._threads.append(t)

    def _accept(self, server: socket.socket) -> None:
        while True:
            try:
                inside, _ = server.accept()
                outside = socket.create_connection(self.target, timeout=5.0)
                outside.settimeout(None)
            except OSError:
                return
            with self._lock:
                self._socks += [inside, outside]
            self._spawn(self._pump, inside, outside)
            self._spawn(self._pump, outside, inside)

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := src.recv(65536):
                dst.sendall(data)
        for s in (src, dst):
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)

    def cut(self) -> None:
        """Close the listening socket and every relayed connection (as a cable pulled)."""
        if self._server is not None:
            with contextlib.suppress(OSError):
                self._server.shutdown(socket.SHUT_RDWR)
            self._server.close()
            self._server = None
        with self._lock:
            socks, self._socks = self._socks, []
        for s in socks:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            s.close()
        for t in self._threads:
            t.join(5.0)
        self._threads = [t for t in self._threads if t.is_alive()]

    def close(self) -> None:
        self.cut()

    def __enter__(self) -> "TcpRelay":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def make_certificates(directory: Path, names: tuple[str, ...]) -> None:
    """A throw-away CA (``ca.pem``) and, per name, ``<name>.pem`` / ``<name>.key`` with that
    common name, valid for localhost and 127.0.0.1, for servers and clients (TLS / mutual
    TLS tests; the ``openssl`` command line)."""
    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], check=True, capture_output=True, cwd=directory)
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    run("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.pem", "-days", "2", "-subj", "/CN=afmctl-test-ca",
        "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign")
    for name in names:
        (directory / f"{name}.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
                                               "keyUsage=digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n")
        run("req", *ec, "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={name}")
        run("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", f"{name}.pem", "-days", "2", "-extfile", f"{name}.ext")
