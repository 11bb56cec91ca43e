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

Security: with ``certificate``/``private_key`` the server offers only Basic256Sha256
SignAndEncrypt and, with ``users``, accepts only those user/password pairs.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Iterable
from datetime import UTC, datetime, timedelta
from itertools import groupby
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.crypto.permission_rules import SimpleRoleRuleset, User, UserRole
from asyncua.server.user_managers import UserManager

from schemas import keys
from schemas.messages import BlenderDrive, Event, FeederFlow, MeasuredConcentration
from schemas.opcua import BridgeConfig

log = logging.getLogger(__name__)

#: plant time 0 of the loopback plant's source timestamps
EPOCH = datetime(2026, 1, 1, tzinfo=UTC)
NAMESPACE = "urn:powder-twin:loopback-plant"
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


def node_id(name: str) -> str:
    """The string node id of a loopback plant variable (namespace 2)."""
    return f"ns=2;s={name}"


class LoopbackPlant:
    """The recording's plant-input messages served as OPC UA variables (module docstring).

    ``messages``: ``(key, message)`` pairs of one line (feeder flows, NIR, tracer events), in
    time order, e.g. ``Recording.messages`` decoded.
    """

    def __init__(
        self,
        messages: Iterable[tuple[str, Any]],
        *,
        port: int,
        speed: float = 200.0,
        certificate: Path | None = None,
        private_key: Path | None = None,
        users: dict[str, str] | None = None,
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
        self.certificate = certificate
        self.private_key = private_key
        self.users = users
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
        e.g. ``security``)."""
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
        return BridgeConfig.model_validate({**data, **overrides})

    # -- the server ------------------------------------------------------------------------------
    async def start(self) -> LoopbackPlant:
        """Create the address space and start serving."""
        if self.users is not None:
            server = Server(user_manager=_Users(self.users))
        else:
            server = Server()
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name("powder-twin loopback plant")
        if self.certificate is not None:
            server.set_security_policy(
                [ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt],
                permission_ruleset=SimpleRoleRuleset(),
            )
            await server.load_certificate(str(self.certificate))
            await server.load_private_key(str(self.private_key))
        if self.users is not None:
            server.set_security_IDs(["Username"])
        ns = await server.register_namespace(NAMESPACE)
        plc = await server.nodes.objects.add_object(ns, "Line")
        waiting = ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)
        for nid in self._node_names():
            kind = ua.VariantType.Boolean if nid.endswith("Refilling") else ua.VariantType.Double
            value = False if kind == ua.VariantType.Boolean else 0.0
            var = await plc.add_variable(ua.NodeId(nid, ns), nid, value, varianttype=kind)
            await var.set_writable()  # a test writes bad values as a faulty PLC would
            await server.write_attribute_value(var.nodeid, ua.DataValue(StatusCode=waiting))
            self.vars[nid] = var
        gate = await plc.add_variable(
            ua.NodeId("Gate.Command", ns), "Gate.Command", "", varianttype=ua.VariantType.String
        )
        await gate.set_writable()
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
        if self.server is not None:
            await self.server.stop()
            self.server = None

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


def recording_messages(path: str | Path) -> list[tuple[str, Any]]:
    """The decoded messages of a recording, in time order (for :class:`LoopbackPlant`)."""
    from services.recording import read_recording

    rec = read_recording(path)
    rec.require_complete(False)
    return [(m.key, m.decode()) for m in rec.messages]
