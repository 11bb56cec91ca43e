"""The OPC UA mapping of a line (``BRIDGE.yaml``): which PLC/SCADA/PAT node feeds which field of
the wire contract, in which unit, scaled how and valid in which range.

One mapping serves both ways in (``twin bridge opcua`` on a live server, ``twin import`` on a
historian or PAT-software export, where a node's ``tag`` names its column or file). Example::

    endpoint: opc.tcp://plc.line1:4840
    line: line1
    epoch_utc: "2026-01-01T00:00:00+00:00"   # plant time 0 (source timestamps minus this)
    feeders:
      - id: api
        component: api
        sample_period_s: 1.0
        nodes:
          mass_flow_kg_h: {node_id: "ns=2;s=API.MassFlow", unit: "kg/h", valid_max: 50}
          screw_speed_rpm: {node_id: "ns=2;s=API.Screw", unit: "rev/s"}
          hopper_mass_kg: {node_id: "ns=2;s=API.Hopper", unit: "g", scale: 0.1}
          refilling: {node_id: "ns=2;s=API.Refill", unit: "bool"}
    sensor: {id: nir1, component: api, sample_period_s: 1.0,
             node: {node_id: "ns=2;s=NIR.API", unit: "fraction"}}
    tracer: {component: api, node: {node_id: "ns=2;s=Tracer.Mass", unit: "g"}}
    blender: {id: blender, node: {node_id: "ns=2;s=Blender.BladeSpeed", unit: "rpm"}}
    diverter: {node_id: "ns=2;s=Gate.Command"}
    security: {policy: Basic256Sha256, mode: SignAndEncrypt, certificate: client.der,
               private_key: client.pem, user: twin, password_file: opcua.pw}

A node's value ``v`` becomes ``(v * scale + offset)`` in its declared ``unit``, then the field's
unit of the contract (:data:`UNITS`); ``valid_min`` / ``valid_max`` bound the value in the
declared unit after scale and offset.
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from schemas.base import Finite, Ident, NonNegative, Positive, StrictModel

#: every unit a node may declare: unit -> (quantity, factor to the contract's unit of that
#: quantity); the contract's units: kg/h, rev/min, kg, g/rev, % w/w, s, and booleans
UNITS: dict[str, tuple[str, float]] = {
    "kg/h": ("mass_flow", 1.0),
    "kg/min": ("mass_flow", 60.0),
    "kg/s": ("mass_flow", 3600.0),
    "g/h": ("mass_flow", 1e-3),
    "g/min": ("mass_flow", 0.06),
    "g/s": ("mass_flow", 3.6),
    "t/h": ("mass_flow", 1000.0),
    "rpm": ("rotation", 1.0),
    "rev/min": ("rotation", 1.0),
    "rev/s": ("rotation", 60.0),
    "kg": ("mass", 1.0),
    "g": ("mass", 1e-3),
    "mg": ("mass", 1e-6),
    "g/rev": ("feed_factor", 1.0),
    "kg/rev": ("feed_factor", 1000.0),
    "% w/w": ("concentration", 1.0),
    "%": ("concentration", 1.0),
    "fraction": ("concentration", 100.0),
    "mg/g": ("concentration", 0.1),
    "bool": ("flag", 1.0),
}

#: fields of the contract a node can feed, and the quantity of each
FEEDER_FIELDS: dict[str, str] = {
    "mass_flow_kg_h": "mass_flow",
    "setpoint_kg_h": "mass_flow",
    "screw_speed_rpm": "rotation",
    "hopper_mass_kg": "mass",
    "feed_factor_g_rev": "feed_factor",
    "refilling": "flag",
}
#: the feeder fields a :class:`FeederMap` must map (the contract's required ``FeederFlow`` fields
#: besides the component, which the mapping declares)
REQUIRED_FEEDER_FIELDS = ("mass_flow_kg_h", "screw_speed_rpm", "hopper_mass_kg")

OPCUA_PREFIX = "opc.tcp://"


class NodeMap(StrictModel):
    """One OPC UA node (or one column / file of an export: ``tag``) feeding one field."""

    node_id: str = Field(min_length=1, description="OPC UA node id, e.g. 'ns=2;s=API.MassFlow'")
    tag: str | None = Field(
        None, min_length=1, description="column or file name in an export (default: node_id)"
    )
    unit: str = Field(description=f"unit of the node's value, one of {sorted(UNITS)}")
    scale: Finite = Field(1.0, description="value in `unit` = raw * scale + offset")
    offset: Finite = Field(0.0, description="value in `unit` = raw * scale + offset")
    valid_min: Finite | None = Field(None, description="smallest valid value (declared unit)")
    valid_max: Finite | None = Field(None, description="largest valid value (declared unit)")
    stamped: Literal["every_sample", "on_change"] = Field(
        "every_sample",
        description="every_sample: the PLC stamps the node at each sample of its unit (the "
        "unit's message waits for it); on_change: only when its value changes (its last value "
        "is used)",
    )

    @field_validator("unit")
    @classmethod
    def _known_unit(cls, value: str) -> str:
        if value not in UNITS:
            raise ValueError(f"unit must be one of {sorted(UNITS)}, got {value!r}")
        return value

    @model_validator(mode="after")
    def _range_ordered(self) -> NodeMap:
        lo, hi = self.valid_min, self.valid_max
        if lo is not None and hi is not None and lo > hi:
            raise ValueError(f"valid_min must be <= valid_max, got {lo} > {hi}")
        return self

    @property
    def column(self) -> str:
        """The name of this node in an export (its ``tag``, else its node id)."""
        return self.tag or self.node_id


def _check_quantity(field: str, node: NodeMap, quantity: str) -> None:
    got = UNITS[node.unit][0]
    if got != quantity:
        raise ValueError(
            f"{field}.unit must be a unit of {quantity} "
            f"({sorted(u for u, (q, _) in UNITS.items() if q == quantity)}), got {node.unit!r}"
        )


class FeederMap(StrictModel):
    """The nodes of one loss-in-weight feeder (``FeederFlow`` on ``twin/<line>/feeder/<id>/flow``)."""

    id: Ident
    component: Ident
    sample_period_s: Positive = Field(1.0, description="the PLC's update period of the flows, s")
    nodes: dict[str, NodeMap] = Field(description="FeederFlow field -> node")

    @model_validator(mode="after")
    def _fields_known(self) -> FeederMap:
        for name, node in self.nodes.items():
            if name not in FEEDER_FIELDS:
                raise ValueError(
                    f"nodes: field must be one of {sorted(FEEDER_FIELDS)}, got {name!r}"
                )
            _check_quantity(f"nodes.{name}", node, FEEDER_FIELDS[name])
        missing = [f for f in REQUIRED_FEEDER_FIELDS if f not in self.nodes]
        if missing:
            raise ValueError(f"nodes must map {list(REQUIRED_FEEDER_FIELDS)}, missing {missing}")
        return self


class SensorMap(StrictModel):
    """The PAT reading (``MeasuredConcentration`` on ``twin/<line>/pat/<id>/concentration``)."""

    id: Ident
    component: Ident
    sample_period_s: Positive = Field(1.0, description="the analyser's sample period, s")
    node: NodeMap

    @model_validator(mode="after")
    def _concentration(self) -> SensorMap:
        _check_quantity("node", self.node, "concentration")
        return self


class TracerMap(StrictModel):
    """A tracer injection: the node holds the mass injected by the last pulse; each update with
    a mass > 0 is a ``tracer_pulse`` ``Event`` at its source time."""

    component: Ident
    duration_s: Positive = Field(1.0, description="duration of an injection, s")
    node: NodeMap

    @model_validator(mode="after")
    def _mass(self) -> TracerMap:
        _check_quantity("node", self.node, "mass")
        return self


class BlenderMap(StrictModel):
    """The blender's blade drive (``BlenderDrive`` on ``twin/<line>/blender/<id>/drive``)."""

    id: Ident = "blender"
    sample_period_s: Positive = Field(1.0, description="the drive's update period, s")
    node: NodeMap

    @model_validator(mode="after")
    def _rotation(self) -> BlenderMap:
        _check_quantity("node", self.node, "rotation")
        return self


class DiverterMap(StrictModel):
    """The diversion gate's command node (a String node): the bridge writes there the JSON of
    each ``DivertCommand`` the twin's diverter issued."""

    node_id: str = Field(min_length=1)


class OpcuaSecurity(StrictModel):
    """OPC UA security of the bridge's session: policy and mode, the client's certificate and
    private key (PEM or DER files), the server's certificate, user and password (from a 0600
    file or an environment variable, never inline)."""

    policy: Literal["None", "Basic256Sha256"] = "None"
    mode: Literal["None", "Sign", "SignAndEncrypt"] = "None"
    certificate: Path | None = None
    private_key: Path | None = None
    server_certificate: Path | None = None
    user: str | None = Field(None, min_length=1)
    password_file: Path | None = None
    password_env: str | None = Field(None, min_length=1)

    @model_validator(mode="after")
    def _consistent(self) -> OpcuaSecurity:
        if (self.policy == "None") != (self.mode == "None"):
            raise ValueError(
                f"policy and mode must both be 'None' or neither, got {self.policy!r} / {self.mode!r}"
            )
        if self.policy != "None" and (self.certificate is None or self.private_key is None):
            raise ValueError(
                f"security.policy {self.policy!r} needs certificate and private_key, "
                f"got {self.certificate} / {self.private_key}"
            )
        if self.user is not None and self.password_file is None and self.password_env is None:
            raise ValueError(f"security.user {self.user!r} needs password_file or password_env")
        return self

    @property
    def secured(self) -> bool:
        """Whether messages are signed and encrypted (a write may travel on this session)."""
        return self.policy != "None" and self.mode == "SignAndEncrypt"


class BridgeConfig(StrictModel):
    """``BRIDGE.yaml``: the OPC UA server, the node mapping, the plant clock and security (see
    the module docstring)."""

    endpoint: str = Field(description="opc.tcp://host:port[/path] of the OPC UA server")
    line: Ident = Field(description="line name of the twin's keys")
    epoch_utc: datetime = Field(
        description="plant time 0: a sample's plant time is its source timestamp minus this "
        "(time zone required)"
    )
    feeders: list[FeederMap] = Field(min_length=1)
    sensor: SensorMap
    tracer: TracerMap | None = None
    blender: BlenderMap | None = None
    diverter: DiverterMap | None = None
    security: OpcuaSecurity = Field(default_factory=OpcuaSecurity)
    publishing_interval_ms: Positive = Field(
        20.0, description="subscription publishing interval, ms (notifications batched this long)"
    )
    reconnect_s: Positive = Field(1.0, description="wait between reconnection attempts, s")
    future_tolerance_s: NonNegative = Field(
        1.0,
        description="a live sample stamped more than this ahead of the plant clock (the latest "
        "stamp of the other units, advanced at real time since it was received) is held, and "
        "refused if its node then reports an earlier stamp (twin_core.plant.opcua_map), s",
    )

    @field_validator("endpoint")
    @classmethod
    def _opc_tcp(cls, value: str) -> str:
        if not value.startswith(OPCUA_PREFIX) or len(value) <= len(OPCUA_PREFIX):
            raise ValueError(f"endpoint must start with {OPCUA_PREFIX!r}, got {value!r}")
        return value

    @field_validator("epoch_utc")
    @classmethod
    def _aware(cls, value: datetime) -> datetime:
        if value.tzinfo is None:
            raise ValueError(f"epoch_utc must carry a time zone, got {value.isoformat()!r}")
        return value

    @model_validator(mode="after")
    def _distinct_nodes(self) -> BridgeConfig:
        ids = [n.node_id for n in self.nodes()]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"a node may feed one field only, got {dup} more than once")
        fids = [f.id for f in self.feeders]
        if len(set(fids)) != len(fids):
            raise ValueError(f"feeder ids must be distinct, got {fids}")
        return self

    def nodes(self) -> list[NodeMap]:
        """Every mapped input node (feeders, sensor, tracer, blender drive)."""
        out = [n for f in self.feeders for n in f.nodes.values()] + [self.sensor.node]
        if self.tracer is not None:
            out.append(self.tracer.node)
        if self.blender is not None:
            out.append(self.blender.node)
        return out
