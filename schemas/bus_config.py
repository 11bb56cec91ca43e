"""Configuration of a zenoh session for the twin's bus.

The default is a peer on loopback with multicast and gossip scouting off and explicit endpoints:
nothing is discovered or exposed beyond what the configuration names. Router mode, remote
endpoints and the security options (user/password authentication, TLS and mutual TLS, access
control) are chosen by configuration only; :meth:`BusConfig.to_zenoh_dict` renders the zenoh
(1.x) configuration, which ``services.bus.open_session`` opens.

Example (YAML or JSON with the same fields)::

    mode: router
    listen: ["tls/127.0.0.1:7447"]
    tls: {root_ca_certificate: ca.pem, listen_certificate: router.pem,
          listen_private_key: router.key, enable_mtls: true}
    access_control:
      default_permission: deny
      rules:
        - {id: divert, permission: allow, key_exprs: ["twin/*/divert/command"],
           messages: [put], flows: [ingress, egress]}
      subjects: [{id: diverter, cert_common_names: [diverter]}]
      policies: [{rules: [divert], subjects: [diverter]}]
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from schemas.base import Ident, StrictModel

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
_PROTOCOLS = ("tcp", "udp", "tls", "quic", "unixsock-stream", "ws")


def _check_endpoint(value: str) -> str:
    proto, sep, rest = value.partition("/")
    if not sep or proto not in _PROTOCOLS or not rest:
        raise ValueError(
            f"endpoint must look like '<proto>/<address>' with proto in {_PROTOCOLS}, got {value!r}"
        )
    return value


def is_loopback(endpoint: str) -> bool:
    """Whether an endpoint (``<proto>/<host>:<port>``) names the loopback interface."""
    host = endpoint.partition("/")[2].rsplit(":", 1)[0].strip("[]").split("#")[0]
    return host == "localhost" or host.startswith("127.") or host == "::1"


class UserPassword(StrictModel):
    """User/password authentication (``transport/auth/usrpwd``).

    ``user``: the name this session presents, with its password read when the session opens
    from ``password_file`` (a file holding only the password, readable by its owner alone) or
    from the environment variable ``password_env``: a password is never written in a
    configuration file. ``dictionary_file``: a file of ``user:password`` lines that this session
    accepts from others (a listener; it needs no password of its own).
    """

    user: str | None = Field(None, min_length=1)
    password_file: Path | None = None
    password_env: str | None = Field(None, min_length=1)
    dictionary_file: Path | None = None

    @model_validator(mode="before")
    @classmethod
    def _no_inline_password(cls, data: Any) -> Any:
        if isinstance(data, dict) and "password" in data:
            raise ValueError(
                "password must not be written in a configuration; give password_file (a file "
                "readable by its owner only) or password_env (an environment variable), got an "
                "inline password"
            )
        return data

    @model_validator(mode="after")
    def _one_source(self) -> UserPassword:
        sources = [n for n in ("password_file", "password_env") if getattr(self, n) is not None]
        if len(sources) > 1:
            raise ValueError(f"give one of password_file and password_env, got {sources}")
        if (self.user is None) != (not sources):
            raise ValueError(
                "user and a password source (password_file or password_env) go together, got "
                f"user={self.user!r} and {sources or 'no password source'}"
            )
        if self.user is None and self.dictionary_file is None:
            raise ValueError("usrpwd must give a user or a dictionary_file, got neither")
        return self


class Tls(StrictModel):
    """TLS transport (``transport/link/tls``): PEM paths; ``enable_mtls`` requires client certs."""

    root_ca_certificate: Path
    listen_certificate: Path | None = None
    listen_private_key: Path | None = None
    connect_certificate: Path | None = None
    connect_private_key: Path | None = None
    enable_mtls: bool = False
    verify_name_on_connect: bool = True

    @model_validator(mode="after")
    def _pairs(self) -> Tls:
        for a, b in (
            ("listen_certificate", "listen_private_key"),
            ("connect_certificate", "connect_private_key"),
        ):
            if (getattr(self, a) is None) != (getattr(self, b) is None):
                raise ValueError(f"{a} and {b} must be given together, got only one of them")
        return self


AclMessage = Literal[
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]


class AclRule(StrictModel):
    id: Ident
    permission: Literal["allow", "deny"]
    key_exprs: list[str] = Field(min_length=1)
    messages: list[AclMessage] = Field(min_length=1)
    flows: list[Literal["ingress", "egress"]] = Field(default=["ingress", "egress"], min_length=1)


class AclSubject(StrictModel):
    """Who a rule applies to: any of interfaces, certificate common names, usernames."""

    id: Ident
    interfaces: list[str] | None = None
    cert_common_names: list[str] | None = None
    usernames: list[str] | None = None


class AclPolicy(StrictModel):
    rules: list[Ident] = Field(min_length=1)
    subjects: list[Ident] = Field(min_length=1)


class AccessControl(StrictModel):
    """Access control (zenoh ``access_control``), enforced by the session that has it."""

    enabled: bool = True
    default_permission: Literal["allow", "deny"] = "deny"
    rules: list[AclRule] = Field(default_factory=list)
    subjects: list[AclSubject] = Field(default_factory=list)
    policies: list[AclPolicy] = Field(default_factory=list)

    @model_validator(mode="after")
    def _references(self) -> AccessControl:
        rule_ids = {r.id for r in self.rules}
        subject_ids = {s.id for s in self.subjects}
        for p in self.policies:
            for r in p.rules:
                if r not in rule_ids:
                    raise ValueError(f"policies refer to unknown rule id, got {r!r}")
            for s in p.subjects:
                if s not in subject_ids:
                    raise ValueError(f"policies refer to unknown subject id, got {s!r}")
        return self


class BusConfig(StrictModel):
    """A zenoh session configuration for the twin.

    Attributes:
        mode: ``peer`` (default), ``client`` or ``router`` (a router forwards between the
            peers/clients connected to it and timestamps their samples).
        listen: endpoints to listen on, e.g. ``tcp/127.0.0.1:7447``.
        connect: endpoints to connect to (a peer retries a dead endpoint; a client fails).
        multicast_scouting, gossip_scouting: discovery; off by default.
        timestamping: zenoh HLC timestamps on samples.
        line: the line name used in key expressions (``twin/<line>/...``).
        usrpwd, tls, access_control: security options (None = off).
        allow_insecure_listen: accept listening on a non-loopback endpoint without TLS or
            user/password authentication (refused otherwise, :meth:`insecure_listeners`).
        extra: raw zenoh config entries (dotted path -> value) applied last, for anything not
            modelled here; unknown keys fail loudly when the session opens.
    """

    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=list)
    connect: list[str] = Field(default_factory=lambda: [DEFAULT_ENDPOINT])
    multicast_scouting: bool = False
    gossip_scouting: bool = False
    timestamping: bool = False
    line: Ident = "line1"
    usrpwd: UserPassword | None = None
    tls: Tls | None = None
    access_control: AccessControl | None = None
    allow_insecure_listen: bool = False
    extra: dict[str, Any] = Field(default_factory=dict)

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, value: list[str]) -> list[str]:
        return [_check_endpoint(v) for v in value]

    @model_validator(mode="after")
    def _client_needs_connect(self) -> BusConfig:
        if self.mode == "client" and not self.connect:
            raise ValueError("connect must name at least one endpoint in client mode, got []")
        return self

    @classmethod
    def loopback(cls, port: int, *, listen: bool, **kwargs: Any) -> BusConfig:
        """A loopback peer that listens on (``listen=True``) or connects to ``127.0.0.1:port``."""
        endpoint = f"tcp/127.0.0.1:{port}"
        if listen:
            return cls(listen=[endpoint], connect=[], **kwargs)
        return cls(listen=[], connect=[endpoint], **kwargs)

    def insecure_listeners(self) -> list[str]:
        """Listen endpoints reachable from other hosts (not loopback, not a local socket) with
        neither TLS nor user/password authentication on them."""
        if self.usrpwd is not None and self.usrpwd.dictionary_file is not None:
            return []
        return [
            ep
            for ep in self.listen
            if not ep.startswith(("tls/", "quic/", "unixsock-stream/")) and not is_loopback(ep)
        ]

    def to_zenoh_dict(self, password: str | None = None) -> dict[str, Any]:
        """The zenoh 1.x configuration as nested dicts (JSON-serialisable); ``password``: the
        user's password (``usrpwd``), read by the caller from its file or variable."""
        cfg: dict[str, Any] = {
            "mode": self.mode,
            "listen": {"endpoints": list(self.listen)},
            "connect": {"endpoints": list(self.connect)},
            "scouting": {
                "multicast": {"enabled": self.multicast_scouting},
                "gossip": {"enabled": self.gossip_scouting},
            },
            "timestamping": {"enabled": self.timestamping},
        }
        transport: dict[str, Any] = {}
        if self.usrpwd is not None:
            up: dict[str, Any] = {}
            if self.usrpwd.user is not None:
                if password is None:
                    raise ValueError(f"usrpwd.user {self.usrpwd.user!r} needs its password")
                up.update(user=self.usrpwd.user, password=password)
            if self.usrpwd.dictionary_file is not None:
                up["dictionary_file"] = str(self.usrpwd.dictionary_file)
            transport["auth"] = {"usrpwd": up}
        if self.tls is not None:
            tls = {
                k: (str(v) if isinstance(v, Path) else v)
                for k, v in self.tls.model_dump().items()
                if v is not None
            }
            transport["link"] = {"tls": tls}
        if transport:
            cfg["transport"] = transport
        if self.access_control is not None:
            cfg["access_control"] = self.access_control.model_dump(exclude_none=True)
        for dotted, value in self.extra.items():
            node = cfg
            parts = dotted.split("/") if "/" in dotted else dotted.split(".")
            for part in parts[:-1]:
                node = node.setdefault(part, {})
            node[parts[-1]] = value
        return cfg
