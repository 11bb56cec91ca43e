"""The live twin's bus is secure by default: per-run credentials and the access control that
``twin up`` gives its router.

Identities: every supervised service under its own name (``oos``, ``blender``, ...), ``plant``
(the virtual plant of ``twin replay``, or a bridge of the real line: the one source of
plant inputs), ``operator`` (``twin status``, ``twin alerts``, the dashboard, DEM job requests)
and ``record`` (``twin record``: reads everything, publishes only its own health). Each gets a
random password per run (:class:`RunCredentials`); the router accepts only those users
(zenoh user/password authentication) and enforces :func:`line_acl`, default deny:

- everyone may subscribe, fetch history (the advanced publishers' caches), ping the services
  and receive what the router forwards;
- an identity may publish only its own outputs (:func:`published_keys`): the diverter ``oos``
  alone its alerts and divert commands, the ``plant`` alone the configured feeders' flows, the
  configured sensor's concentration, the plant's events and blade speeds, the blender its
  predictions and the model it predicts with, the dem service its jobs' outputs and section
  models, ...; and its own health, liveliness token and ping under ``twin/<line>/service/<identity>/``;
- ``operator`` may request DEM jobs, which the ``dem`` service alone serves; the ``blender``
  may put a request (a section run at a blade speed outside its table of models).

Where the passwords are: the router's dictionary in memory (an anonymous memory file on Linux;
elsewhere a file readable by its owner only, removed as soon as the router has read it); a
service's in its environment (``TWIN_BUS_USER``, ``TWIN_BUS_PASSWORD``, set by the supervisor);
the tools' in ``<run dir>/credentials/<identity>`` (mode 0600, folder 0700), which ``twin
replay``, ``twin status`` and ``twin alerts`` find through the run's lock file
(``services.common.RunInfo``), or in the environment (``TWIN_BUS_USER`` with
``TWIN_BUS_PASSWORD`` or ``TWIN_BUS_PASSWORD_FILE``). ``line.json`` of a run holds no password.
"""

from __future__ import annotations

import os
import secrets
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import get_args

from schemas import keys
from schemas.bus_config import AccessControl, AclMessage, BusConfig, UserPassword
from schemas.line import LineSpec

#: identities of the tools (not supervised services)
TOOL_IDENTITIES = ("plant", "operator", "record")
#: environment variables of a session's identity
USER_ENV = "TWIN_BUS_USER"
PASSWORD_ENV = "TWIN_BUS_PASSWORD"
PASSWORD_FILE_ENV = "TWIN_BUS_PASSWORD_FILE"

_INGRESS = ["ingress"]
_EVERY_MESSAGE = list(get_args(AclMessage))


def published_keys(spec: LineSpec, identity: str) -> list[str]:
    """The keys ``identity`` may publish on (besides its own ``service/<identity>/*`` keys)."""
    line = spec.name
    outputs = {
        "oos": [keys.oos_alert(line), keys.divert_command(line)],
        "blender": [
            keys.predicted_concentration(line, "outlet"),
            keys.blender_model_in_use(line),
            keys.dem_requests(line),
        ],
        "rtd": [
            keys.rtd_estimate(line),
            keys.rtd_skipped(line),
            keys.adoption_progress(line, "rtd"),
        ],
        "closeloop": [keys.model_finding(line), keys.adoption_progress(line, "closeloop")],
        "trace": [keys.trace_outlet(line), keys.trace_batch(line)],
        "dem": [
            keys.dem_jobs(line, "progress"),
            keys.dem_jobs(line, "result"),
            keys.blender_model_update(line, "dem"),
        ],
        "operator": [keys.dem_requests(line)],
        "plant": [
            *(keys.feeder_flow(line, f.id) for f in spec.feeders),
            keys.measured_concentration(line, spec.sensor.id),
            keys.events(line),
            keys.blender_drives(line),
        ],
    }
    outputs["bridge"] = outputs["plant"]  # the OPC UA bridge is the plant's source of inputs
    if spec.feeder_mode == "simulate":
        outputs["feeder"] = [keys.feeder_flow(line, f.id) for f in spec.feeders]
    return outputs.get(identity, [])


def served_keys(spec: LineSpec, identity: str) -> list[str]:
    """Key expressions ``identity`` answers queries on (besides its own pings and caches)."""
    return [keys.dem_requests(spec.name)] if identity == "dem" else []


def _rule(rule_id: str, key_exprs: list[str], messages: list[str], flows: list[str]) -> dict:
    return {
        "id": rule_id,
        "permission": "allow",
        "key_exprs": key_exprs,
        "messages": messages,
        "flows": flows,
    }


def line_acl(spec: LineSpec, identities: list[str]) -> AccessControl:
    """The router's access control for these identities (module docstring), default deny."""
    line = spec.name
    everything = [keys.everything(line), keys.advanced(keys.everything(line))]
    rules = [
        _rule(
            "read",
            everything,
            ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            _INGRESS,
        ),
        _rule(
            "fetch",
            [keys.advanced(keys.everything(line)), keys.services_ping(line)],
            ["query"],
            _INGRESS,
        ),
        _rule("detect", [keys.advanced(keys.everything(line))], ["liveliness_token"], _INGRESS),
        _rule("forward", everything, _EVERY_MESSAGE, ["egress"]),
    ]
    policies = [{"rules": ["read", "fetch", "detect", "forward"], "subjects": ["everyone"]}]
    subjects = [{"id": "everyone", "usernames": list(identities)}]
    for who in identities:
        out = published_keys(spec, who)
        own = [*out, *(keys.advanced(k) for k in out), keys.service_keys(line, who)]
        rules += [
            _rule(f"{who}_publish", own, ["put", "delete"], _INGRESS),
            _rule(
                f"{who}_serve",
                own + served_keys(spec, who),
                ["declare_queryable", "reply", "liveliness_token"],
                _INGRESS,
            ),
        ]
        ids = [f"{who}_publish", f"{who}_serve"]
        if who == "operator":
            rules.append(_rule("operator_request", [keys.dem_requests(line)], ["query"], _INGRESS))
            ids.append("operator_request")
        subjects.append({"id": f"as_{who}", "usernames": [who]})
        policies.append({"rules": ids, "subjects": [f"as_{who}"]})
    return AccessControl.model_validate(
        {"default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
    )


@dataclass
class RunCredentials:
    """One random password per identity, for one run of ``twin up``."""

    passwords: dict[str, str]

    @classmethod
    def generate(cls, identities: list[str]) -> RunCredentials:
        return cls({who: secrets.token_urlsafe(24) for who in identities})

    def dictionary(self) -> bytes:
        """The router's ``user:password`` lines."""
        return "".join(f"{u}:{p}\n" for u, p in self.passwords.items()).encode()

    def write_tool_files(self, run_dir: Path) -> Path:
        """``<run_dir>/credentials/<tool>`` (mode 0600, folder 0700) for the tool identities;
        returns the folder."""
        folder = run_dir / "credentials"
        folder.mkdir(mode=0o700, exist_ok=True)
        for who in TOOL_IDENTITIES:
            if who in self.passwords:
                write_private(folder / who, self.passwords[who])
        return folder


def write_private(path: Path, text: str) -> None:
    """Write ``text`` to a new file readable and writable by its owner only (0600)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, text.encode())
    finally:
        os.close(fd)


class RouterDictionary:
    """The router's ``user:password`` dictionary where only the router reads it: an anonymous
    memory file (Linux ``memfd``, named by ``/proc/self/fd/<n>``), or else a 0600 file that
    :meth:`router_opened` removes once the router has read it. Close it when the router is
    closed."""

    def __init__(self, creds: RunCredentials, fallback_dir: Path) -> None:
        self._fd: int | None = None
        self._file: Path | None = None
        if hasattr(os, "memfd_create") and sys.platform.startswith("linux"):
            self._fd = os.memfd_create("twin-bus-users")
            os.write(self._fd, creds.dictionary())
            self.path = Path(f"/proc/self/fd/{self._fd}")
        else:
            self._file = fallback_dir / ".bus-users"
            write_private(self._file, creds.dictionary().decode())
            self.path = self._file

    def router_opened(self) -> None:
        """The router has read the dictionary: remove the fallback file."""
        if self._file is not None:
            self._file.unlink(missing_ok=True)
            self._file = None

    def close(self) -> None:
        self.router_opened()
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def secured_router(bus: BusConfig, spec: LineSpec, identities: list[str], dictionary: Path):
    """The router's session configuration with authentication and :func:`line_acl`."""
    return bus.model_copy(
        update={
            "usrpwd": UserPassword(dictionary_file=dictionary),
            "access_control": line_acl(spec, identities),
        }
    )


def as_identity(
    bus: BusConfig, user: str, *, password_file: Path | None = None, password_env: str | None = None
) -> BusConfig:
    """A client configuration presenting ``user`` with its password from a file or a variable."""
    up = UserPassword(user=user, password_file=password_file, password_env=password_env)
    return bus.model_copy(update={"usrpwd": up})


def identity_from_env(bus: BusConfig) -> BusConfig:
    """``bus`` presenting the identity of the environment (``TWIN_BUS_USER`` with
    ``TWIN_BUS_PASSWORD`` or ``TWIN_BUS_PASSWORD_FILE``), or ``bus`` as it is without one."""
    user = os.environ.get(USER_ENV)
    if not user:
        return bus
    if os.environ.get(PASSWORD_FILE_ENV):
        return as_identity(bus, user, password_file=Path(os.environ[PASSWORD_FILE_ENV]))
    return as_identity(bus, user, password_env=PASSWORD_ENV)


def service_bus(spec: LineSpec) -> BusConfig:
    """The bus of a service process: the router's client, as the identity its supervisor gave
    it in the environment."""
    return identity_from_env(spec.client_bus())


def tool_bus(spec: LineSpec, identity: str) -> BusConfig:
    """The bus of a tool (``twin replay``, ``twin record``, ``twin status``, ``twin alerts``, the
    dashboard) talking to the line's twin: a client of the router of the ``twin up`` of the line
    running here (its endpoints from the run's lock file, read at each call: a restarted twin
    may listen elsewhere), else of the line's configured endpoints; as the identity of the
    environment if it names one; else, with a secured running twin, as ``identity`` with its
    password from the run directory (a new run has new passwords); else without credentials
    (an open bus, or a twin elsewhere)."""
    from services.common import running_twin

    bus = spec.client_bus()
    info = running_twin(spec)
    if info is not None and info.listen:
        bus = bus.model_copy(update={"connect": list(info.listen)})
    if os.environ.get(USER_ENV):
        return identity_from_env(bus)
    if info is None or not info.secure:
        return bus
    return as_identity(bus, identity, password_file=Path(info.run_dir) / "credentials" / identity)
