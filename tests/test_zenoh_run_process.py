"""Issue 8 acceptance, against the real service process: ``python -m afmctl run`` with the
in-process simulated scanner (CAN virtual bus), ``trajectory.kind = "queue"``, the drift
predictor fed by temperatures from zenoh, and ``[zenoh]`` on loopback with access control
(the test client authenticates as an operator). A real zenoh client session publishes a
trajectory segment and a rising temperature stream, watches setpoint/drift/status, asks
``cmd status`` and ``cmd stop``; the process exits 0 and its run log holds exactly the
samples the client received."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from afmctl.zenoh_api.messages import CmdRequest, SegmentMsg, TemperatureMsg, decode_setpoints
from afmctl.control.runlog import RunLogReader
from afmctl.testing import wait_for, stop_process
from afmctl.zenoh_api.settings import UserPasswordSettings, ZenohSettings, free_loopback_endpoint

import zenoh
pytestmark = pytest.mark.timeout(180)

SCANNER = "zrun"
N_SEG = 4000              # samples of the segment at dt 1 ms: 4 s of motion
T0_C = 22.0               # the configured (and first streamed) temperature [°C]
T_RISE_C = [22.5 + 0.5 * i for i in range(10)]   # then 22.5 … 27.0 °C, one reading per 0.1 s

CONFIG = """
[scanner]
name = "{scanner}"
axes = ["x", "y", "z"]
[scanner.calibration.x]
nm_per_V = 80.0
[scanner.calibration.y]
nm_per_V = 80.0
[amplifier]
driver = "can"
port = "virtual:{channel}"
[loop]
rate_Hz = 1000
[compensation.drift]
enabled = true
params = "physical_tube"
[compensation.temperature]
source = "external"
T_C = {T0}
[safety]
ramp_V_per_s = 1000.0
watchdog_s = 0.1
on_stall = "hold"
on_finish = "safe"
[trajectory]
kind = "queue"
[runlog]
dir = "{runs}"
[simulation]
enabled = true
[zenoh]
enabled = true
listen = ["{endpoint}"]
[zenoh.auth]
dictionary_file = "{users}"
[zenoh.acl]
enabled = true
operators = [{{ id = "scripts", usernames = ["op"] }}]
"""


class Client:
    """An operator's zenoh session (scouting off, connects to the service's endpoint)."""

    def __init__(self, endpoint: str) -> None:
        settings = ZenohSettings(listen=[], connect=[endpoint],
                                 auth=UserPasswordSettings(user="op", password="op-pw"))
        self.session = zenoh.open(settings.to_zenoh_config())
        self.lock = threading.Lock()
        self.batches: list[tuple[int, np.ndarray]] = []
        self.drift: list[dict] = []
        self.status: list[dict] = []
        self.seq = {"cmd": 0, "trajectory": 0, "temperature": 0}
        key = f"afm/{SCANNER}"
        self.subs = [
            self.session.declare_subscriber(f"{key}/setpoint", lambda s: self._add(self.batches, decode_setpoints(
                s.payload.to_bytes()))),
            self.session.declare_subscriber(f"{key}/drift", lambda s: self._add(self.drift, json.loads(
                s.payload.to_bytes()))),
            self.session.declare_subscriber(f"{key}/status", lambda s: self._add(self.status, json.loads(
                s.payload.to_bytes()))),
        ]

    def _add(self, where: list, item) -> None:
        with self.lock:
            where.append(item)

    def samples(self) -> int:
        with self.lock:
            return sum(len(b) for _, b in self.batches)

    def cmd(self, name: str, timeout: float = 5.0) -> list[dict]:
        req = CmdRequest(seq=self.seq["cmd"], cmd=name, args={})
        self.seq["cmd"] += 1
        replies = self.session.get(f"afm/{SCANNER}/cmd", payload=req.to_json_bytes(), timeout=timeout)
        return [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]

    def put(self, leaf: str, msg) -> None:
        self.session.put(f"afm/{SCANNER}/{leaf}", msg.to_json_bytes())

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


def _start_service(tmp_path: Path) -> tuple[subprocess.Popen, str, Path]:
    """Start `afmctl run` on a free loopback port; retry when another process took the
    port between choosing and binding it. Returns (process, endpoint, run log path)."""
    users = tmp_path / "users.txt"
    users.write_text("op:op-pw\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("AFMCTL_")}
    env["PYTHONUNBUFFERED"] = "1"
    for attempt in range(3):
        endpoint = free_loopback_endpoint()
        cfg = tmp_path / f"service{attempt}.toml"
        cfg.write_text(CONFIG.format(scanner=SCANNER, channel=f"zrun-{os.getpid()}-{attempt}", T0=T0_C,
                                     runs=tmp_path / "runs", endpoint=endpoint, users=users))
        runlog = tmp_path / f"run{attempt}.afmlog"
        out = open(tmp_path / f"stdout{attempt}.txt", "wb")
        err = open(tmp_path / f"stderr{attempt}.txt", "wb")
        proc = subprocess.Popen([sys.executable, "-m", "afmctl", "run", "--config", str(cfg), "--log", str(runlog)],
                                stdout=out, stderr=err, env=env, cwd=tmp_path)
        out.close()
        err.close()
        # up once it says it runs (the bridge is declared before the controller starts)
        wait_for(lambda: proc.poll() is not None or b"afmctl: running" in (tmp_path / f"stderr{attempt}.txt")
                 .read_bytes(), 90.0, 0.05)
        if proc.poll() is None:
            return proc, endpoint, runlog
        text = (tmp_path / f"stderr{attempt}.txt").read_text(errors="replace")
        if "Address already in use" not in text or attempt == 2:   # not a port race: say what it said
            pytest.fail(f"afmctl run exited {proc.returncode} before serving:\n{text}")
    raise AssertionError("unreachable")


def test_run_process_serves_trajectory_and_temperature_over_zenoh(tmp_path):
    threads_before = set(threading.enumerate())
    proc, endpoint, runlog = _start_service(tmp_path)
    client = None
    try:
        client = Client(endpoint)
        # the service's status (published at least every second) reaches us: our
        # subscriptions are declared on the service's side, the ACL lets us observe
        assert wait_for(lambda: client.status, 30.0), "no status from the service"
        replies: list[dict] = []
        assert wait_for(lambda: bool(replies.extend(client.cmd("status")) or replies), 30.0), \
            "cmd status never answered (ACL refused the operator?)"
        assert replies[0]["ok"] and replies[0]["result"]["state"] in ("running", "holding"), replies[0]
        assert replies[0]["result"]["stats"]["samples"] == 0     # queue mode: nothing queued yet

        client.put("temperature", TemperatureMsg(seq=0, t_s=0.0, T_C=T0_C))
        client.seq["temperature"] = 1
        x = np.linspace(1000.0, 5000.0, N_SEG)
        pos = np.column_stack([x, np.full(N_SEG, 2000.0), np.zeros(N_SEG)])
        client.put("trajectory", SegmentMsg(seq=0, dt_s=1e-3, positions_nm=pos.tolist()))

        # drift estimates at the constant starting temperature first, then the rise
        assert wait_for(lambda: len(client.drift) >= 5, 30.0), (
            f"no drift estimates while the segment runs; last status {client.status[-1:]}; the service said: "
            + "".join(p.read_text(errors="replace")[-3000:] for p in sorted(tmp_path.glob("stderr*.txt"))))
        for T in T_RISE_C:
            client.put("temperature", TemperatureMsg(seq=client.seq["temperature"], t_s=0.1 * client.seq[
                "temperature"], T_C=T))
            client.seq["temperature"] += 1
            time.sleep(0.1)

        # the segment ends, the queue runs dry: the watchdog holds the output
        def segment_done() -> bool:
            r = client.cmd("status")
            return bool(r) and r[0]["result"]["state"] == "holding" and r[0]["result"]["stats"]["samples"] >= N_SEG
        assert wait_for(segment_done, 60.0, 0.2), f"segment never finished: {client.status[-1]}"
        status = client.cmd("status")[0]
        assert status["ok"]
        stats = status["result"]["stats"]
        for key in ("lateness_p50_s", "lateness_p99_s", "lateness_max_s", "missed_deadlines", "samples"):
            assert key in stats, key
        assert 0.0 <= stats["lateness_p50_s"] <= stats["lateness_p99_s"] <= stats["lateness_max_s"]
        assert stats["lateness_max_s"] > 0.0
        assert stats["errors"] == 0 and stats["dropped_records"] == 0
        assert stats["bridge"]["rejected"] == 0 and stats["bridge"]["seq_gaps_in"] == 0
        assert stats["bridge"]["accepted"] >= 1 + 1 + len(T_RISE_C)   # segment, temperatures, queries
        n_loop = stats["samples"]
        # holding records nothing: every sample the loop made is published, none dropped
        assert wait_for(lambda: client.samples() >= n_loop, 30.0), (client.samples(), n_loop)
        with client.lock:
            batches = list(client.batches)
            drift = list(client.drift)
        assert [s for s, _ in batches] == list(range(len(batches))), "setpoint batch sequence gap"
        rec = np.concatenate([b for _, b in batches])
        assert np.array_equal(rec["seq"].astype(np.int64), np.arange(len(rec))), "sample sequence gap"
        assert len(rec) == n_loop
        # the whole segment went through: every target sample of it, in order (plus the
        # ramp from the safe output to its first sample, which repeats the first target)
        tx = rec["target_nm"][:, 0]
        first = int(np.argmax(tx > x[0]))
        assert np.allclose(tx[first - 1:first - 1 + N_SEG], x) and np.all(tx[:first] == x[0])
        assert np.all(rec["target_nm"][:, 1] == 2000.0)

        # drift estimates follow the temperature: flat at the starting temperature, then
        # growing as it rises; each names the temperature it was computed with
        assert [d["seq"] for d in drift] == list(range(len(drift))), "drift sequence gap"
        Ts = np.array([d["T_C"] for d in drift])
        dz = np.array([d["drift_nm"][2] for d in drift])
        assert np.all(np.diff(Ts) >= 0) and Ts[0] == T0_C and Ts[-1] == T_RISE_C[-1], Ts
        # at the starting temperature only the heat of the drive voltages moves it (µnm)
        flat = dz[Ts == T0_C]
        assert len(flat) >= 5 and np.all(np.abs(flat) < 1e-3), flat
        warm = dz[Ts == T_RISE_C[-1]]
        assert len(warm) >= 1 and np.abs(warm).max() > 0.05, (dz, Ts)
        assert np.abs(warm).max() > 100 * np.abs(flat).max()
        assert np.all(np.diff(dz[Ts > T0_C]) > 0), "drift does not grow while the temperature rises"
        # and the drift the loop subtracted is the drift published: target - corrected
        by_seq = {int(r["seq"]): r for r in rec}
        for d in drift:
            r = by_seq[d["inputs"]["seq"]]
            assert np.allclose(r["target_nm"] - r["corrected_nm"], d["drift_nm"], atol=1e-9)

        stop = client.cmd("stop")
        assert stop and stop[0]["ok"], stop
        rc = proc.wait(60.0)
        err = [p.read_text(errors="replace") for p in sorted(tmp_path.glob("stderr*.txt"))][-1]
        assert rc == 0, f"afmctl run exited {rc}:\n{err}"
        summary = [p.read_text() for p in sorted(tmp_path.glob("stdout*.txt"))][-1]
        assert "state             stopped" in summary, summary

        log = RunLogReader(runlog)
        sp = log.setpoints()
        assert not log.torn and log.summary()["seq_gaps"] == 0
        # the stop ramp (to the safe 0 V) happened after our status query: the client
        # receives those samples too, every one of them before the service closes
        assert len(sp) > n_loop
        assert wait_for(lambda: client.samples() >= len(sp), 10.0), (client.samples(), len(sp))
        with client.lock:
            batches = list(client.batches)
        assert [s for s, _ in batches] == list(range(len(batches))), "setpoint batch sequence gap"
        rec = np.concatenate([b for _, b in batches])
        assert len(rec) == len(sp)          # the run log holds exactly what the client received
        for field in ("seq", "t_s", "target_nm", "corrected_nm", "u_V"):
            assert np.array_equal(rec[field], sp[field]), field
        assert np.allclose(sp["u_V"][-1], 0.0)            # ended at the safe value
        assert log.meta()["scanner"] == SCANNER
    finally:
        if client is not None:
            client.close()
        stop_process(proc, timeout_s=5.0)     # still running: the test failed; its stacks, then kill
    assert wait_for(lambda: set(threading.enumerate()) <= threads_before, 5.0), \
        f"leaked threads: {set(threading.enumerate()) - threads_before}"
