"""Issue 39, the parts of a lab in one process with real zenoh sessions on loopback: the
ACL file (one-line errors, `afmctl router` exit 2, its translation), presence tokens and
the late joiner's status through a router, and two linked routers (two rooms, mutual
TLS between them): a view on one sees the scanners of the other, also after the link
between them was cut and joined again. The whole lab as processes: test_lab_router.py."""
from __future__ import annotations

import json
import shutil
import threading
import time

import pytest

from afmctl.cli import main
from afmctl.errors import AfmctlError
from afmctl.testing import wait_for
from afmctl.view.feed import ViewFeed
from afmctl.view.labstack import TcpRelay, make_certificates
from afmctl.zenoh_api.bridge import ZenohBridge
from afmctl.zenoh_api.lab_acl import load_acl
from afmctl.zenoh_api.router import Router, RouterSettings
from afmctl.zenoh_api.session import open_session
from afmctl.zenoh_api.sim_publisher import SimPublisher
from afmctl.zenoh_api.settings import TlsSettings, UserPasswordSettings, ZenohSettings, free_loopback_endpoint

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]


class IdleController:
    """Controller-shaped, idle: what the bridge needs to serve status and presence."""

    state = "idle"

    def __init__(self) -> None:
        self.sinks: list = []

    def add_sink(self, sink) -> None:
        self.sinks.append(sink)

    def remove_sink(self, sink) -> None:
        self.sinks.remove(sink)

    def stats(self) -> dict:
        return {"samples": 0}


@pytest.mark.parametrize("text, error", [
    ('observers = ["nobody"]', "observers: unknown subject 'nobody'"),
    ('[subjects]\na = {}\n[scanners."x/y"]\noperators = ["a"]', "scanner 'x/y'"),
    ('[subjects]\na = { usernames = [] }', "field subjects.a.usernames"),
    ('[subjects]\na = { user = ["u"] }', "field subjects.a.user: Extra inputs are not permitted"),
    ('prefix = ""', "field prefix"),
    ("observers = [", "not valid TOML"),
])
def test_a_bad_acl_file_is_one_line_naming_the_field(tmp_path, text, error):
    path = tmp_path / "acl.toml"
    path.write_text(text)
    with pytest.raises(AfmctlError) as err:
        load_acl(path)
    assert str(err.value).startswith(str(path)) and error in str(err.value) and "\n" not in str(err.value)


def test_router_cli_exits_2_on_a_bad_acl_and_prints_its_zenoh_config(tmp_path, capsys):
    bad = tmp_path / "acl.toml"
    bad.write_text('[scanners.s1]\noperators = ["alice"]\n')
    assert main(["router", "--acl", str(bad), "--print-config"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "scanners.s1.operators: unknown subject 'alice'" in err, err
    (tmp_path / "router.toml").write_text('[router]\nlisten = ["tcp/127.0.0.1:7999"]\nacl = "good.toml"\n'
                                          '[router.auth]\nuser = "room-a"\npassword = "secret"\n')
    (tmp_path / "good.toml").write_text('[subjects]\nalice = { usernames = ["alice"] }\n'
                                        '[scanners.s1]\noperators = ["alice"]\n')
    assert main(["router", "--config", str(tmp_path / "router.toml"), "--print-config"]) == 0
    out = capsys.readouterr().out
    config = json.loads(out)
    assert "secret" not in out and config["mode"] == "router" and config["listen/endpoints"] == ["tcp/127.0.0.1:7999"]
    acl = config["access_control"]
    assert acl["default_permission"] == "deny"
    operate = next(r for r in acl["rules"] if r["id"] == "operate-s1-query")
    assert operate == {"id": "operate-s1-query", "permission": "allow", "flows": ["ingress"], "messages": ["query"],
                       "key_exprs": ["afm/s1/cmd"]}
    assert {"id": "operators-s1", "rules": ["operate-s1-put", "operate-s1-query", "operate-s1-reply"],
            "subjects": ["alice"]} in acl["policies"]


def test_without_an_acl_file_nobody_may_command():
    acl = RouterSettings().access_control().to_zenoh()
    allowed = {(flow, m, k) for r in acl["rules"] for flow in r["flows"] for m in r["messages"] for k in r["key_exprs"]}
    assert not any(m in ("put", "query") and flow == "ingress" and k.endswith(("cmd", "trajectory", "temperature"))
                   for flow, m, k in allowed), allowed
    assert ("ingress", "put", "afm/*/setpoint") in allowed and ("ingress", "liveliness_token", "afm/*/alive") in allowed


def test_presence_and_the_late_joiners_status_through_a_router():
    endpoint = free_loopback_endpoint()
    router = Router(RouterSettings(listen=[endpoint]))
    client = ZenohSettings(mode="client", listen=[], connect=[endpoint])
    ctl = IdleController()
    try:
        # the service publishes its status once a minute: a view that joins later gets it
        # at once from the status queryable, and sees the token come and go
        bridge = ZenohBridge(ctl, client, "stage7", status_period_s=60.0)
        bridge.publish_status()
        with ViewFeed(ZenohSettings(listen=[], connect=[endpoint])) as view:
            assert wait_for(lambda: "stage7" in view.feeds() and view.feeds()["stage7"].status is not None, 10.0)
            feed = view.feeds()["stage7"]
            assert feed.alive is True and feed.status["state"] == "idle" and feed.status["scanner"] == "stage7"
            bridge.close()
            assert wait_for(lambda: feed.alive is False, 10.0)
            # the simulator declares its scanner's presence too
            sim = SimPublisher(client, "sim7")
            assert wait_for(lambda: "sim7" in view.feeds() and view.feeds()["sim7"].alive is True, 10.0)
            sim.close()
            assert wait_for(lambda: view.feeds()["sim7"].alive is False, 10.0)
    finally:
        router.close()


def _room(tmp_path, room: str, users: str, acl: str, listen: list[str], connect: tuple[str, ...] = (),
          user: str | None = None) -> Router:
    """The router of ``room``: its users and ACL files, mutual TLS with its certificate."""
    (tmp_path / f"users-{room}.txt").write_text(users)
    (tmp_path / f"acl-{room}.toml").write_text(acl)
    tls = TlsSettings(root_ca=tmp_path / "ca.pem", certificate=tmp_path / f"{room}.pem",
                      private_key=tmp_path / f"{room}.key", mtls=True)
    auth = UserPasswordSettings(dictionary_file=tmp_path / f"users-{room}.txt", user=user,
                                password=None if user is None else f"{user}-pw")
    return Router(RouterSettings(listen=listen, connect=list(connect), acl=tmp_path / f"acl-{room}.toml", tls=tls,
                                 auth=auth))


ACL_A = """observers = ["viewer"]
routers = ["room-b"]
[subjects]
viewer = { usernames = ["viewer"] }
room-b = { cert_common_names = ["room-b"] }
"""
ACL_B = """routers = ["room-a"]
[subjects]
svc = { usernames = ["svc-stage9"] }
room-a = { cert_common_names = ["room-a"] }
[scanners.stage9]
services = ["svc"]
"""


def test_two_rooms_a_view_sees_the_other_room_and_recovers_after_the_link_is_cut(tmp_path):
    """Room A's router listens for routers on mutual TLS (the link's subject: its
    certificate's common name); room B's connects to it through a relay that can be cut."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl command not available to make test certificates")
    make_certificates(tmp_path, ("room-a", "room-b"))
    ep_a, ep_b, tls_a = (free_loopback_endpoint() for _ in range(3))
    tls_a = tls_a.replace("tcp/", "tls/")
    router_a = _room(tmp_path, "room-a", "viewer:viewer-pw\nroom-b:room-b-pw\n", ACL_A, [ep_a, tls_a])
    relay = TcpRelay(tls_a.split("/", 1)[1])
    router_b = _room(tmp_path, "room-b", "svc-stage9:svc-stage9-pw\n", ACL_B, [ep_b],
                     connect=(relay.endpoint.replace("tcp/", "tls/"),), user="room-b")
    service = open_session(ZenohSettings(mode="client", listen=[], connect=[ep_b],
                                         auth=UserPasswordSettings(user="svc-stage9", password="svc-stage9-pw")))
    stop = threading.Event()
    view = ViewFeed(ZenohSettings(listen=[], connect=[ep_a],
                                  auth=UserPasswordSettings(user="viewer", password="viewer-pw")))
    try:
        token = service.liveliness().declare_token("afm/stage9/alive")
        status = json.dumps({"schema": 1, "seq": 0, "scanner": "stage9", "t_s": 0.0, "state": "running",
                             "stats": {}, "errors": [], "rejected": 0}).encode()
        pub = threading.Thread(target=_publish_until, args=(service, status, stop), name="lab-status", daemon=True)
        pub.start()
        view.start()
        assert wait_for(lambda: "stage9" in view.feeds() and view.feeds()["stage9"].alive is True, 15.0)
        feed = view.feeds()["stage9"]
        assert wait_for(lambda: feed.counts["status"] > 0, 10.0), feed.counts
        relay.cut()
        assert wait_for(lambda: feed.alive is False, 15.0), "the cut link went unnoticed"
        heard = feed.counts["status"]
        relay.join()
        assert wait_for(lambda: feed.alive is True and feed.counts["status"] > heard + 2, 20.0), feed.counts
        token.undeclare()
    finally:
        stop.set()
        view.close()
        service.close()
        router_b.close()
        relay.close()
        router_a.close()


def _publish_until(session, payload: bytes, stop: threading.Event) -> None:
    while not stop.wait(0.05):
        session.put("afm/stage9/status", payload)


def test_the_lab_section_of_zenoh_md_shows_the_tests_own_files():
    """docs/ZENOH.md's "A lab" shows examples/lab/router.toml and acl.toml as they are
    (every setting line, comments aside), the files tests/test_lab_router.py runs."""
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    doc = (root / "docs" / "ZENOH.md").read_text()
    section = doc[doc.index("## A lab"):doc.index("## The simulator's truth")]
    for name in ("router.toml", "acl.toml"):
        for line in (root / "examples" / "lab" / name).read_text().splitlines():
            setting = line.split("#", 1)[0].strip()
            if setting:
                assert setting in section, (name, setting)
    acl = load_acl(root / "examples" / "lab" / "acl.toml")
    assert sorted(acl.scanners) == ["stage1", "stage2", "stage3"]
