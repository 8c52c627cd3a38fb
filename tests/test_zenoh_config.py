"""ZenohSettings: safe defaults, validation, and access control enforced by real zenoh
sessions on loopback (user-password authentication identifies the subjects)."""
from __future__ import annotations

import json
import time

import pytest
from pydantic import ValidationError

from afmctl.errors import AfmctlError
from afmctl.zenoh_api.settings import AclSettings, AclSubject, UserPasswordSettings, ZenohSettings, loopback_pair

import zenoh


def test_defaults_are_private():
    s = ZenohSettings()
    assert s.enabled is False and s.mode == "peer"
    assert s.listen == ["tcp/127.0.0.1:7447"] and s.connect == []
    cfg = s.to_zenoh_config()
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(cfg.get_json("scouting/gossip/enabled")) is False
    assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(cfg.get_json("mode")) == "peer"
    assert json.loads(cfg.get_json("access_control/enabled")) is False


@pytest.mark.parametrize("field,value", [
    ("listen", ["127.0.0.1:7447"]),
    ("listen", ["tcp/127.0.0.1"]),
    ("listen", ["tcp/127.0.0.1:70000"]),
    ("connect", ["http/example.org:80"]),
    ("mode", "server"),
    ("prefix", "afm/**"),
    ("prefix", ""),
    ("setpoint_batch", 0),
    ("bogus", 1),
])
def test_bad_settings_name_the_field(field, value):
    with pytest.raises(ValidationError) as err:
        ZenohSettings.model_validate({field: value})
    assert err.value.errors()[0]["loc"][0] == field


def test_tls_and_auth_need_pairs(tmp_path):
    with pytest.raises(ValidationError, match="together"):
        ZenohSettings.model_validate({"tls": {"certificate": str(tmp_path / "c.pem")}})
    with pytest.raises(ValidationError, match="mtls"):
        ZenohSettings.model_validate({"tls": {"mtls": True}})
    with pytest.raises(ValidationError, match="together"):
        ZenohSettings.model_validate({"auth": {"user": "a"}})


def test_tls_paths_reach_zenoh_config(tmp_path):
    s = ZenohSettings.model_validate({
        "listen": ["tls/127.0.0.1:7448"],
        "tls": {"root_ca": str(tmp_path / "ca.pem"), "certificate": str(tmp_path / "me.pem"),
                "private_key": str(tmp_path / "me.key"), "mtls": True}})
    cfg = s.to_zenoh_config()
    assert json.loads(cfg.get_json("transport/link/tls/enable_mtls")) is True
    assert json.loads(cfg.get_json("transport/link/tls/listen_certificate")) == str(tmp_path / "me.pem")
    assert json.loads(cfg.get_json("transport/link/tls/root_ca_certificate")) == str(tmp_path / "ca.pem")


def test_router_mode_and_acl_json_accepted_by_zenoh():
    s = ZenohSettings(mode="router", acl=AclSettings(
        enabled=True, operators=[AclSubject(id="ui", cert_common_names=["ui.lab"])],
        observers=[AclSubject(id="lab", interfaces=["lo"])]))
    cfg = s.to_zenoh_config("s1")
    acl = json.loads(cfg.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    operate = next(r for r in acl["rules"] if r["id"] == "afmctl-operate")
    assert set(operate["key_exprs"]) == {"afm/s1/trajectory", "afm/s1/temperature", "afm/s1/cmd"}
    policy = next(p for p in acl["policies"] if p["id"] == "afmctl-operators")
    assert policy["subjects"] == ["ui"]


def _client(cli_settings, user, password):
    s = cli_settings.model_copy(update={"auth": UserPasswordSettings(user=user, password=password)})
    return zenoh.open(s.to_zenoh_config())


def test_access_control_only_operators_may_command(tmp_path):
    """Deny by default: a peer authenticated as 'viewer' can watch but cannot put a
    trajectory or query cmd; the 'op' user can."""
    users = tmp_path / "users.txt"
    users.write_text("op:op-secret\nviewer:viewer-secret\n")
    srv, cli = loopback_pair(ZenohSettings(
        auth=UserPasswordSettings(dictionary_file=users),
        acl=AclSettings(enabled=True, operators=[AclSubject(id="operators", usernames=["op"])])))
    service = zenoh.open(srv.to_zenoh_config("s1"))
    got: list[bytes] = []
    spoofed: list[bytes] = []   # puts by peers on keys only the service may publish
    subs = [service.declare_subscriber("afm/s1/trajectory", lambda s: got.append(s.payload.to_bytes())),
            service.declare_queryable("afm/s1/cmd", lambda q: q.reply(q.key_expr, b"started")),
            *(service.declare_subscriber(f"afm/s1/{leaf}", lambda s: spoofed.append(s.payload.to_bytes())
                                         if s.payload.to_bytes().startswith(b"spoof") else None)
              for leaf in ("status", "setpoint", "drift"))]
    status = service.declare_publisher("afm/s1/status")
    try:
        results = {}
        for user in ("viewer", "op"):
            got.clear()
            seen: list[bytes] = []
            c = _client(cli, user, f"{user}-secret")
            try:
                w = c.declare_subscriber("afm/s1/status", lambda s: seen.append(s.payload.to_bytes()))
                deadline = time.monotonic() + 5
                while not seen and time.monotonic() < deadline:  # wait until connected and routed
                    status.put(b"{}")
                    time.sleep(0.05)
                c.put("afm/s1/trajectory", user.encode())
                for leaf in ("status", "setpoint", "drift"):
                    c.put(f"afm/s1/{leaf}", b"spoof " + user.encode())
                replies = [r.ok.payload.to_bytes() for r in c.get("afm/s1/cmd", timeout=1.0) if r.ok]
                time.sleep(0.2)
                results[user] = (bool(seen), list(got), replies)
                w.undeclare()
            finally:
                c.close()
        assert results["viewer"] == (True, [], [])            # watches, cannot command
        assert results["op"] == (True, [b"op"], [b"started"])
        assert spoofed == []        # nobody may publish on the service's own keys
    finally:
        for s in subs:
            s.undeclare()
        status.undeclare()
        service.close()


def test_open_session_error_is_one_line():
    from afmctl.zenoh_api.bridge import open_session
    srv, _ = loopback_pair()
    first = open_session(srv)
    try:
        with pytest.raises(AfmctlError, match="cannot open session"):
            open_session(srv)  # the port is taken
    finally:
        first.close()


def test_mtls_access_control_by_certificate_common_name(tmp_path):
    """Mutual TLS on loopback; only the certificate with CN 'operator' may put a trajectory."""
    import shutil
    from afmctl.zenoh_api.settings import TlsSettings, free_loopback_endpoint
    if shutil.which("openssl") is None:
        pytest.skip("openssl command not available to make test certificates")
    from afmctl.view.labstack import make_certificates
    make_certificates(tmp_path, ("service", "operator", "viewer"))
    endpoint = "tls/localhost:" + free_loopback_endpoint().rsplit(":", 1)[1]

    def tls(name):
        return TlsSettings(root_ca=tmp_path / "ca.pem", certificate=tmp_path / f"{name}.pem",
                           private_key=tmp_path / f"{name}.key", mtls=True)
    srv = ZenohSettings(listen=[endpoint], tls=tls("service"),
                        acl=AclSettings(enabled=True, operators=[AclSubject(id="ops", cert_common_names=["operator"])]))
    service = zenoh.open(srv.to_zenoh_config("s1"))
    got: list[bytes] = []
    sub = service.declare_subscriber("afm/s1/trajectory", lambda s: got.append(s.payload.to_bytes()))
    status = service.declare_publisher("afm/s1/status")
    results = {}
    try:
        for who in ("viewer", "operator"):
            got.clear()
            seen: list[int] = []
            c = zenoh.open(ZenohSettings(listen=[], connect=[endpoint], tls=tls(who)).to_zenoh_config())
            try:
                w = c.declare_subscriber("afm/s1/status", lambda s: seen.append(1))
                deadline = time.monotonic() + 5
                while not seen and time.monotonic() < deadline:
                    status.put(b"{}")
                    time.sleep(0.05)
                c.put("afm/s1/trajectory", who.encode())
                time.sleep(0.3)
                results[who] = (bool(seen), list(got))
                w.undeclare()
            finally:
                c.close()
    finally:
        sub.undeclare()
        status.undeclare()
        service.close()
    assert results == {"viewer": (True, []), "operator": (True, [b"operator"])}


def test_password_never_dumped_but_reaches_zenoh():
    s = ZenohSettings.model_validate({"auth": {"user": "op", "password": "s3cret"}})
    assert "s3cret" not in json.dumps(s.model_dump(mode="json")) and "s3cret" not in repr(s)
    assert json.loads(s.to_zenoh_config().get_json("transport/auth/usrpwd/password")) == "s3cret"


def _socket_inodes() -> set[str]:
    import os
    out = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            link = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            out.add(link[8:-1])
    return out


def _proc_net(name: str) -> dict[str, tuple[str, str]]:
    """inode -> (local address hex, state hex) from /proc/net/<name>."""
    rows = {}
    with open(f"/proc/net/{name}") as f:
        for line in f.read().splitlines()[1:]:
            fields = line.split()
            rows[fields[9]] = (fields[1], fields[3])
    return rows


@pytest.mark.skipif(not __import__("os").path.exists("/proc/self/fd"), reason="needs Linux /proc")
def test_default_session_opens_only_a_loopback_listener():
    """The zenoh.Config the defaults produce, dumped and opened: one TCP listener on
    127.0.0.1, no UDP socket (no multicast scouting), no admin space."""
    srv, _ = loopback_pair()
    cfg = srv.to_zenoh_config()
    dump = json.loads(str(cfg))
    assert dump["mode"] == "peer" and dump["connect"]["endpoints"] == []
    assert dump["listen"]["endpoints"] == srv.listen and srv.listen[0].startswith("tcp/127.0.0.1:")
    assert dump["scouting"]["multicast"]["enabled"] is False and dump["scouting"]["gossip"]["enabled"] is False
    assert dump["adminspace"]["enabled"] is False and dump["plugins"] == {}
    before = _socket_inodes()
    session = zenoh.open(cfg)
    try:
        time.sleep(0.3)
        new = _socket_inodes() - before
        tcp = {i: r for i, r in {**_proc_net("tcp"), **_proc_net("tcp6")}.items() if i in new}
        udp = {i: r for i, r in {**_proc_net("udp"), **_proc_net("udp6")}.items() if i in new}
    finally:
        session.close()
    port = int(srv.listen[0].rsplit(":", 1)[1])
    assert list(tcp.values()) == [(f"0100007F:{port:04X}", "0A")]   # 127.0.0.1:port, LISTEN
    assert udp == {}


def test_huge_payloads_are_dropped_by_zenoh_before_reassembly():
    """zenoh's own receive limit (4 × max_message_bytes; zenoh's default is 1 GiB):
    a payload just above max_message_bytes still arrives (the bridge reports it on
    status), one far above it never reaches the service's callbacks."""
    from afmctl.zenoh_api.settings import RX_LIMIT_FACTOR
    srv, cli = loopback_pair(ZenohSettings(max_message_bytes=4096))
    assert json.loads(srv.to_zenoh_config().get_json("transport/link/rx/max_message_size")) == RX_LIMIT_FACTOR * 4096
    service = zenoh.open(srv.to_zenoh_config("s1"))
    sizes: list[int] = []
    sub = service.declare_subscriber("afm/s1/trajectory", lambda s: sizes.append(len(s.payload.to_bytes())))
    conf = cli.to_zenoh_config()
    conf.insert_json5("transport/shared_memory/enabled", "false")  # a remote peer: fragmented over TCP
    client = zenoh.open(conf)
    try:
        deadline = time.monotonic() + 5
        while not sizes and time.monotonic() < deadline:   # until connected and routed
            client.put("afm/s1/trajectory", b"x")
            time.sleep(0.05)
        sizes.clear()
        block = zenoh.CongestionControl.BLOCK
        client.put("afm/s1/trajectory", b"a" * 5000, congestion_control=block)            # above, near
        client.put("afm/s1/trajectory", b"b" * 200_000, congestion_control=block)         # far above
        client.put("afm/s1/trajectory", b"c", congestion_control=block)                   # still alive
        deadline = time.monotonic() + 5
        while 1 not in sizes and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        sub.undeclare()
        client.close()
        service.close()
    assert sizes == [5000, 1]
