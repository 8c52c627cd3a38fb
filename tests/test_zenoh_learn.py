"""``afm/<scanner>/learn``: each learning iteration reaches a subscriber over a real zenoh
session on loopback, as a :class:`LearnMsg` that decodes back to what was published."""
from __future__ import annotations

import queue

import pytest

from afmctl.zenoh_api.bridge import open_session
from afmctl.zenoh_api.learn import LearnPublisher
from afmctl.zenoh_api.messages import LearnMsg, MessageError, decode_json
from afmctl.zenoh_api.settings import loopback_pair

pytestmark = pytest.mark.slow


def test_iterations_reach_a_subscriber_in_order():
    srv, cli = loopback_pair()
    with LearnPublisher(srv, "s1") as pub:
        sub_session = open_session(cli)
        got: queue.Queue = queue.Queue()
        sub = sub_session.declare_subscriber(pub.key, lambda s: got.put(bytes(s.payload.to_bytes())))
        try:
            msgs = []
            for k in range(3):   # the first puts may go before the route exists: repeat until heard
                for _ in range(50):
                    pub.publish(k, {"max_pct": 2.0 / (k + 1), "rms_pct": 0.5 / (k + 1)}, step=0.8)
                    try:
                        msgs.append(decode_json(got.get(timeout=0.1), LearnMsg))
                        break
                    except queue.Empty:
                        continue
            last = pub.publish(3, {"max_pct": 0.1, "rms_pct": 0.02, "central_max_pct": 0.05,
                                   "central_rms_pct": 0.01}, state="converged", detail="noise floor")
            msgs.append(decode_json(got.get(timeout=5), LearnMsg))
            # while learning, the scanner's presence token is declared (afmctl view lists it)
            alive = [str(r.ok.key_expr) for r in sub_session.liveliness().get("afm/*/alive", timeout=5) if r.ok]
            assert alive == ["afm/s1/alive"], alive
        finally:
            sub.undeclare()
            sub_session.close()
    assert [m.iteration for m in msgs] == [0, 1, 2, 3]
    assert msgs[-1] == last and msgs[-1].state == "converged" and msgs[-1].central_max_pct == 0.05
    assert [m.seq for m in msgs] == sorted(m.seq for m in msgs)


def test_a_bad_learn_message_names_the_field():
    with pytest.raises(MessageError, match="max_pct"):
        decode_json(b'{"schema":1,"seq":0,"t_s":1,"iteration":0,"max_pct":-1,"rms_pct":0}', LearnMsg)
