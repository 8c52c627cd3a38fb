"""The lab's access-control file (TOML) and its translation to zenoh's ``access_control``.

``afmctl router --acl lab-acl.toml`` decides at the router who may do what with which
scanner (docs/ZENOH.md, *A lab*). The file names subjects — who connects, matched by zenoh
by user name (user/password authentication), TLS certificate common name (mTLS) and/or
network interface — and gives them roles:

* ``services`` of a scanner may *be* it: publish its ``setpoint``, ``drift``, ``status``,
  ``learn`` and ``sim/**``, serve its ``cmd`` and ``status`` queryables, subscribe to its
  ``trajectory`` and ``temperature``, declare its liveliness token ``alive``
  (``afmctl run``, ``sim``, ``learn``);
* ``operators`` of a scanner may command it: put ``trajectory`` and ``temperature``, query
  ``cmd`` (and get the reply); an operator also observes every scanner;
* ``observers`` may watch every scanner: subscribe to what services publish, query
  ``status``, watch the ``alive`` tokens — and nothing else;
* ``routers``: linked routers (another room): everything under the prefix passes.

Example::

    observers = ["watchers"]
    [subjects]
    stage1-svc = { usernames = ["svc-stage1"] }
    alice = { usernames = ["alice"] }
    watchers = { usernames = ["viewer", "watcher"] }
    [scanners.stage1]
    services = ["stage1-svc"]
    operators = ["alice"]

Anything not allowed is denied (``default_permission = "deny"``): a subject that is no
operator of a scanner cannot command it, whatever it sends. The scanner name ``"*"`` stands
for every scanner. Without a file the router uses :func:`default_acl`: everyone who can
connect may serve and watch, nobody may command.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from ..errors import AfmctlError
from .settings import _KEY_CHUNK_RE

#: keys a scanner's services publish (leaf after ``<prefix>/<scanner>/``)
PUBLISHED = ("setpoint", "drift", "status", "learn", "sim/**")
#: keys a scanner's operators put on, and the query they may make
COMMAND_PUTS = ("trajectory", "temperature")
COMMAND_QUERY = "cmd"
#: the liveliness token of every running service of a scanner, and the status queryable
ALIVE = "alive"
STATUS = "status"

_NAME_RE = _KEY_CHUNK_RE      # a key chunk: what a scanner name or a subject id may hold
_SUBJECT_FIELDS = ("usernames", "cert_common_names", "interfaces")


class AclSubjectSpec(BaseModel):
    """Who connects: lists AND-ed with each other, entries OR-ed; an omitted list matches
    anything (``{}``: every session that can connect at all)."""

    model_config = ConfigDict(extra="forbid")

    usernames: list[str] | None = Field(None, min_length=1, description="user names of user/password authentication")
    cert_common_names: list[str] | None = Field(None, min_length=1, description="TLS certificate common names (mTLS)")
    interfaces: list[str] | None = Field(None, min_length=1, description="the router's network interfaces, e.g. 'lo'")


class ScannerAccess(BaseModel):
    """Who may be (``services``) and who may command (``operators``) one scanner."""

    model_config = ConfigDict(extra="forbid")

    services: list[str] = Field(default_factory=list, description="subjects that may run, simulate or learn it")
    operators: list[str] = Field(default_factory=list, description="subjects that may command it")


class LabAcl(BaseModel):
    """The lab's access-control file (module docstring)."""

    model_config = ConfigDict(extra="forbid")

    prefix: str = Field("afm", description="first key chunk(s), as zenoh.prefix of the services")
    subjects: dict[str, AclSubjectSpec] = Field(default_factory=dict, description="subject id -> who it matches")
    observers: list[str] = Field(default_factory=list, description="subjects that may watch every scanner")
    routers: list[str] = Field(default_factory=list, description="linked routers: everything under the prefix")
    scanners: dict[str, ScannerAccess] = Field(default_factory=dict, description="scanner name ('*': all) -> roles")

    @field_validator("prefix")
    @classmethod
    def _prefix(cls, value: str) -> str:
        if not value or not all(_NAME_RE.match(c) for c in value.split("/")):
            raise ValueError(f"{value!r}: key chunks of letters, digits, '_', '-', '.' separated by '/'")
        return value

    @field_validator("subjects", "scanners")
    @classmethod
    def _names(cls, value: dict[str, Any], info: ValidationInfo) -> dict[str, Any]:
        what = "subject id" if info.field_name == "subjects" else "scanner"
        for name in value:
            if not _NAME_RE.match(name) and not (what == "scanner" and name == "*"):
                raise ValueError(f"{what} {name!r}: letters, digits, '_', '-', '.' only"
                                 + (" (or '*': every scanner)" if what == "scanner" else ""))
        return value

    @model_validator(mode="after")
    def _known_subjects(self) -> "LabAcl":
        known = set(self.subjects)
        refs = [("observers", self.observers), ("routers", self.routers)]
        for name, access in self.scanners.items():
            refs += [(f"scanners.{name}.services", access.services), (f"scanners.{name}.operators", access.operators)]
        for where, ids in refs:
            for sid in ids:
                if sid not in known:
                    raise ValueError(f"{where}: unknown subject {sid!r} (defined in [subjects]: "
                                     f"{', '.join(sorted(known)) or 'none'})")
        return self

    # ------------------------------------------------------------------ zenoh
    def key(self, scanner: str, leaf: str) -> str:
        return f"{self.prefix}/{scanner}/{leaf}"

    def to_zenoh(self) -> dict[str, Any]:
        """zenoh's ``access_control`` object for the router (deny by default)."""
        rules: list[dict[str, Any]] = []
        policies: list[dict[str, Any]] = []

        def rule(rid: str, flow: str, messages: list[str], keys: list[str]) -> str:
            rules.append({"id": rid, "permission": "allow", "flows": [flow], "messages": messages,
                          "key_exprs": keys})
            return rid

        def policy(pid: str, rule_ids: list[str], subject_ids: list[str]) -> None:
            if subject_ids:
                policies.append({"id": pid, "rules": rule_ids, "subjects": sorted(set(subject_ids))})

        everything = [f"{self.prefix}/**"]
        # declarations of subscribers and queryables reveal interest, not data: they pass to
        # everyone, so that a service learns that someone listens (zenoh's clients do not
        # send what nobody subscribes to); whether data then flows is decided by the rules below
        declare = rule("declarations-out", "egress", ["declare_subscriber", "declare_queryable"], everything)
        policy("everyone-declarations", [declare], list(self.subjects))
        observe = self._observe_rules(rule)
        operators = sorted({s for a in self.scanners.values() for s in a.operators})
        policy("observers", observe, self.observers + operators)
        for name, access in sorted(self.scanners.items()):
            tag = "all" if name == "*" else name
            policy(f"services-{tag}", self._service_rules(rule, name, tag), access.services)
            policy(f"operators-{tag}", self._operator_rules(rule, name, tag), access.operators)
        if self.routers:
            link = [rule(f"routers-{flow}", flow, ["put", "delete", "declare_subscriber", "query", "reply",
                                                  "declare_queryable", "liveliness_token", "liveliness_query",
                                                  "declare_liveliness_subscriber"], everything)
                    for flow in ("ingress", "egress")]
            policy("routers", link, self.routers)
        subjects = [{"id": sid, **spec.model_dump(exclude_none=True)} for sid, spec in sorted(self.subjects.items())]
        used = {rid for p in policies for rid in p["rules"]}
        rules = [r for r in rules if r["id"] in used]       # a role nobody has grants nothing
        return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
                "policies": policies}

    def _observe_rules(self, rule: Any) -> list[str]:
        published = [self.key("*", leaf) for leaf in PUBLISHED]
        alive, status = self.key("*", ALIVE), self.key("*", STATUS)
        return [rule("observe-subscribe", "ingress", ["declare_subscriber"], published),
                rule("observe-receive", "egress", ["put"], published),
                rule("observe-status-query", "ingress", ["query"], [status]),
                rule("observe-status-reply", "egress", ["reply"], [status]),
                rule("observe-alive-watch", "ingress", ["declare_liveliness_subscriber", "liveliness_query"], [alive]),
                rule("observe-alive-receive", "egress", ["liveliness_token"], [alive])]

    def _service_rules(self, rule: Any, name: str, tag: str) -> list[str]:
        key = lambda leaf: self.key(name, leaf)  # noqa: E731
        commands = [key(leaf) for leaf in COMMAND_PUTS]
        queryables = [key(COMMAND_QUERY), key(STATUS)]
        return [rule(f"serve-{tag}-publish", "ingress", ["put"], [key(leaf) for leaf in PUBLISHED]),
                rule(f"serve-{tag}-subscribe", "ingress", ["declare_subscriber"], commands),
                rule(f"serve-{tag}-queryables", "ingress", ["declare_queryable", "reply"], queryables),
                rule(f"serve-{tag}-alive", "ingress", ["liveliness_token"], [key(ALIVE)]),
                rule(f"serve-{tag}-inputs", "egress", ["put"], commands),
                rule(f"serve-{tag}-queries", "egress", ["query"], [*queryables, self.key("*", STATUS)])]

    def _operator_rules(self, rule: Any, name: str, tag: str) -> list[str]:
        key = lambda leaf: self.key(name, leaf)  # noqa: E731
        return [rule(f"operate-{tag}-put", "ingress", ["put"], [key(leaf) for leaf in COMMAND_PUTS]),
                rule(f"operate-{tag}-query", "ingress", ["query"], [key(COMMAND_QUERY)]),
                rule(f"operate-{tag}-reply", "egress", ["reply"], [key(COMMAND_QUERY)])]


def default_acl(prefix: str = "afm") -> LabAcl:
    """The router's ACL without a file: every session that connects may serve and watch any
    scanner; nobody may command one (deny by default for commands)."""
    return LabAcl(prefix=prefix, subjects={"anyone": AclSubjectSpec()}, observers=["anyone"],
                  scanners={"*": ScannerAccess(services=["anyone"])})


def load_acl(path: str | Path) -> LabAcl:
    """Read and validate an ACL file; a bad one raises :class:`AfmctlError` (one line naming
    the file and the field)."""
    from afmctl.compensators.errortext import validation_error_line
    from afmctl.compensators.textfiles import read_text_file

    from ..config import parse_toml
    p = Path(path)
    data = parse_toml(read_text_file(p, "access-control file", AfmctlError), str(p))
    try:
        return LabAcl.model_validate(data)
    except ValidationError as err:
        raise AfmctlError(f"{p}: {validation_error_line(err).replace('Value error, ', '')}") from None
