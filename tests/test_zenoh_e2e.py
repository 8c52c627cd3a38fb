"""End to end over zenoh on loopback: the real Controller (afmctl.control.controller) driving the
simulated scanner through the real CAN driver on a python-can virtual bus, the
ZenohBridge, and a client session that publishes trajectories and temperatures and
watches setpoints, drift and status."""
from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from afmctl.zenoh_api.messages import CmdRequest, LineMsg, SegmentMsg, TemperatureMsg, decode_setpoints
from afmctl.zenoh_api.settings import AclSettings, AclSubject, UserPasswordSettings, ZenohSettings
from afmctl.testing import bridge_on_free_port, wait_for

import zenoh

CONFIG = """
[scanner]
name = "s1"
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
T_C = 22.0
[trajectory]
kind = "queue"
[runlog]
enabled = false
[simulation]
enabled = true
"""




class Client:
    def __init__(self, settings: ZenohSettings) -> None:
        self.session = zenoh.open(settings.to_zenoh_config())
        self.batches: list = []
        self.drift: list[dict] = []
        self.status: list[dict] = []
        self.subs = [
            self.session.declare_subscriber("afm/s1/setpoint",
                                            lambda s: self.batches.append(decode_setpoints(s.payload.to_bytes()))),
            self.session.declare_subscriber("afm/s1/drift", lambda s: self.drift.append(json.loads(s.payload.to_bytes()))),
            self.session.declare_subscriber("afm/s1/status",
                                            lambda s: self.status.append(json.loads(s.payload.to_bytes()))),
        ]

    def cmd(self, name: str, **args) -> list[dict]:
        replies = self.session.get("afm/s1/cmd", payload=CmdRequest(cmd=name, args=args).to_json_bytes(), timeout=3.0)
        return [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    from afmctl.config import load_config
    from afmctl.control.controller import Controller
    from afmctl.simulation.link import simulated_amplifier

    before = {t.ident for t in threading.enumerate()}
    users = tmp_path_factory.mktemp("zenoh") / "users.txt"
    users.write_text("op:op-pw\nviewer:viewer-pw\n")
    server = ZenohSettings(
        auth=UserPasswordSettings(dictionary_file=users),
        acl=AclSettings(enabled=True, operators=[AclSubject(id="operators", usernames=["op"])]))
    cfg = load_config(text=CONFIG.format(channel=f"zen-e2e-{id(server)}"))
    with simulated_amplifier(cfg) as (amp, _scanner):
        ctl = Controller(cfg, amp)
        bridge, cli = bridge_on_free_port(ctl, "s1", server, status_period_s=0.2)
        op = Client(cli.model_copy(update={"auth": UserPasswordSettings(user="op", password="op-pw")}))
        viewer = Client(cli.model_copy(update={"auth": UserPasswordSettings(user="viewer", password="viewer-pw")}))
        try:
            assert wait_for(lambda: op.status and viewer.status), "clients never saw status"
            yield cfg, ctl, bridge, op, viewer
        finally:
            op.close()
            viewer.close()
            ctl.stop()
            ctl.close()
            bridge.close()
    time.sleep(0.2)
    ours = [t for t in threading.enumerate() if t.ident not in before and t.name.startswith("afmctl")]
    assert not ours, f"leaked threads: {ours}"


def test_viewer_cannot_start_or_send_trajectories(service):
    cfg, ctl, bridge, op, viewer = service
    seg = SegmentMsg(seq=0, dt_s=1e-3, positions_nm=[[1000.0, 1000.0, 0.0]] * 50).to_json_bytes()
    viewer.session.put("afm/s1/trajectory", seg)
    assert viewer.cmd("start") == []            # the query never reaches the service
    time.sleep(0.3)
    assert ctl.state.value == "idle"
    assert bridge.counters["accepted"] == 0
    assert viewer.status, "the viewer may still watch"


def test_trajectory_and_temperature_end_to_end(service):
    cfg, ctl, bridge, op, viewer = service
    reply = op.cmd("start")
    assert reply and reply[0]["ok"], reply
    assert ctl.state.value == "running"
    n_seg = 3
    for k in range(n_seg):
        pos = np.zeros((300, 3))
        pos[:, 0] = np.linspace(1000.0, 4000.0, 300)
        pos[:, 1] = 2000.0
        op.session.put("afm/s1/trajectory", SegmentMsg(seq=k, dt_s=1e-3, positions_nm=pos.tolist()).to_json_bytes())
    op.session.put("afm/s1/trajectory", LineMsg(seq=n_seg, dt_s=1e-3, from_nm=[4000, 2000, 0], to_nm=[2000, 3000, 0],
                                                 duration_s=0.3).to_json_bytes())
    for i in range(12):
        op.session.put("afm/s1/temperature", TemperatureMsg(seq=i, t_s=0.1 * i, T_C=22.0 + 0.5 * i).to_json_bytes())
        time.sleep(0.08)
    assert wait_for(lambda: ctl.stats()["samples"] >= 1200 and ctl.state.value == "holding", 10)
    status = op.cmd("status")[0]["result"]
    assert status["state"] == "holding"
    for key in ("lateness_p50_s", "lateness_p99_s", "lateness_max_s", "missed_deadlines", "samples", "errors"):
        assert key in status["stats"], key
    assert status["stats"]["samples"] >= 1200
    assert wait_for(lambda: sum(len(b) for _, b in op.batches) >= ctl.stats()["samples"], 5)
    batch_seqs = [s for s, _ in op.batches]
    assert batch_seqs == list(range(len(batch_seqs))), "setpoint batch sequence gap"
    samples = np.concatenate([b["seq"] for _, b in op.batches]).astype(np.int64)
    assert np.array_equal(samples, np.arange(samples[0], samples[0] + len(samples))), "sample sequence gap"
    targets = np.concatenate([b["target_nm"] for _, b in op.batches])
    assert np.any(np.isclose(targets[:, 0], 4000.0)) and np.any(np.isclose(targets[:, 1], 3000.0, atol=5))
    # drift estimates respond to the temperature: zero at 22 °C, growing as it warms
    assert all(abs(d["drift_nm"][2]) < 1e-3 for d in op.drift if d["T_C"] == 22.0)   # only the voltages' heat
    assert max(abs(d["drift_nm"][2]) for d in op.drift) > 0.05
    assert [d["T_C"] for d in op.drift][-1] == pytest.approx(27.5)
    seqs = [d["seq"] for d in op.drift]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    # every estimate names its inputs: the temperature and the voltages of its sample
    records = {int(r["seq"]): r for _, b in op.batches for r in b}
    for d in op.drift:
        rec = records[d["inputs"]["seq"]]
        assert d["inputs"]["T_C"] == d["T_C"]
        assert d["inputs"]["u_V"] == [float(v) for v in rec["u_V"]]


BAD = [
    ("trajectory", b"{not json"),
    ("trajectory", b'{"schema":9,"seq":0,"type":"segment","dt_s":0.001,"positions_nm":[[1,1,0]]}'),
    ("trajectory", b'{"schema":1,"seq":0,"type":"segment","dt_s":0.001,"positions_nm":[[900000,1,0]]}'),
    ("trajectory", b'{"schema":1,"seq":0,"type":"segment","dt_s":0.001,"positions_nm":[[-1e5,1,0]]}'),
    ("temperature", b'{"schema":1,"seq":0,"t_s":0,"T_C":-300}'),
    ("temperature", b'[]'),
]


def _u_within_limits(cfg, batches) -> None:
    u = np.concatenate([b["u_V"] for _, b in batches])
    for i, axis in enumerate(cfg.scanner.axes):
        lo, hi = cfg.limits(axis)
        assert u[:, i].min() >= lo and u[:, i].max() <= hi, axis


@pytest.mark.parametrize("leaf,payload", BAD)
def test_bad_messages_rejected_service_alive(service, leaf, payload):
    cfg, ctl, bridge, op, viewer = service
    before = bridge.counters["rejected"]
    op.session.put(f"afm/s1/{leaf}", payload)
    assert wait_for(lambda: bridge.counters["rejected"] > before, 5)
    assert wait_for(lambda: op.status[-1]["rejected"] > before, 5)          # reported on status
    assert op.status[-1]["errors"][-1]["source"] == leaf
    assert op.cmd("status")[0]["ok"]
    assert ctl.state.value in ("running", "holding")


_segments = st.builds(
    lambda pos, dt, schema: {"schema": schema, "seq": 0, "type": "segment", "dt_s": dt,
                             "positions_nm": [list(p) for p in pos]},
    st.lists(st.tuples(st.floats(-2e6, 2e6), st.floats(-2e6, 2e6), st.floats(-1e3, 1e3)), min_size=1, max_size=40),
    st.sampled_from([1e-3, 1e-4, 0.5, 0.0, 2.0]), st.sampled_from([1, 1, 1, 2]))
_temperatures = st.fixed_dictionaries({"schema": st.sampled_from([1, 1, 0]), "seq": st.integers(-1, 10),
                                       "t_s": st.floats(-1.0, 1e3), "T_C": st.floats(-400.0, 400.0)})


@settings(max_examples=16, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(leaf_doc=st.one_of(st.tuples(st.just("trajectory"), _segments),
                          st.tuples(st.just("temperature"), _temperatures)))
def test_fuzzed_messages_never_exceed_voltage_limits(service, leaf_doc):
    """Fuzzed segments (out of range, bad dt, wrong version) and temperatures (out of
    range, NaN-free but wild) on the real controller: each is accepted or rejected with an
    error on status, the service lives, every voltage sent stays within the limits."""
    leaf, doc = leaf_doc
    cfg, ctl, bridge, op, viewer = service
    rejected = bridge.counters["rejected"]
    before = rejected + bridge.counters["accepted"]
    op.session.put(f"afm/s1/{leaf}", json.dumps(doc).encode())
    assert wait_for(lambda: bridge.counters["rejected"] + bridge.counters["accepted"] > before, 5)
    if bridge.counters["rejected"] > rejected:
        assert wait_for(lambda: op.status[-1]["rejected"] > rejected, 5)
        assert op.status[-1]["errors"][-1]["source"] == leaf
    assert bridge._worker.is_alive() and ctl.state.value in ("running", "holding")
    _u_within_limits(cfg, op.batches)


def test_stop_reports_stopped_and_limits_held(service):
    cfg, ctl, bridge, op, viewer = service
    assert op.cmd("stop")[0]["ok"]
    assert ctl.wait(10)
    assert wait_for(lambda: op.status and op.status[-1]["state"] == "stopped", 5)
    _u_within_limits(cfg, op.batches)
