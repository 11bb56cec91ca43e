"""A plant on loopback that speaks OPC UA: :class:`LoopbackPlant` serves a recording as a PLC
would, for tests, demos and benchmarks of ``twin bridge opcua``.

An asyncua server (the same library as the bridge) with one variable per mapped field (feeder
mass flow, set point, screw speed, hopper mass, feed factor, refill flag; the NIR
concentration; the tracer mass of the last injection; the blade speed when the recording
reports the blender's drive) and a writable String node for the
diversion gate's command. :meth:`LoopbackPlant.play` writes the recording's values tick by
tick in plant time at ``speed`` x real time, each value stamped with its plant time as OPC UA
source timestamp (``epoch + t``), every node of a tick with the same stamp; the commands the
bridge writes to the gate node are kept in :attr:`LoopbackPlant.commands`.
:meth:`LoopbackPlant.bridge_config` is the ``BRIDGE.yaml`` mapping of these nodes.

Security, secure by default: the server offers only Basic256Sha256 SignAndEncrypt and
accepts only user/password sessions (no anonymous one) of its ``users``. Without
``certificate``/``private_key`` it makes its own per run (:func:`make_pki`, in ``pki`` or a
temporary folder removed by :meth:`LoopbackPlant.stop`): a self-signed server certificate, a
client certificate for the bridge (the only client certificate it then trusts), and, without
``users``, user ``twin`` with a random password in a 0600 file; :meth:`LoopbackPlant.bridge_config`
then carries the bridge's side (its certificate, the server's, user and password file).
``insecure=True`` is the open server: security None, anonymous sessions. Either way clients
may write only the gate's command node, as a PLC exposes it; the measurement nodes are
read-only to clients (the plant itself writes them).
"""

from __future__ import annotations

import asyncio
import json
import logging
import secrets
import shutil
import socket
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from itertools import groupby
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.permission_rules import SimpleRoleRuleset, User, UserRole
from asyncua.server.user_managers import UserManager

from schemas import keys
from schemas.messages import BlenderDrive, Event, FeederFlow, MeasuredConcentration
from schemas.opcua import BridgeConfig
from services.security import write_private

log = logging.getLogger(__name__)

#: plant time 0 of the loopback plant's source timestamps
EPOCH = datetime(2026, 1, 1, tzinfo=UTC)
NAMESPACE = "urn:powder-twin:loopback-plant"
#: application URIs of the server's and the bridge's certificates (asyncua's defaults, which
#: each side checks its own certificate against)
SERVER_URI = "urn:freeopcua:python:server"
CLIENT_URI = "urn:example.org:FreeOpcUa:opcua-asyncio"
#: FeederFlow field -> (node name suffix, unit served)
FEEDER_NODES = {
    "mass_flow_kg_h": ("MassFlow", "kg/h"),
    "setpoint_kg_h": ("SetPoint", "kg/h"),
    "screw_speed_rpm": ("ScrewSpeed", "rpm"),
    "hopper_mass_kg": ("HopperMass", "kg"),
    "feed_factor_g_rev": ("FeedFactor", "g/rev"),
    "refilling": ("Refilling", "bool"),
}


class _Users(UserManager):
    """Accepts only the configured user/password pairs (as operators: they may write)."""

    def __init__(self, users: dict[str, str]) -> None:
        self.users = users

    def get_user(
        self,
        iserver: Any,
        username: str | None = None,
        password: str | None = None,
        certificate: Any = None,
    ) -> User | None:
        if username is not None and self.users.get(username) == password:
            return User(role=UserRole.User, name=username)
        return None


@dataclass(frozen=True)
class PlantPki:
    """The files of a secured loopback plant and of its bridge (:func:`make_pki`)."""

    folder: Path
    server_certificate: Path
    server_key: Path
    client_certificate: Path
    client_key: Path
    user: str
    password_file: Path

    def bridge_security(self) -> dict[str, Any]:
        """The ``security`` section of the bridge's ``BRIDGE.yaml``."""
        return {
            "policy": "Basic256Sha256",
            "mode": "SignAndEncrypt",
            "certificate": str(self.client_certificate),
            "private_key": str(self.client_key),
            "server_certificate": str(self.server_certificate),
            "user": self.user,
            "password_file": str(self.password_file),
        }


def _self_signed(folder: Path, who: str, uri: str, use: Any) -> tuple[Path, Path]:
    """A self-signed application certificate (DER) and its private key (PEM, 0600)."""
    from asyncua.crypto.cert_gen import (
        dump_private_key_as_pem,
        generate_private_key,
        generate_self_signed_app_certificate,
    )
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    key = generate_private_key()
    cert = generate_self_signed_app_certificate(
        key,
        uri,
        {"organizationName": "powder-twin"},
        [
            x509.UniformResourceIdentifier(uri),
            x509.DNSName("localhost"),
            x509.DNSName(socket.gethostname()),
        ],
        extended=[use],
        days=30,
    )
    cert_path, key_path = folder / f"{who}.der", folder / f"{who}.pem"
    cert_path.write_bytes(cert.public_bytes(Encoding.DER))
    write_private(key_path, dump_private_key_as_pem(key).decode())
    return cert_path, key_path


def make_pki(folder: Path, user: str = "twin", password: str | None = None) -> PlantPki:
    """Per-run security of a loopback plant in ``folder`` (made 0700): a server certificate,
    a client certificate for its bridge, ``user`` and its password (default random) in
    ``opcua.pw`` (0600)."""
    from cryptography.x509.oid import ExtendedKeyUsageOID

    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    folder.chmod(0o700)
    server = _self_signed(folder, "server", SERVER_URI, ExtendedKeyUsageOID.SERVER_AUTH)
    client = _self_signed(folder, "client", CLIENT_URI, ExtendedKeyUsageOID.CLIENT_AUTH)
    pw = folder / "opcua.pw"
    write_private(pw, password if password is not None else secrets.token_urlsafe(24))
    return PlantPki(folder, *server, *client, user, pw)


def node_id(name: str) -> str:
    """The string node id of a loopback plant variable (namespace 2)."""
    return f"ns=2;s={name}"


class LoopbackPlant:
    """The recording's plant-input messages served as OPC UA variables (module docstring).

    ``messages``: ``(key, message)`` pairs of one line (feeder flows, NIR, tracer events), in
    time order, e.g. ``Recording.messages`` decoded. Security (module docstring): secured by
    default, ``insecure=True`` for the open server; ``certificate``/``private_key``, ``users``
    and ``trusted_clients`` (client certificates accepted, default any) to give one's own,
    else made per run in ``pki`` (default a temporary folder).
    """

    def __init__(
        self,
        messages: Iterable[tuple[str, Any]],
        *,
        port: int,
        speed: float = 200.0,
        insecure: bool = False,
        pki: Path | None = None,
        certificate: Path | None = None,
        private_key: Path | None = None,
        users: dict[str, str] | None = None,
        trusted_clients: list[Path] | None = None,
    ) -> None:
        self.messages = [
            (k, m)
            for k, m in messages
            if isinstance(m, (FeederFlow, MeasuredConcentration, BlenderDrive))
            or (isinstance(m, Event) and m.kind == "tracer_pulse")
        ]
        if not self.messages:
            raise ValueError(
                "the loopback plant needs feeder flows and a PAT concentration, got none"
            )
        self.port = port
        self.speed = speed
        if insecure and (certificate is not None or users is not None):
            raise ValueError("insecure: the open server takes no certificate and no users")
        self.insecure = insecure
        self.pki_folder = pki
        self.pki: PlantPki | None = None
        self._temp_pki: Path | None = None
        self.certificate = certificate
        self.private_key = private_key
        self.users = users
        self.trusted_clients = trusted_clients
        self.endpoint = f"opc.tcp://127.0.0.1:{port}/twin/"
        self.commands: list[dict[str, Any]] = []
        self.line = keys.parse_key(self.messages[0][0]).line
        self.feeders: dict[str, str] = {}
        self.sensor: tuple[str, str] | None = None
        self.tracer: str | None = None
        self.blender: str | None = None
        for key, m in self.messages:
            if isinstance(m, FeederFlow):
                self.feeders.setdefault(keys.parse_key(key).id, m.component)
            elif isinstance(m, MeasuredConcentration) and self.sensor is None:
                self.sensor = (m.sensor, m.component)
            elif isinstance(m, Event):
                self.tracer = self.tracer or m.component
            elif isinstance(m, BlenderDrive):
                self.blender = self.blender or keys.parse_key(key).id
        if self.sensor is None:
            raise ValueError("the loopback plant needs a PAT concentration, got none")
        self.server: Server | None = None
        self.vars: dict[str, Any] = {}
        self.written = 0

    # -- the mapping ---------------------------------------------------------------------------
    def bridge_config(self, **overrides: Any) -> BridgeConfig:
        """The ``BRIDGE.yaml`` of this plant's nodes (``overrides``: other top-level fields,
        e.g. ``security``); after :meth:`start` of a plant that made its own security, with the
        bridge's side of it."""
        sid, scomp = self.sensor
        data: dict[str, Any] = {
            "endpoint": self.endpoint,
            "line": self.line,
            "epoch_utc": EPOCH.isoformat(),
            "feeders": [
                {
                    "id": fid,
                    "component": comp,
                    "nodes": {
                        f: {"node_id": node_id(f"{fid}.{suffix}"), "unit": unit}
                        for f, (suffix, unit) in FEEDER_NODES.items()
                    },
                }
                for fid, comp in self.feeders.items()
            ],
            "sensor": {
                "id": sid,
                "component": scomp,
                "node": {"node_id": node_id(f"{sid}.Concentration"), "unit": "% w/w"},
            },
            "diverter": {"node_id": node_id("Gate.Command")},
        }
        if self.blender is not None:
            data["blender"] = {
                "id": self.blender,
                "node": {"node_id": node_id(f"{self.blender}.BladeSpeed"), "unit": "rpm"},
            }
        if self.tracer is not None:
            data["tracer"] = {
                "component": self.tracer,
                "node": {"node_id": node_id("Tracer.Mass"), "unit": "kg"},
            }
        if self.pki is not None:
            data["security"] = self.pki.bridge_security()
        return BridgeConfig.model_validate({**data, **overrides})

    def _secure(self) -> None:
        """Certificate, key, users and trusted client of a secured plant made per run where
        not given (module docstring)."""
        if self.insecure or self.certificate is not None or self.pki is not None:
            return
        folder = self.pki_folder
        if folder is None:
            folder = self._temp_pki = Path(tempfile.mkdtemp(prefix="twin-opcua-plant-"))
        user, password = next(iter(self.users.items())) if self.users else ("twin", None)
        self.pki = make_pki(folder.resolve(), user, password)
        self.certificate, self.private_key = self.pki.server_certificate, self.pki.server_key
        if self.trusted_clients is None:
            self.trusted_clients = [self.pki.client_certificate]
        if self.users is None:
            self.users = {user: self.pki.password_file.read_text()}

    async def _check_client(self, certificate: Any, app: Any) -> None:
        """Only the trusted client certificates open a secure channel."""
        from cryptography.hazmat.primitives.serialization import Encoding

        if certificate.public_bytes(Encoding.DER) not in self._trusted:
            log.warning("loopback plant: untrusted client certificate refused (%s)", app)
            raise ServiceError(ua.StatusCodes.BadSecurityChecksFailed)

    # -- the server ------------------------------------------------------------------------------
    async def start(self) -> LoopbackPlant:
        """Create the address space and start serving."""
        from asyncua.crypto.uacrypto import load_certificate

        self._secure()
        if self.users is not None:
            server = Server(user_manager=_Users(self.users))
        else:
            server = Server()
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name("powder-twin loopback plant")
        if self.insecure:
            server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
            server.set_identity_tokens([ua.AnonymousIdentityToken])
        if self.certificate is not None:
            server.set_security_policy(
                [ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt],
                permission_ruleset=SimpleRoleRuleset(),
            )
            await server.load_certificate(str(self.certificate))
            await server.load_private_key(str(self.private_key))
        if self.users is not None:
            server.set_identity_tokens([ua.UserNameIdentityToken])
        if self.trusted_clients is not None:
            from cryptography.hazmat.primitives.serialization import Encoding

            certs = [await load_certificate(str(c)) for c in self.trusted_clients]
            self._trusted = {c.public_bytes(Encoding.DER) for c in certs}
            server.set_certificate_validator(self._check_client)
        ns = await server.register_namespace(NAMESPACE)
        plc = await server.nodes.objects.add_object(ns, "Line")
        waiting = ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)
        for nid in self._node_names():
            kind = ua.VariantType.Boolean if nid.endswith("Refilling") else ua.VariantType.Double
            value = False if kind == ua.VariantType.Boolean else 0.0
            # read-only to clients: the plant writes its measurements (server side)
            var = await plc.add_variable(ua.NodeId(nid, ns), nid, value, varianttype=kind)
            await server.write_attribute_value(var.nodeid, ua.DataValue(StatusCode=waiting))
            self.vars[nid] = var
        gate = await plc.add_variable(
            ua.NodeId("Gate.Command", ns), "Gate.Command", "", varianttype=ua.VariantType.String
        )
        await gate.set_writable()  # the one node a client (the twin's bridge) writes
        self.vars["Gate.Command"] = gate
        await server.start()
        self.server = server
        sub = await server.create_subscription(10, self)
        await sub.subscribe_data_change(gate, queuesize=1000)
        return self

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        """The gate node changed: keep the command written there."""
        if val:
            self.commands.append(json.loads(val))

    def _node_names(self) -> list[str]:
        names = [f"{fid}.{s}" for fid in self.feeders for s, _ in FEEDER_NODES.values()]
        names.append(f"{self.sensor[0]}.Concentration")
        if self.tracer is not None:
            names.append("Tracer.Mass")
        if self.blender is not None:
            names.append(f"{self.blender}.BladeSpeed")
        return names

    async def stop(self) -> None:
        """Stop serving; a temporary folder of per-run security is removed."""
        if self.server is not None:
            await self.server.stop()
            self.server = None
        if self._temp_pki is not None:
            shutil.rmtree(self._temp_pki, ignore_errors=True)
            self._temp_pki = None

    async def write(self, name: str, value: Any, t: float) -> None:
        """Write ``value`` to variable ``name`` stamped with plant time ``t`` (``None``: no value,
        after which the node takes a value of any type, as a misconfigured PLC tag would)."""
        kind = ua.VariantType.Boolean if isinstance(value, bool) else ua.VariantType.Double
        if isinstance(value, str):
            kind = ua.VariantType.String
        dv = ua.DataValue(
            None if value is None else ua.Variant(value, kind),
            SourceTimestamp=EPOCH + timedelta(seconds=t),
            ServerTimestamp=datetime.now(UTC),
        )
        await self.server.write_attribute_value(self.vars[name].nodeid, dv)
        self.written += 1

    async def write_tick(self, t: float, batch: list[tuple[str, Any]]) -> None:
        """Every node value of one plant time."""
        for key, m in batch:
            if isinstance(m, FeederFlow):
                fid = keys.parse_key(key).id
                for f, (suffix, _) in FEEDER_NODES.items():
                    v = getattr(m, f)
                    if v is None:
                        continue
                    await self.write(f"{fid}.{suffix}", v if isinstance(v, bool) else float(v), t)
            elif isinstance(m, MeasuredConcentration):
                await self.write(f"{m.sensor}.Concentration", m.concentration_pct_w_w, t)
            elif isinstance(m, Event) and m.mass_kg:
                await self.write("Tracer.Mass", m.mass_kg, t)
            elif isinstance(m, BlenderDrive):
                await self.write(f"{keys.parse_key(key).id}.BladeSpeed", m.blade_speed_rpm, t)

    async def play(
        self, *, t_from: float = 0.0, t_to: float | None = None, on_tick: Any = None
    ) -> int:
        """Write the recording's ticks in ``[t_from, t_to]`` at ``speed`` x real time (plant
        time paced from the first tick); returns the ticks written. ``on_tick(t, wall)`` is
        called after each."""
        loop = asyncio.get_running_loop()
        ticks = 0
        t0 = w0 = None
        for t, group in groupby(self.messages, key=lambda km: km[1].t):
            if t < t_from or (t_to is not None and t > t_to):
                continue
            batch = list(group)
            if t0 is None:
                t0, w0 = t, loop.time()
            delay = w0 + (t - t0) / self.speed - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            await self.write_tick(t, batch)
            ticks += 1
            if on_tick is not None:
                on_tick(t, loop.time())
        return ticks


def read_users(path: Path) -> dict[str, str]:
    """``user:password`` lines (``#`` comments and blank lines skipped) of a file readable by
    its owner only; raises ValueError naming the file and line of a bad one."""
    mode = path.stat().st_mode & 0o777
    if mode & 0o077:
        raise ValueError(f"--users {path} must be readable by its owner only (0600), got {mode:o}")
    users: dict[str, str] = {}
    for i, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        user, sep, password = line.partition(":")
        if not sep or not user or not password:
            raise ValueError(f"--users {path} line {i}: expected user:password")
        users[user] = password
    if not users:
        raise ValueError(f"--users {path}: no user:password line")
    return users


def recording_messages(path: str | Path) -> list[tuple[str, Any]]:
    """The decoded messages of a recording, in time order (for :class:`LoopbackPlant`)."""
    from services.recording import read_recording

    rec = read_recording(path)
    rec.require_complete(False)
    return [(m.key, m.decode()) for m in rec.messages]
