"""A zenoh router for a lab of scanners (``afmctl router``, docs/ZENOH.md *A lab*).

The router is zenoh's own — a session opened in ``mode = "router"`` by the installed
eclipse-zenoh package — configured from :class:`RouterSettings` (the ``[router]`` table
of a TOML file): listen and connect endpoints (other routers: another room), TLS / mutual
TLS, user/password authentication, and the lab's access-control file
(:mod:`afmctl.zenoh_api.lab_acl`), applied at the router. Defaults: listen on loopback
only, scouting off, and without an ACL file everyone may serve and watch but nobody may
command (:func:`afmctl.zenoh_api.lab_acl.default_acl`).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from ..errors import AfmctlError
from .lab_acl import LabAcl, default_acl, load_acl
from .settings import TlsSettings, UserPasswordSettings, ZenohSettings, _check_endpoint

log = logging.getLogger(__name__)


class RouterSettings(BaseModel):
    """The ``[router]`` table of ``afmctl router --config FILE.toml``.

    Example (TOML)::

        [router]
        listen = ["tcp/127.0.0.1:7447"]
        connect = []                      # routers of other rooms, e.g. ["tcp/10.0.2.1:7447"]
        acl = "lab-acl.toml"              # relative to this file
        [router.auth]
        dictionary_file = "users.txt"     # user:password lines accepted from the lab's sessions
    """

    model_config = ConfigDict(extra="forbid")

    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"],
                              description="endpoints to listen on; default loopback only")
    connect: list[str] = Field(default_factory=list, description="routers of other rooms to link with")
    acl: Path | None = Field(None, description="the lab's access-control file (TOML); none: nobody may command")
    prefix: str = Field("afm", description="key prefix of the lab's services (the default ACL's)")
    tls: TlsSettings = Field(default_factory=TlsSettings)
    auth: UserPasswordSettings = Field(default_factory=UserPasswordSettings)
    reconnect_period_s: float = Field(0.5, ge=0.05, le=60.0,
                                      description="how often a lost link to another router is retried [s]")

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, value: list[str]) -> list[str]:
        return [_check_endpoint(v) for v in value]

    def zenoh_settings(self) -> ZenohSettings:
        """The router's session as :class:`ZenohSettings` (mode router, scouting off)."""
        return ZenohSettings(enabled=True, mode="router", prefix=self.prefix, listen=self.listen,
                             connect=self.connect, tls=self.tls, auth=self.auth,
                             reconnect_period_s=self.reconnect_period_s)

    def access_control(self) -> LabAcl:
        return load_acl(self.acl) if self.acl is not None else default_acl(self.prefix)

    def to_json(self) -> dict[str, Any]:
        """The zenoh configuration (key -> value, as inserted into ``zenoh.Config``)."""
        out = self.zenoh_settings().to_json()
        out["access_control"] = self.access_control().to_zenoh()
        return out

    def to_zenoh_config(self) -> Any:
        return config_from_json(self.to_json())


def config_from_json(values: dict[str, Any]) -> Any:
    """A ``zenoh.Config`` from key -> value; a value zenoh refuses is an :class:`AfmctlError`."""
    import zenoh
    config = zenoh.Config()
    for key, value in values.items():
        try:
            config.insert_json5(key, json.dumps(value))
        except Exception as err:  # zenoh raises its own ZError
            raise AfmctlError(f"router.{key}: rejected by zenoh ({' '.join(str(err).split())})") from None
    return config


def load_router_settings(path: str | Path | None, overrides: dict[str, Any] | None = None) -> RouterSettings:
    """The ``[router]`` table of ``path`` (None: defaults) with ``overrides`` on top; paths
    in the file are relative to it. Bad input: :class:`AfmctlError` naming the field."""
    from afmctl.compensators.errortext import validation_error_line
    from afmctl.compensators.textfiles import read_text_file

    from ..config import parse_toml
    table: dict[str, Any] = {}
    where, base = "command line", Path.cwd()
    if path is not None:
        p = Path(path)
        where, base = str(p), p.resolve().parent
        data = parse_toml(read_text_file(p, "router configuration", AfmctlError), where)
        unknown = set(data) - {"router"}
        if unknown:
            raise AfmctlError(f"{where}: unknown table(s) {', '.join(sorted(unknown))}; allowed: [router]")
        table = dict(data.get("router", {}))
    table.update({k: v for k, v in (overrides or {}).items() if v is not None})
    try:
        settings = RouterSettings.model_validate(table)
    except ValidationError as err:
        raise AfmctlError(f"{where}: {validation_error_line(err, 'router.').replace('Value error, ', '')}") from None
    fix = lambda q: q if q is None or q.is_absolute() else base / q  # noqa: E731
    settings.acl = fix(settings.acl)
    settings.auth.dictionary_file = fix(settings.auth.dictionary_file)
    settings.tls.root_ca = fix(settings.tls.root_ca)
    settings.tls.certificate = fix(settings.tls.certificate)
    settings.tls.private_key = fix(settings.tls.private_key)
    return settings


class Router:
    """A running zenoh router: ``with Router(settings) as r: ...`` (or :meth:`close`).
    The session is opened at once; a port that is taken is an :class:`AfmctlError`."""

    def __init__(self, settings: RouterSettings) -> None:
        import zenoh
        self.settings = settings
        config = settings.to_zenoh_config()
        try:
            self.session = zenoh.open(config)
        except Exception as err:  # zenoh.ZError: e.g. the port is taken
            raise AfmctlError(f"router: cannot start ({' '.join(str(err).split())}); "
                              f"check router.listen {settings.listen}") from None
        log.info("zenoh router %s listening on %s", self.session.zid(), ", ".join(settings.listen))

    def close(self) -> None:
        self.session.close()

    def __enter__(self) -> "Router":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
