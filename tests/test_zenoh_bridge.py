"""ZenohBridge over real zenoh sessions on loopback, against a small real controller-shaped
object (StandInController) that follows the Controller interface (interfaces item 6):
sinks are called from its own dispatcher thread, never from the caller's thread."""
from __future__ import annotations

import json
import queue
import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from afmctl.zenoh_api.messages import (
    SETPOINT_DTYPE,
    CmdReply,
    CmdRequest,
    RasterMsg,
    SegmentMsg,
    StatusMsg,
    TemperatureMsg,
    decode_setpoints,
)
from afmctl.zenoh_api.bridge import ZenohBridge
from afmctl.zenoh_api.settings import loopback_pair
from afmctl.testing import bridge_on_free_port, wait_for

import zenoh

LIMITS_V = (0.0, 150.0)
NM_PER_V = 66.7
RANGE_NM = (0.0, 10_000.0)


class StandInController:
    """Controller-shaped: linear axis, drift 40 nm/K in x, limits 0..150 V, own dispatcher."""

    def __init__(self) -> None:
        self.state = "idle"
        self._sinks: list = []
        self._seq = 0
        self._t_s = 0.0
        self._T0: float | None = None
        self._drift = np.zeros(3)
        self._q: queue.Queue = queue.Queue()
        self.emitted_u: list[np.ndarray] = []
        self.segments = 0
        self.temperatures = 0
        self._thread = threading.Thread(target=self._dispatch, name="standin-dispatch", daemon=True)
        self._thread.start()

    # interface ------------------------------------------------------------
    def add_sink(self, sink) -> None:
        self._sinks.append(sink)

    def remove_sink(self, sink) -> None:
        self._sinks.remove(sink)

    def submit_segment(self, positions_nm: np.ndarray, dt_s: float) -> None:
        p = np.asarray(positions_nm, float)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"positions_nm: shape {p.shape}; expected (N, 3)")
        lo, hi = RANGE_NM
        if p.min() < lo or p.max() > hi:
            raise ValueError(f"positions_nm: outside the scan range {lo:g}..{hi:g} nm")
        n = len(p)
        batch = np.zeros(n, SETPOINT_DTYPE)
        batch["seq"] = np.arange(self._seq, self._seq + n)
        batch["t_s"] = self._t_s + dt_s * np.arange(1, n + 1)
        batch["target_nm"] = p
        batch["corrected_nm"] = p - self._drift
        batch["u_V"] = np.clip(batch["corrected_nm"] / NM_PER_V, *LIMITS_V)
        self._seq += n
        self._t_s = float(batch["t_s"][-1])
        self.segments += 1
        self._q.put(("setpoints", batch))

    def set_temperature(self, t_s: float, T_C: float) -> None:
        if self._T0 is None:
            self._T0 = T_C
        self._drift = np.array([40.0, 0.0, 0.0]) * (T_C - self._T0)
        self.temperatures += 1
        self._q.put(("drift", {"t_s": t_s, "drift_nm": self._drift.copy(), "std_nm": np.ones(3), "T_C": T_C}))

    def start(self, source) -> None:
        self.state = "running"

    def stop(self) -> None:
        self.state = "stopped"

    def estop(self) -> None:
        self.state = "fault"

    def stats(self) -> dict:
        return {"samples": self._seq, "lateness_p50_s": 1e-5, "lateness_p99_s": 5e-5, "missed_deadlines": 0}

    def close(self) -> None:
        self._q.put(None)
        self._thread.join(5)

    # dispatcher ------------------------------------------------------------
    def _dispatch(self) -> None:
        while (item := self._q.get()) is not None:
            kind, data = item
            for sink in list(self._sinks):
                if kind == "setpoints":
                    self.emitted_u.append(data["u_V"].copy())
                    sink.on_setpoints(data)
                else:
                    sink.on_drift(data)


class Client:
    """A zenoh client session collecting everything the service publishes."""

    def __init__(self, settings, scanner: str = "s1") -> None:
        self.session = zenoh.open(settings.to_zenoh_config())
        self.prefix = f"afm/{scanner}"
        self.batches: list[tuple[int, np.ndarray]] = []
        self.drift: list[dict] = []
        self.status: list[dict] = []
        self._subs = [
            self.session.declare_subscriber(f"{self.prefix}/setpoint",
                                            lambda s: self.batches.append(decode_setpoints(s.payload.to_bytes()))),
            self.session.declare_subscriber(f"{self.prefix}/drift",
                                            lambda s: self.drift.append(json.loads(s.payload.to_bytes()))),
            self.session.declare_subscriber(f"{self.prefix}/status",
                                            lambda s: self.status.append(json.loads(s.payload.to_bytes()))),
        ]

    def put(self, leaf: str, payload: bytes) -> None:
        # BLOCK: a large (fragmented) put must not be dropped by the client's own queue
        self.session.put(f"{self.prefix}/{leaf}", payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def cmd(self, name: str, **args) -> dict:
        req = CmdRequest(cmd=name, args=args)
        replies = list(self.session.get(f"{self.prefix}/cmd", payload=req.to_json_bytes(), timeout=5.0))
        oks = [r.ok for r in replies if r.ok is not None]
        assert len(oks) == 1, f"expected one reply, got {replies}"
        return json.loads(oks[0].payload.to_bytes())

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.session.close()




@pytest.fixture(scope="module")
def service():
    """One service + one client for the module (zenoh sessions are slowish to open)."""
    before = {t.ident for t in threading.enumerate()}
    ctl = StandInController()
    bridge, cli = bridge_on_free_port(ctl, "s1", status_period_s=0.2)
    client = Client(cli)
    assert wait_for(lambda: len(client.status) > 0), "client never saw a status message"
    yield ctl, bridge, client
    client.close()
    bridge.close()
    ctl.close()

    def leaked():
        return [t for t in threading.enumerate() if t.ident not in before and t.is_alive()]
    wait_for(lambda: not leaked(), 10.0)   # zenoh ends its callback threads shortly after close()
    assert not leaked(), f"leaked threads: {leaked()}"


def test_setpoints_arrive_without_gap_and_drift_follows_temperature(service):
    ctl, bridge, client = service
    client.batches.clear()
    n0 = ctl._seq
    rng = np.random.default_rng(1)
    for seq in range(5):
        pos = rng.uniform(100, 9000, size=(700, 3))
        client.put("trajectory", SegmentMsg(seq=seq, dt_s=1e-3, positions_nm=pos.tolist()).to_json_bytes())
    raster = RasterMsg(seq=5, dt_s=1e-3, center_nm=[5000, 5000, 0], size_nm=[2000, 2000], lines=4,
                       line_rate_hz=10)
    client.put("trajectory", raster.to_json_bytes())
    expected = 5 * 700 + 4 * 100
    assert wait_for(lambda: sum(len(b) for _, b in client.batches) >= expected, 10)
    seqs = [s for s, _ in client.batches]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "batch sequence gap"
    samples = np.concatenate([b["seq"] for _, b in client.batches])
    assert np.array_equal(samples, np.arange(n0, n0 + expected)), "sample sequence gap"
    assert all(len(b) <= bridge.settings.setpoint_batch for _, b in client.batches)

    client.drift.clear()
    for i, T in enumerate([22.0, 22.5, 23.0]):
        client.put("temperature", TemperatureMsg(seq=i, t_s=float(i), T_C=T).to_json_bytes())
    assert wait_for(lambda: len(client.drift) >= 3)
    dx = [d["drift_nm"][0] for d in client.drift[-3:]]
    assert dx == pytest.approx([0.0, 20.0, 40.0])
    assert [d["seq"] for d in client.drift] == list(range(client.drift[0]["seq"], client.drift[0]["seq"] + len(client.drift)))


def test_cmd_start_stop_estop_status_config(service):
    ctl, bridge, client = service
    reply = CmdReply.model_validate(client.cmd("start"))
    assert reply.ok and reply.result["state"] == "running"
    status = client.cmd("status")
    assert status["ok"]
    st = StatusMsg.model_validate(status["result"])
    assert st.state == "running" and st.stats["samples"] == ctl._seq
    assert "lateness_p99_s" in st.stats and "bridge" in st.stats
    assert client.cmd("stop")["result"]["state"] == "stopped"
    assert client.cmd("estop")["result"]["state"] == "fault"
    assert client.cmd("config") == {**client.cmd("config"), "ok": True}
    # selector form: afm/s1/cmd?cmd=status
    replies = list(client.session.get("afm/s1/cmd?cmd=status", timeout=5.0))
    assert json.loads(replies[0].ok.payload.to_bytes())["result"]["state"] == "fault"
    ctl.state = "idle"


def test_unknown_command_is_an_error_reply(service):
    _, _, client = service
    replies = list(client.session.get("afm/s1/cmd", payload=b'{"schema":1,"seq":0,"cmd":"selfdestruct"}',
                                      timeout=5.0))
    body = json.loads(replies[0].ok.payload.to_bytes())
    assert body["ok"] is False and "cmd" in body["error"]


BAD_TRAJECTORIES = [
    b"",
    b"\xff\xfe",
    b"not json",
    b"[1,2,3]",
    b'{"seq":0,"type":"segment","dt_s":0.001,"positions_nm":[[1,2,3]]}',             # no schema
    b'{"schema":2,"seq":0,"type":"segment","dt_s":0.001,"positions_nm":[[1,2,3]]}',  # wrong version
    b'{"schema":1,"seq":0,"type":"segment","dt_s":0.0,"positions_nm":[[1,2,3]]}',    # dt out of range
    b'{"schema":1,"seq":0,"type":"segment","dt_s":0.001,"positions_nm":[[1,2]]}',    # wrong shape
    b'{"schema":1,"seq":0,"type":"segment","dt_s":0.001,"positions_nm":[[NaN,2,3]]}',
    b'{"schema":1,"seq":0,"type":"segment","dt_s":0.001,"positions_nm":[[-5000,2,3]]}',  # outside scan range
    b'{"schema":1,"seq":0,"type":"raster","dt_s":1e-6,"center_nm":[0,0,0],"size_nm":[1,1],"lines":65536,'
    b'"line_rate_hz":0.001}',                                                           # too many samples
    b'{"schema":1,"seq":0,"type":"warp","dt_s":0.001}',
    b'{"schema":1,"seq":' + b"9" * 5000 + b',"type":"segment","dt_s":0.001,"positions_nm":[[1,2,3]]}',
]
BAD_TEMPERATURES = [
    b"{}",
    b'{"schema":1,"seq":0,"t_s":0,"T_C":1000}',
    b'{"schema":1,"seq":0,"t_s":0,"T_C":"warm"}',
    b'{"schema":0,"seq":0,"t_s":0,"T_C":22}',
    b'{"schema":1,"seq":0,"t_s":-1,"T_C":22,"extra":1}',
    b'{"schema":1,"seq":0,"t_s":0,"T_C":' + b"2" * 4400 + b'}',
]


def _reject_and_check(service, leaf: str, payload: bytes) -> None:
    ctl, bridge, client = service
    before = bridge.counters["rejected"]
    segments, temps = ctl.segments, ctl.temperatures
    client.put(leaf, payload)
    assert wait_for(lambda: bridge.counters["rejected"] > before), f"{payload[:80]!r} was not rejected"
    # reported on status (a bad cmd of the test before may be counted after `before` was read:
    # its rejection is queued for the bridge's worker, so wait for this message's error)
    assert wait_for(lambda: client.status[-1]["rejected"] > before and
                    client.status[-1]["errors"][-1]["source"] == leaf), client.status[-1]["errors"][-3:]
    assert ctl.segments == segments and ctl.temperatures == temps


@pytest.mark.parametrize("payload", BAD_TRAJECTORIES)
def test_bad_trajectory_rejected_on_status(service, payload):
    _reject_and_check(service, "trajectory", payload)


@pytest.mark.parametrize("payload", BAD_TEMPERATURES)
def test_bad_temperature_rejected_on_status(service, payload):
    _reject_and_check(service, "temperature", payload)


def test_oversized_payload_rejected(service):
    ctl, bridge, client = service
    big = b" " * (bridge.settings.max_message_bytes + 1)
    _reject_and_check(service, "trajectory", big)
    assert "allowed at most" in bridge.status().errors[-1].message


_json_values = st.recursive(st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=8),
                            lambda children: st.lists(children, max_size=4)
                            | st.dictionaries(st.text(max_size=8), children, max_size=4), max_leaves=12)
_fuzz_docs = st.fixed_dictionaries(
    {"schema": st.sampled_from([1, 1, 2, "1", None]), "seq": st.integers(-2, 2**64)},
    optional={"type": st.sampled_from(["segment", "line", "raster", "x"]),
              "dt_s": st.floats(), "positions_nm": _json_values, "from_nm": _json_values,
              "to_nm": _json_values, "duration_s": st.floats(), "T_C": st.floats(), "t_s": st.floats(),
              "extra": _json_values})


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(doc=_fuzz_docs, leaf=st.sampled_from(["trajectory", "temperature"]))
def test_fuzzed_messages_never_break_limits_or_service(service, doc, leaf):
    ctl, bridge, client = service
    payload = json.dumps(doc).encode()
    before = bridge.counters["rejected"] + bridge.counters["accepted"]
    client.put(leaf, payload)
    assert wait_for(lambda: bridge.counters["rejected"] + bridge.counters["accepted"] > before, 5)
    assert bridge._worker.is_alive()
    for u in ctl.emitted_u:
        assert u.min() >= LIMITS_V[0] and u.max() <= LIMITS_V[1]


def test_service_still_answers_after_abuse(service):
    _, bridge, client = service
    assert client.cmd("status")["ok"]
    assert bridge.status().rejected >= len(BAD_TRAJECTORIES) + len(BAD_TEMPERATURES)


def test_sim_publisher_tip_positions(service):
    from afmctl.zenoh_api.messages import SimTipMsg, decode_json
    from afmctl.zenoh_api.sim_publisher import SimPublisher
    _, bridge, client = service
    got: list = []
    sub = client.session.declare_subscriber("afm/s1/sim/**", lambda s: got.append((str(s.key_expr),
                                                                                  s.payload.to_bytes())))
    try:
        with SimPublisher(bridge.settings, "s1", session=bridge.session) as sim:
            time.sleep(0.2)
            for k in range(5):
                sim.publish_tip(0.01 * k, [100.0 + k, 200.0, 3.0])
            sim.publish_json("image", {"rows": 4, "pixel_nm": 39.0, "schema": 7, "seq": 99})  # cannot override
            assert wait_for(lambda: len(got) >= 6)
    finally:
        sub.undeclare()
    tips = [decode_json(p, SimTipMsg) for k, p in got if k == "afm/s1/sim/tip"]
    assert [t.seq for t in tips] == [0, 1, 2, 3, 4]
    assert tips[-1].position_nm == [104.0, 200.0, 3.0]
    assert json.loads(dict(got)["afm/s1/sim/image"]) == {"schema": 1, "seq": 0, "rows": 4, "pixel_nm": 39.0}


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(doc=st.one_of(_json_values, st.fixed_dictionaries(
    {"schema": st.sampled_from([1, 2]), "seq": st.integers(-1, 5),
     "cmd": st.sampled_from(["status", "config", "launch", 3])},
    optional={"args": _json_values})))
def test_fuzzed_cmd_queries_always_get_one_reply(service, doc):
    ctl, bridge, client = service
    state = ctl.state
    before = bridge.counters["rejected"]
    replies = list(client.session.get("afm/s1/cmd", payload=json.dumps(doc).encode(), timeout=5.0))
    assert len(replies) == 1 and replies[0].ok is not None
    body = json.loads(replies[0].ok.payload.to_bytes())
    assert isinstance(body["ok"], bool) and (body["ok"] or body["error"])
    if not body["ok"]:   # a refused command is an error on status too
        assert wait_for(lambda: bridge.status().rejected > before)
        assert bridge.status().errors[-1].source == "cmd"
    assert ctl.state == state            # status/config/bad commands never change the state


def test_start_with_bad_args_is_refused(service):
    ctl, bridge, client = service
    for args in ({"trajectory": {"type": "segment", "dt_s": 0.001, "positions_nm": [[1e9, 0, 0]]}},
                 {"trajectory": 5}, {"bogus": 1}):
        body = client.cmd("start", **args)
        assert body["ok"] is False and body["error"], args
    assert ctl.state == "idle"


def test_bad_scanner_name_is_a_user_error():
    from afmctl.errors import AfmctlError
    with pytest.raises(AfmctlError, match="scanner.name"):
        ZenohBridge(StandInController.__new__(StandInController), loopback_pair()[0], "a/b*")


def test_estop_is_not_queued_behind_a_full_inbox(service):
    """Fill the worker's queue (the worker is held busy) and estop still acts at once."""
    ctl, bridge, client = service
    release = threading.Event()
    bridge._inbox.put(("reject", ("test", "hold the worker")))
    orig = bridge.reject

    def slow_reject(source, message):
        release.wait(5)
        orig(source, message)
    bridge.reject = slow_reject
    try:
        time.sleep(0.1)
        while True:  # fill the queue
            try:
                bridge._inbox.put_nowait(("tick", None))
            except queue.Full:
                break
        assert client.cmd("status")["error"] == "service busy: queue full"
        t0 = time.monotonic()
        assert client.cmd("estop")["result"]["state"] == "fault"
        assert time.monotonic() - t0 < 2.0
    finally:
        release.set()
        bridge.reject = orig
        ctl.state = "idle"


def test_non_finite_drift_is_reported_not_published(service):
    ctl, bridge, client = service
    n = len(client.drift)
    before = bridge.counters["rejected"]
    bridge.on_drift({"seq": 1, "t_s": 1.0, "drift_nm": [float("nan"), 0.0, 0.0], "std_nm": None, "T_C": 22.0})
    assert bridge.counters["rejected"] == before + 1
    err = bridge.status().errors[-1]
    assert err.source == "drift" and "not published" in err.message
    time.sleep(0.1)
    assert len(client.drift) == n


def test_a_bare_drift_vector_is_published_with_its_three_components(service):
    """The documented array (3,) [nm] form of ``on_drift`` (a controller without a predictor's
    extras): published, not a KeyError in the dispatcher."""
    from afmctl.testing import wait_for
    ctl, bridge, client = service
    n = len(client.drift)
    errors = len(bridge.status().errors)
    bridge.on_drift(np.array([1.0, -2.0, 3.5]))
    bridge.on_drift([0.5, 0.0, 0.0])
    assert wait_for(lambda: len(client.drift) >= n + 2, 5.0)
    assert [m["drift_nm"] for m in client.drift[n:n + 2]] == [[1.0, -2.0, 3.5], [0.5, 0.0, 0.0]]
    assert len(bridge.status().errors) == errors


def test_the_child_process_forwards_every_bridge_part_logger():
    """ZenohBridgeProcess sets the child's log level from bridge.LOGGERS: every module the
    bridge is built from that logs must be listed there."""
    import importlib
    import logging
    import pkgutil
    import afmctl.zenoh_api as pkg
    from afmctl.zenoh_api.bridge import LOGGERS
    parts = [m.name for m in pkgutil.iter_modules(pkg.__path__) if m.name not in ("process", "learn", "router")]
    logging_parts = []
    for name in parts:
        module = importlib.import_module(f"afmctl.zenoh_api.{name}")
        log = getattr(module, "log", None)
        if isinstance(log, logging.Logger):
            logging_parts.append(log.name)
    assert {"afmctl.zenoh_api.bridge", "afmctl.zenoh_api.worker"} <= set(logging_parts)
    assert set(logging_parts) <= set(LOGGERS), set(logging_parts) - set(LOGGERS)
