"""Zenoh settings of the afmctl service (the ``[zenoh]`` table of the configuration).

:class:`ZenohSettings` is plain pydantic and imports nothing heavy: ``zenoh`` is imported
only inside :meth:`ZenohSettings.to_zenoh_config`.

Safe defaults (see docs/ZENOH.md):

* peer mode, multicast and gossip scouting **off** — nobody is discovered, nobody
  discovers us unless an endpoint is configured explicitly;
* listen only on ``tcp/127.0.0.1:7447`` (loopback);
* access control off; when switched on it is **deny by default**, and only the configured
  ``operators`` may put on ``<prefix>/<scanner>/trajectory`` and ``.../temperature`` and
  query ``.../cmd``; ``observers`` (by default: every connected peer) may subscribe to
  ``setpoint``, ``drift``, ``status`` and ``sim/**``.

Subjects are matched by zenoh itself: by TLS certificate common name
(``cert_common_names``, needs TLS/mTLS), by user name of the user-password authentication
(``usernames``), or by local network interface (``interfaces``). Inside one subject the
lists are AND-ed, the entries of a list OR-ed; an omitted list matches anything.
"""
from __future__ import annotations

import json
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator

if TYPE_CHECKING:  # pragma: no cover
    import zenoh

#: protocols a zenoh endpoint may use here
ENDPOINT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "unixsock-stream", "ws")

#: zenoh's receive (defragmentation) limit, as a multiple of ``max_message_bytes``
RX_LIMIT_FACTOR = 4

_ENDPOINT_RE = re.compile(r"^(?P<proto>[a-z\-]+)/(?P<addr>.+)$")
_KEY_CHUNK_RE = re.compile(r"^[A-Za-z0-9_\-.]+$")


def _check_endpoint(value: str) -> str:
    m = _ENDPOINT_RE.match(value)
    if not m or m.group("proto") not in ENDPOINT_PROTOCOLS:
        raise ValueError(
            f"endpoint {value!r} must look like 'tcp/127.0.0.1:7447' "
            f"(protocol one of {', '.join(ENDPOINT_PROTOCOLS)})")
    proto, addr = m.group("proto"), m.group("addr")
    if proto != "unixsock-stream":
        host, sep, port = addr.split("#", 1)[0].rpartition(":")
        if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
            raise ValueError(f"endpoint {value!r}: needs HOST:PORT with port 0..65535")
    return value


class TlsSettings(BaseModel):
    """TLS / mutual TLS for ``tls/...`` endpoints (PEM files).

    The service presents ``certificate``/``private_key`` when listening and when connecting;
    with ``mtls = true`` it also demands a client certificate signed by ``root_ca``, whose
    common name the access-control ``cert_common_names`` match.
    """

    model_config = ConfigDict(extra="forbid")

    root_ca: Path | None = Field(None, description="PEM file of the CA that signs the peers' certificates")
    certificate: Path | None = Field(None, description="PEM certificate this service presents")
    private_key: Path | None = Field(None, description="PEM private key of `certificate`")
    mtls: bool = Field(False, description="require and verify a client certificate (mutual TLS)")
    verify_name_on_connect: bool = Field(True, description="check the server name against its certificate when connecting")

    @property
    def configured(self) -> bool:
        return any(p is not None for p in (self.root_ca, self.certificate, self.private_key))

    @model_validator(mode="after")
    def _pairs(self) -> "TlsSettings":
        if (self.certificate is None) != (self.private_key is None):
            raise ValueError("tls.certificate and tls.private_key must be given together")
        if self.mtls and (self.root_ca is None or self.certificate is None):
            raise ValueError("tls.mtls needs tls.root_ca, tls.certificate and tls.private_key")
        return self


class UserPasswordSettings(BaseModel):
    """zenoh user-password authentication.

    ``user``/``password``: the credentials this session presents when it connects to
    others; ``dictionary_file``: a text file of ``user:password`` lines accepted from peers
    that connect to us (only they can be matched by ``usernames`` in access control).
    """

    model_config = ConfigDict(extra="forbid")

    user: str | None = None
    password: SecretStr | None = Field(None, description="shown as ********** in dumps and run logs")
    dictionary_file: Path | None = None

    @property
    def configured(self) -> bool:
        return self.user is not None or self.dictionary_file is not None

    @model_validator(mode="after")
    def _pair(self) -> "UserPasswordSettings":
        if (self.user is None) != (self.password is None):
            raise ValueError("auth.user and auth.password must be given together")
        return self


class AclSubject(BaseModel):
    """Who a rule applies to. Lists AND-ed with each other, entries OR-ed; omitted = any."""

    model_config = ConfigDict(extra="forbid")

    id: str = Field(..., min_length=1, description="a unique name for this subject")
    cert_common_names: list[str] | None = Field(None, description="TLS certificate common names (needs TLS)")
    usernames: list[str] | None = Field(None, description="user names of the user-password authentication")
    interfaces: list[str] | None = Field(None, description="local network interfaces, e.g. 'lo', 'eth0'")

    def to_zenoh(self) -> dict[str, Any]:
        out: dict[str, Any] = {"id": self.id}
        for name in ("cert_common_names", "usernames", "interfaces"):
            value = getattr(self, name)
            if value is not None:
                out[name] = list(value)
        return out


class AclSettings(BaseModel):
    """Access control of the service session (zenoh ``access_control``), deny by default.

    ``operators`` may command the scanner (put ``trajectory`` and ``temperature``, query
    ``cmd``). ``observers`` may subscribe to what the service publishes; by default every
    peer that can connect at all. Anything not allowed is dropped by zenoh.
    """

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(False, description="switch access control on (then deny by default)")
    operators: list[AclSubject] = Field(default_factory=list,
                                        description="subjects allowed to put trajectory/temperature and query cmd")
    observers: list[AclSubject] = Field(default_factory=lambda: [AclSubject(id="anyone")],
                                        description="subjects allowed to subscribe to setpoint/drift/status/sim")

    @model_validator(mode="after")
    def _unique_ids(self) -> "AclSettings":
        ids = [s.id for s in self.operators] + [s.id for s in self.observers]
        dup = {i for i in ids if ids.count(i) > 1}
        # the same subject may appear in both lists only if it is the identical object
        for i in dup:
            found = [s for s in self.operators + self.observers if s.id == i]
            if any(f != found[0] for f in found):
                raise ValueError(f"acl: subject id {i!r} used twice with different definitions")
        return self


class ZenohSettings(BaseModel):
    """The service's zenoh session and API (``[zenoh]`` in the TOML configuration).

    Example (TOML)::

        [zenoh]
        enabled = true
        listen = ["tcp/127.0.0.1:7447"]
        [zenoh.acl]
        enabled = true
        operators = [{ id = "stage-ui", usernames = ["ui"] }]
    """

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(False, description="start the zenoh API with the service")
    mode: Literal["peer", "client", "router"] = Field(
        "peer", description="peer (default, no router needed), client (through a router) or router (many scanners)")
    prefix: str = Field("afm", description="first key chunk(s): keys are <prefix>/<scanner>/setpoint ...")
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"],
                              description="endpoints to listen on; default loopback only")
    connect: list[str] = Field(default_factory=list, description="endpoints of peers/routers to connect to")
    multicast_scouting: bool = Field(False, description="UDP multicast discovery (off: nothing is announced)")
    gossip_scouting: bool = Field(False, description="learn peers from peers (off by default)")
    tls: TlsSettings = Field(default_factory=TlsSettings)
    auth: UserPasswordSettings = Field(default_factory=UserPasswordSettings)
    acl: AclSettings = Field(default_factory=AclSettings)
    setpoint_batch: int = Field(256, ge=1, le=65536, description="samples per published setpoint batch")
    max_message_bytes: int = Field(4 * 1024 * 1024, ge=1024, le=256 * 1024 * 1024,
                                   description="incoming payloads larger than this are rejected")
    max_segment_samples: int = Field(1_000_000, ge=1, le=50_000_000,
                                     description="most samples one trajectory message may carry or generate")
    reconnect_period_s: float = Field(0.5, ge=0.05, le=60.0,
                                      description="how often a lost connect endpoint (a router) is retried [s]")

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, value: list[str]) -> list[str]:
        return [_check_endpoint(v) for v in value]

    @field_validator("prefix")
    @classmethod
    def _prefix(cls, value: str) -> str:
        chunks = value.split("/")
        if not value or not all(_KEY_CHUNK_RE.match(c) for c in chunks):
            raise ValueError(f"prefix {value!r}: key chunks of letters, digits, '_', '-', '.' separated by '/'")
        return value

    # ------------------------------------------------------------------ keys
    def key(self, scanner: str, leaf: str) -> str:
        """``<prefix>/<scanner>/<leaf>``, e.g. ``afm/stage1/setpoint``."""
        if not _KEY_CHUNK_RE.match(scanner):
            raise ValueError(f"scanner name {scanner!r}: letters, digits, '_', '-', '.' only")
        return f"{self.prefix}/{scanner}/{leaf}"

    # ------------------------------------------------------------------ zenoh
    def acl_json(self, scanner: str | None = None) -> dict[str, Any]:
        """The zenoh ``access_control`` object (deny by default) for ``scanner`` (``*`` = all)."""
        s = scanner or "*"
        k = lambda leaf: f"{self.prefix}/{s}/{leaf}"  # noqa: E731
        subjects: dict[str, dict[str, Any]] = {}
        for subj in self.acl.operators + self.acl.observers:
            subjects[subj.id] = subj.to_zenoh()
        everyone = "afmctl-any-peer"
        subjects.setdefault(everyone, {"id": everyone})
        rules = [
            # the service announces its subscribers/queryable to every peer; whether a
            # peer may then use them is decided by the ingress rules below
            {"id": "afmctl-declare", "permission": "allow", "flows": ["egress"],
             "messages": ["declare_subscriber", "declare_queryable"],
             "key_exprs": [k("trajectory"), k("temperature"), k("cmd")]},
            # observers: may subscribe (ingress declaration) and receive (egress put) the
            # published keys; nobody else may put on them (no spoofed status/setpoints)
            {"id": "afmctl-observe-declare", "permission": "allow", "flows": ["ingress"],
             "messages": ["declare_subscriber"],
             "key_exprs": [k("setpoint"), k("drift"), k("status"), k("sim/**")]},
            {"id": "afmctl-observe-receive", "permission": "allow", "flows": ["egress"],
             "messages": ["put"],
             "key_exprs": [k("setpoint"), k("drift"), k("status"), k("sim/**")]},
            # operators: may put (ingress) on trajectory/temperature, query cmd and get the reply
            {"id": "afmctl-operate", "permission": "allow", "flows": ["ingress"],
             "messages": ["put", "query"],
             "key_exprs": [k("trajectory"), k("temperature"), k("cmd")]},
            {"id": "afmctl-operate-reply", "permission": "allow", "flows": ["egress"],
             "messages": ["reply"], "key_exprs": [k("cmd")]},
        ]
        observe = ["afmctl-observe-declare", "afmctl-observe-receive"]
        operate = ["afmctl-operate", "afmctl-operate-reply"]
        policies = [{"id": "afmctl-declare", "rules": ["afmctl-declare"], "subjects": [everyone]}]
        if self.acl.observers:
            policies.append({"id": "afmctl-observers", "rules": observe,
                             "subjects": [o.id for o in self.acl.observers]})
        if self.acl.operators:
            # operators also observe, unless a wildcard observer subject already covers them
            # (zenoh checks a rule twice when two subjects match one peer)
            wildcard = any(o.cert_common_names is None and o.usernames is None and o.interfaces is None
                           for o in self.acl.observers)
            rules_op = operate if wildcard else operate + observe
            policies.append({"id": "afmctl-operators", "rules": rules_op,
                             "subjects": [o.id for o in self.acl.operators]})
        return {"enabled": True, "default_permission": "deny", "rules": rules,
                "subjects": list(subjects.values()), "policies": policies}

    def to_json(self, scanner: str | None = None) -> dict[str, Any]:
        """The zenoh configuration as a JSON object (inserted key by key into zenoh.Config)."""
        out: dict[str, Any] = {
            "mode": self.mode,
            "listen/endpoints": list(self.listen),
            "connect/endpoints": list(self.connect),
            "scouting/multicast/enabled": self.multicast_scouting,
            "scouting/gossip/enabled": self.gossip_scouting,
            # zenoh reassembles fragmented messages up to this size (its default: 1 GiB);
            # above our own limit the bridge still sees the payload and reports it on
            # status, far above it zenoh drops it before it fills the memory
            "transport/link/rx/max_message_size": RX_LIMIT_FACTOR * self.max_message_bytes,
            # a lost router is retried every reconnect_period_s (zenoh's default backs off to 4 s)
            "connect/retry": {"period_init_ms": round(1000 * self.reconnect_period_s),
                              "period_max_ms": round(1000 * self.reconnect_period_s), "period_increase_factor": 1},
        }
        if self.tls.configured:
            t = self.tls
            tls: dict[str, Any] = {}
            if t.root_ca is not None:
                tls["root_ca_certificate"] = str(t.root_ca)
            if t.certificate is not None:
                tls["listen_certificate"] = str(t.certificate)
                tls["listen_private_key"] = str(t.private_key)
                tls["connect_certificate"] = str(t.certificate)
                tls["connect_private_key"] = str(t.private_key)
            tls["enable_mtls"] = t.mtls
            tls["verify_name_on_connect"] = t.verify_name_on_connect
            for name, value in tls.items():
                out[f"transport/link/tls/{name}"] = value
        if self.auth.configured:
            a = self.auth
            if a.user is not None:
                out["transport/auth/usrpwd/user"] = a.user
                out["transport/auth/usrpwd/password"] = a.password.get_secret_value() if a.password else None
            if a.dictionary_file is not None:
                out["transport/auth/usrpwd/dictionary_file"] = str(a.dictionary_file)
        if self.acl.enabled:
            out["access_control"] = self.acl_json(scanner)
        return out

    def to_zenoh_config(self, scanner: str | None = None) -> "zenoh.Config":
        """Build a ``zenoh.Config``; a bad value raises :class:`afmctl.errors.AfmctlError`."""
        import zenoh

        from ..errors import AfmctlError
        config = zenoh.Config()
        for key, value in self.to_json(scanner).items():
            try:
                config.insert_json5(key, json.dumps(value))
            except Exception as err:  # zenoh raises its own ZError
                raise AfmctlError(f"zenoh.{key}: rejected by zenoh ({' '.join(str(err).split())})") from None
        return config


def free_loopback_endpoint() -> str:
    """``tcp/127.0.0.1:PORT`` with a port that was free a moment ago (for tests and demos)."""
    import socket
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def loopback_pair(server: ZenohSettings | None = None, **client: Any) -> tuple[ZenohSettings, ZenohSettings]:
    """Settings for a service listening on a fresh loopback port and a client connecting to it."""
    endpoint = free_loopback_endpoint()
    srv = (server or ZenohSettings()).model_copy(update={"listen": [endpoint]})
    cli = ZenohSettings(listen=[], connect=[endpoint], **client)
    return srv, cli
