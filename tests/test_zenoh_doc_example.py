"""docs/ZENOH.md, "A client in Python", run as written: the page's service command
(``afmctl run --config examples/sim_zenoh.toml``, a queue-mode run) as a process and the
page's Python client as another, over real zenoh on loopback. Only the port is changed, to a
free one (the service through ``AFMCTL_ZENOH__LISTEN``, the client's text by replacing the
page's ``tcp/127.0.0.1:7447``). The client's ``start`` is accepted, its segment plays, and
the service's summary says why the watchdog tripped."""
from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from afmctl.control.runlog import RunLogReader
from afmctl.testing import stop_process, wait_for
from afmctl.zenoh_api.settings import free_loopback_endpoint

pytestmark = pytest.mark.timeout(180)

ROOT = Path(__file__).resolve().parent.parent
PAGE_ENDPOINT = "tcp/127.0.0.1:7447"


def page_blocks() -> tuple[list[str], str]:
    """The section's service command (its ``sh`` block) and client (its ``python`` block)."""
    text = (ROOT / "docs" / "ZENOH.md").read_text(encoding="utf-8")
    section = text.split("## A client in Python", 1)[1].split("\n## ", 1)[0]
    sh = re.search(r"```sh\n(.*?)```", section, re.S)
    py = re.search(r"```python\n(.*?)```", section, re.S)
    assert sh is not None and py is not None, "docs/ZENOH.md: the client section lost its sh or python block"
    command = shlex.split(sh.group(1).strip())
    assert command[0] == "afmctl", command
    assert PAGE_ENDPOINT in py.group(1)
    return command[1:], py.group(1)


def start_service(tmp_path: Path, args: list[str]) -> tuple[subprocess.Popen, str, Path]:
    """The page's command on a free loopback port (retried when another process took the
    port between choosing and binding it); returns (process, endpoint, run log path)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("AFMCTL_")}
    env["PYTHONUNBUFFERED"] = "1"
    env["AFMCTL_RUNLOG__DIR"] = str(tmp_path / "runs")
    for attempt in range(3):
        endpoint = free_loopback_endpoint()
        env["AFMCTL_ZENOH__LISTEN"] = json.dumps([endpoint])
        runlog = tmp_path / f"run{attempt}.afmlog"
        err_path = tmp_path / f"service-stderr{attempt}.txt"
        with open(tmp_path / f"service-stdout{attempt}.txt", "wb") as out, open(err_path, "wb") as err:
            proc = subprocess.Popen([sys.executable, "-m", "afmctl", *args, "--log", str(runlog)],
                                    stdout=out, stderr=err, env=env, cwd=ROOT)
        wait_for(lambda: proc.poll() is not None or b"afmctl: running" in err_path.read_bytes(), 90.0, 0.05)
        if proc.poll() is None:
            return proc, endpoint, runlog
        text = err_path.read_text(errors="replace")
        if "Address already in use" not in text or attempt == 2:
            pytest.fail(f"afmctl {' '.join(args)} exited {proc.returncode} before serving:\n{text}")
    raise AssertionError("unreachable")


def test_the_pages_client_runs_as_written_against_a_queue_mode_run(tmp_path):
    args, client = page_blocks()
    proc, endpoint, runlog = start_service(tmp_path, args)
    try:
        env = {k: v for k, v in os.environ.items() if not k.startswith("AFMCTL_")}
        done = subprocess.run([sys.executable, "-c", client.replace(PAGE_ENDPOINT, endpoint)], cwd=tmp_path,
                              env=env, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        lines = done.stdout.splitlines()
        reply = json.loads(lines[0])
        # the page: a run already in queue mode accepts the start and says so
        assert reply["ok"] is True and reply["cmd"] == "start", reply
        assert reply["result"]["state"] in ("running", "holding")
        assert "already running in queue mode" in reply["result"]["detail"]
        # the page's subscribers printed states and setpoint batch numbers while it watched
        assert {"running", "holding"} & set(lines[1:]), lines
        assert any(line.isdigit() for line in lines[1:]), lines

        # the segment played: its 100 samples at (1000, 1000, 0) nm reached the loop (after
        # the ramp from the output the run started at, which aims at the segment's first sample)
        def at_target() -> int:
            sp = RunLogReader(runlog).setpoints() if runlog.exists() else np.zeros(0, dtype=[("target_nm", "f8", 3)])
            return int(np.count_nonzero(np.all(np.isclose(sp["target_nm"], [1000.0, 1000.0, 0.0]), axis=1)))
        assert wait_for(lambda: at_target() >= 100, 30.0, 0.2)
        assert stop_process(proc, timeout_s=30.0) == 0
        summary = "\n".join(p.read_text() for p in sorted(tmp_path.glob("service-stdout*.txt")))
        # the summary says why the watchdog tripped: the queue ran empty, the output held
        line = next((x for x in summary.splitlines() if x.startswith("watchdog")), None)
        assert line is not None, summary
        assert "the queue ran empty" in line and "safety.watchdog_s = 0.1 s" in line, line
        assert "held the output" in line
    finally:
        stop_process(proc, timeout_s=5.0)
