"""A live stack for tests, benchmarks and screenshots of ``afmctl view``: ``afmctl sim``
(a PI E-727 on a loopback TCP port — its Ethernet link carries 1 kHz of three-axis setpoints,
which no 115200-baud serial line does — the true tip and a grating image on zenoh),
``afmctl run`` (a raster at ``rate_Hz`` over ``socket://``, zenoh with access control: only
the user ``viewer`` may observe)
and ``afmctl view`` (authenticated as ``viewer``), each its own process, zenoh on loopback
with free ports."""
from __future__ import annotations

import os
import queue
import subprocess
import sys
import threading
import time
from typing import Any
from pathlib import Path

from ..testing import wait_for
from ..zenoh_api.settings import free_loopback_endpoint

SIM_TOML = """
[sim]
tick_s = 0.002
publish_rate_Hz = 500
publish_queue = 256
[zenoh.auth]
dictionary_file = "{users}"
"""

RUN_TOML = """
[scanner]
name = "{scanner}"
[scanner.calibration.x]
nm_per_V = 80.0
[scanner.calibration.y]
nm_per_V = 80.0
[scanner.calibration.z]
nm_per_V = 13.333
[amplifier]
driver = "gcs"
port = "{port}"
slew_V_per_s = 3000
[loop]
rate_Hz = {rate_Hz}
[safety]
slew_V_per_s = 3000
ramp_V_per_s = 600
watchdog_s = 0.5
[runlog]
dir = "{dir}"
fsync = false
[simulation]
enabled = false
[compensation.drift]
enabled = true
params = "physical_tube"
[trajectory]
kind = "raster"
x0_nm = 1000
y0_nm = 1000
width_nm = 6000
height_nm = 5000
lines = {lines}
line_rate_Hz = {line_rate_Hz}
repeat = {repeat}
[zenoh]
enabled = true
listen = ["{endpoint}"]
[zenoh.auth]
dictionary_file = "{users}"
[zenoh.acl]
enabled = true
observers = [{{ id = "viewer", usernames = ["viewer"] }}]
"""

VIEW_TOML = """
[zenoh]
[zenoh.auth]
user = "viewer"
password = "viewer-pw"
"""


class ChildProcess:
    """A child process whose stdout lines are collected by a reader thread; its stderr goes
    to ``<workdir>/<name>.stderr.txt``. ``env``: variables added to the environment (whose
    own ``AFMCTL_*`` are left out)."""

    def __init__(self, argv: list[str], workdir: Path, name: str, env: dict[str, str] | None = None) -> None:
        env = {**{k: v for k, v in os.environ.items() if not k.startswith("AFMCTL_")}, **(env or {})}
        env["PYTHONUNBUFFERED"] = "1"
        self.name = name
        self.err_path = workdir / f"{name}.stderr.txt"
        with open(self.err_path, "wb") as err:
            self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=err, text=True, env=env,
                                         cwd=workdir)
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._read, name=f"view-stack-{name}", daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))

    def wait_line(self, prefix: str, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.1)
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
                continue
            self.seen.append(line)
            if line.startswith(prefix):
                return line
        raise RuntimeError(f"{self.name}: no line {prefix!r} within {timeout_s} s (exit {self.proc.poll()}); "
                           f"stdout {self.seen}; stderr {self.stderr()[-2000:]}")

    def stderr(self) -> str:
        return self.err_path.read_text(errors="replace")

    def stop(self, timeout_s: float = 20.0) -> int:
        from afmctl.testing import stop_process
        return stop_process(self.proc, timeout_s)


class LiveStack:
    """``LiveStack(workdir, rate_Hz=1000, lines=..., line_rate_Hz=..., repeat=frames,
    duration_s=the simulator's lifetime)``; ``start()`` starts
    the three processes and returns when the page is served and the raster runs;
    ``url`` is the page's address; ``stop()`` ends them (view, run, sim)."""

    def __init__(self, workdir: Path, *, scanner: str = "stage1", rate_Hz: float = 1000.0, lines: int = 64,
                 line_rate_Hz: float = 2.0, repeat: int = 1, duration_s: float = 300.0) -> None:
        self.workdir = Path(workdir)
        self.scanner, self.rate_Hz, self.lines, self.line_rate_Hz = scanner, rate_Hz, lines, line_rate_Hz
        self.repeat = repeat
        self.duration_s = duration_s
        self.procs: dict[str, ChildProcess] = {}
        self.url = self.sim_endpoint = self.run_endpoint = ""

    def _py(self, *args: str) -> list[str]:
        return [sys.executable, "-m", "afmctl", *args]

    def _users(self) -> Path:
        """The user/password dictionary of the sim's and the service's zenoh sessions."""
        users = self.workdir / "users.txt"
        users.write_text("viewer:viewer-pw\n")
        return users

    def start_sim(self) -> tuple[str, str]:
        (self.workdir / "sim.toml").write_text(SIM_TOML.format(users=self._users()))
        ep = free_loopback_endpoint()
        sim = self.procs["sim"] = ChildProcess(self._py(
            "sim", "--config", str(self.workdir / "sim.toml"), "--protocol", "gcs", "--tcp", "127.0.0.1:0",
            "--zenoh-listen", ep, "--scanner", self.scanner, "--sample", "grating2d",
            "--duration", str(self.duration_s)), self.workdir, "sim")
        sim.wait_line("zenoh:", 120.0)
        link = next(s for s in sim.seen if s.startswith("link: "))[len("link: "):]
        return ep, link

    def start_run(self, port: str) -> str:
        ep = free_loopback_endpoint()
        users = self._users()
        cfg = self.workdir / "run.toml"
        cfg.write_text(RUN_TOML.format(scanner=self.scanner, port=port, rate_Hz=self.rate_Hz, dir=self.workdir,
                                       lines=self.lines, line_rate_Hz=self.line_rate_Hz, repeat=self.repeat,
                                       endpoint=ep, users=users))
        self.procs["run"] = ChildProcess(self._py("run", "--config", str(cfg)), self.workdir, "run")
        return ep

    def start_view(self, *endpoints: str) -> str:
        cfg = self.workdir / "view.toml"
        cfg.write_text(VIEW_TOML)
        args = ["view", "--config", str(cfg), "--http", "127.0.0.1:0", "--scanner", self.scanner]
        for ep in endpoints:
            args += ["--connect", ep]
        view = self.procs["view"] = ChildProcess(self._py(*args), self.workdir, "view")
        self.url = view.wait_line("afmctl view: http://", 120.0).split(": ", 1)[1]
        return self.url

    def start(self) -> "LiveStack":
        self.sim_endpoint, link = self.start_sim()
        self.run_endpoint = self.start_run(link)
        self.start_view(self.sim_endpoint, self.run_endpoint)
        run = self.procs["run"]
        if not wait_for(lambda: run.proc.poll() is not None or "afmctl: running" in run.stderr(), 120.0, 0.1) \
                or run.proc.poll() is not None:
            raise RuntimeError(f"afmctl run did not start (exit {run.proc.poll()}): {run.stderr()[-2000:]}")
        return self

    def stop(self) -> dict[str, int]:
        return {name: self.procs[name].stop() for name in ("view", "run", "sim") if name in self.procs}

    def __enter__(self) -> "LiveStack":
        try:
            return self.start()
        except BaseException:
            self.stop()
            raise

    def __exit__(self, *exc: object) -> None:
        self.stop()


# ---------------------------------------------------------------------------- browser
#: Debian's chromium, run headless with nothing that reaches the network
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]

#: JavaScript: pixels of a canvas within ``tol`` of an RGB colour, and all non-white ones
_COUNT_JS = """([id, rgb, tol, wFrac]) => {
  const c = document.getElementById(id), w = Math.floor(c.width * wFrac);
  const d = c.getContext("2d").getImageData(0, 0, w, c.height).data;
  let match = 0, ink = 0;
  for (let i = 0; i < d.length; i += 4) {
    if (d[i + 3] === 0) continue;
    if (d[i] < 250 || d[i + 1] < 250 || d[i + 2] < 250) ink++;
    if (Math.abs(d[i] - rgb[0]) <= tol && Math.abs(d[i + 1] - rgb[1]) <= tol && Math.abs(d[i + 2] - rgb[2]) <= tol) match++;
  }
  return {match, ink, total: d.length / 4};
}"""


class Browser:
    """Headless Chromium driven by playwright over CDP (no browser download: Debian's
    ``/usr/bin/chromium``), with an empty user-data-dir. ``with Browser(dir) as b:
    page = b.open(url)``."""

    def __init__(self, user_data_dir: Path, width: int = 1500, height: int = 1000) -> None:
        self.user_data_dir = Path(user_data_dir)
        self.viewport = {"width": width, "height": height}
        self._pw: Any = None    # playwright's handle and its browser context, while entered
        self._ctx: Any = None

    def __enter__(self) -> "Browser":
        from playwright.sync_api import sync_playwright
        if not Path(CHROMIUM).exists():
            raise RuntimeError(f"{CHROMIUM} is missing: install Debian's chromium (apt-get install chromium; "
                               ".ci/run does this in CI)")
        self.user_data_dir.mkdir(parents=True, exist_ok=True)
        self._pw = sync_playwright().start()
        try:
            self._ctx = self._pw.chromium.launch_persistent_context(
                str(self.user_data_dir), executable_path=CHROMIUM, args=CHROMIUM_FLAGS, headless=True,
                viewport=self.viewport)
        except BaseException:
            self._pw.stop()
            raise
        return self

    def open(self, url: str):
        page = self._ctx.new_page()
        page.goto(url)
        return page

    def __exit__(self, *exc: object) -> None:
        if self._ctx is not None:
            self._ctx.close()
        if self._pw is not None:
            self._pw.stop()


def canvas_pixels(page, canvas_id: str, rgb: tuple[int, int, int], tol: int = 40,
                  width_fraction: float = 1.0) -> dict[str, int]:
    """``{"match", "ink", "total"}``: pixels of canvas ``canvas_id`` (its left
    ``width_fraction``) near colour ``rgb``, pixels that are not white, all pixels."""
    return page.evaluate(_COUNT_JS, [canvas_id, list(rgb), tol, width_fraction])


def js_heap_bytes(page) -> float:
    """The page's used JS heap [bytes] after a garbage collection (CDP ``HeapProfiler`` /
    ``Performance.getMetrics``)."""
    cdp = page.context.new_cdp_session(page)
    try:
        cdp.send("HeapProfiler.collectGarbage")
        cdp.send("Performance.enable")
        metrics = {m["name"]: m["value"] for m in cdp.send("Performance.getMetrics")["metrics"]}
        return float(metrics["JSHeapUsedSize"])
    finally:
        cdp.detach()
