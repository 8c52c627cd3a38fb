"""The zenoh API in its own process (afmctl.zenoh_api.process): same keys, payloads and ACL as
the in-process bridge, over a real zenoh session on loopback, with the real Controller."""
from __future__ import annotations

import json
import os
import socket
import time

import numpy as np
import pytest
import zenoh

from afmctl.config import load_config
from afmctl.errors import AfmctlError
from afmctl.control.controller import Controller
from afmctl.zenoh_api.messages import CmdRequest, SegmentMsg, decode_setpoints
from afmctl.simulation.link import RecordingAmplifier
from afmctl.testing import assert_no_threads_left, wait_for
from afmctl.zenoh_api.settings import AclSettings, AclSubject, UserPasswordSettings, ZenohSettings, loopback_pair
from afmctl.zenoh_api.process import ZenohBridgeProcess

CONFIG = """
[scanner]
name = "s1"
[simulation]
enabled = true
[loop]
rate_Hz = 1000
[trajectory]
kind = "queue"
[runlog]
dir = "{dir}"
fsync = false
"""


class Client:
    def __init__(self, settings: ZenohSettings, slow_s: float = 0.0) -> None:
        self.session = zenoh.open(settings.to_zenoh_config())
        self.batches: list = []
        self.status: list[dict] = []
        self.closed = False

        def on_setpoint(s) -> None:
            self.batches.append(decode_setpoints(s.payload.to_bytes()))
            if slow_s and not self.closed:     # once closed, drain what zenoh still queued at once
                time.sleep(slow_s)
        self.subs = [self.session.declare_subscriber("afm/s1/setpoint", on_setpoint),
                     self.session.declare_subscriber("afm/s1/status",
                                                     lambda s: self.status.append(json.loads(s.payload.to_bytes())))]

    def cmd(self, name: str, **args) -> list[dict]:
        replies = self.session.get("afm/s1/cmd", payload=CmdRequest(cmd=name, args=args).to_json_bytes(), timeout=5.0)
        return [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]

    def close(self) -> None:
        self.closed = True   # zenoh's callback thread is not a daemon: the interpreter waits for it
        for s in self.subs:
            s.undeclare()
        self.session.close()


@pytest.fixture
def service(tmp_path):
    users = tmp_path / "users.txt"
    users.write_text("op:op-pw\nviewer:viewer-pw\n")
    server = ZenohSettings(auth=UserPasswordSettings(dictionary_file=users),
                           acl=AclSettings(enabled=True, operators=[AclSubject(id="operators", usernames=["op"])]))
    srv, cli = loopback_pair(server)
    cfg = load_config(text=CONFIG.format(dir=tmp_path / "runs"))
    ctl = Controller(cfg, RecordingAmplifier())
    bridge = ZenohBridgeProcess(ctl, srv, "s1", status_period_s=0.2)
    clients: list[Client] = []

    def client(user: str, slow_s: float = 0.0) -> Client:
        c = Client(cli.model_copy(update={"auth": UserPasswordSettings(user=user, password=f"{user}-pw")}), slow_s)
        clients.append(c)
        assert wait_for(lambda: c.status, 10), "no status from the bridge process"
        return c
    try:
        yield cfg, ctl, bridge, client
    finally:
        for c in clients:
            c.close()
        ctl.stop()
        ctl.close()
        bridge.close()
    assert not bridge._proc.is_alive()
    assert_no_threads_left("afmctl-zenoh")


def _segment(seq: int, n: int = 300) -> bytes:
    pos = np.zeros((n, 3))
    pos[:, 0] = np.linspace(1000.0, 4000.0, n)
    pos[:, 1] = 2000.0
    return SegmentMsg(seq=seq, dt_s=1e-3, positions_nm=pos.tolist()).to_json_bytes()


def test_commands_trajectories_and_every_batch_through_the_child(service):
    cfg, ctl, bridge, client = service
    op, viewer = client("op"), client("viewer")
    assert viewer.cmd("start") == []                 # ACL: a viewer cannot command
    reply = op.cmd("start")
    assert reply and reply[0]["ok"] and reply[0]["result"]["state"] == "running", reply
    for k in range(3):
        op.session.put("afm/s1/trajectory", _segment(k))
    assert wait_for(lambda: ctl.stats()["samples"] >= 900 and ctl.state.value == "holding", 15)
    status = op.cmd("status")[0]["result"]
    assert status["state"] == "holding" and status["stats"]["samples"] >= 900
    assert status["stats"]["bridge"]["accepted"] >= 4
    n = ctl.stats()["samples"]
    for c in (op, viewer):
        assert wait_for(lambda: sum(len(b) for _, b in c.batches) >= n, 10)
        assert [s for s, _ in c.batches] == list(range(len(c.batches)))      # no batch gap
        seqs = np.concatenate([b["seq"] for _, b in c.batches]).astype(np.int64)
        assert np.array_equal(seqs, np.arange(seqs[0], seqs[0] + len(seqs)))
    # a call the controller refuses: its one-line message comes back in the reply and on status
    before = op.status[-1]["rejected"]
    reply = op.cmd("drift-measurement", measured_drift_nm=[1.0, 2.0, None], std_nm=0.5)[0]
    assert not reply["ok"] and "the Kalman filter is off" in reply["error"] and "\n" not in reply["error"]
    assert wait_for(lambda: op.status[-1]["rejected"] > before, 10)
    err = op.status[-1]["errors"][-1]
    assert err["source"] == "cmd" and "the Kalman filter is off" in err["message"], err
    assert op.cmd("estop")[0]["ok"]
    assert ctl.wait(10) and ctl.state.value == "stopped"


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs")
def test_the_zenoh_process_keeps_off_the_loops_cpu(tmp_path):
    loop_cpu = max(os.sched_getaffinity(0))
    text = CONFIG.format(dir=tmp_path / "runs").replace("rate_Hz = 1000\n", f"rate_Hz = 1000\ncpu = {loop_cpu}\n")
    cfg = load_config(text=text)
    ctl = Controller(cfg, RecordingAmplifier())
    srv, _ = loopback_pair()
    bridge = ZenohBridgeProcess(ctl, srv, "s1")
    try:
        assert ctl.cpu_plan.loop_cpu == loop_cpu
        assert os.sched_getaffinity(bridge.pid) == set(ctl.cpu_plan.others)
        assert loop_cpu not in os.sched_getaffinity(bridge.pid)
    finally:
        ctl.close()
        bridge.close()


def test_slow_subscriber_does_not_hold_the_run(service):
    """A subscriber that takes 0.3 s per batch: the run plays its segments and ends, the
    run log keeps every record; what zenoh could not take is dropped and counted."""
    cfg, ctl, bridge, client = service
    op = client("op")
    slow = client("viewer", slow_s=0.3)
    assert op.cmd("start")[0]["ok"]
    for k in range(10):
        op.session.put("afm/s1/trajectory", _segment(k, 400))
    assert wait_for(lambda: ctl.stats()["samples"] >= 4000 and ctl.state.value == "holding", 30)
    assert op.cmd("stop")[0]["ok"]
    assert ctl.wait(10)
    assert ctl.stats()["dropped_records"] == 0
    from afmctl.control.runlog import RunLogReader
    ctl.close()
    sp = RunLogReader(ctl.runlog_path).setpoints()
    assert len(sp) == ctl.stats()["samples"]
    assert len(slow.batches) < len(op.batches) or slow.batches   # slow, yet alive
    assert "dropped_to_child" in op.status[-1]["stats"]["bridge"]   # what zenoh could not take is counted


def test_a_bridge_that_cannot_start_is_one_afmctl_error(tmp_path):
    cfg = load_config(text=CONFIG.format(dir=tmp_path))
    ctl = Controller(cfg, RecordingAmplifier())
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        with pytest.raises(AfmctlError, match="zenoh: cannot open session") as ei:
            ZenohBridgeProcess(ctl, ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"]), "s1")
    assert "\n" not in str(ei.value)
