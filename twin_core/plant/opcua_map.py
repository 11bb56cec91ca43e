"""From PLC/SCADA/PAT samples to the twin's messages: units, validity, assembly, gaps.

Pure computation on the mapping ``schemas.opcua.BridgeConfig`` (no OPC UA stack here: the
bridge in ``services/opcua_bridge.py`` and ``twin import`` feed it samples ``(node, source
time, raw value)``).

- :func:`convert`: a raw node value to the contract's unit, v = (raw * scale + offset) * f_u,
  f_u the factor of the declared unit (``schemas.opcua.UNITS``: e.g. 1 g/s = 3.6 kg/h,
  1 rev/s = 60 rev/min, fraction 1 = 100 % w/w); NaN/inf, a wrong type (text, a missing
  value) and a value outside ``[valid_min, valid_max]`` are refused (:class:`BadValue`, with
  the reason the bridge counts: ``rejected_nan``, ``rejected_type``, ``rejected_range``).
- :class:`MessageAssembler`: the samples of one unit (feeder, sensor, tracer, blender drive)
  with the same source time become one message (``FeederFlow``, ``MeasuredConcentration``, a
  ``tracer_pulse`` ``Event``, ``BlenderDrive``) once every node of the unit has reported that time or a later
  one (OPC UA keeps the order of each monitored item's notifications, not across items), in
  time order per unit. A node the mapping declares ``stamped: on_change`` (a PLC stamping it
  only when its value changes) is not waited for: its field takes the node's last value
  (counted ``incomplete``); a time with a refused value is dropped (``dropped``), and so is a
  time at which a node stamped each sample has no value (``missing``): never filled in with an
  earlier value. Feed factor, when not mapped, is its definition
  ff = 1000 Q / (60 n) g/rev (Q kg/h, n rev/min; 0 when the screw stands), the seed's Eq. 2.
- Gaps: a unit's next time more than 1.5 sample periods after its last is a gap of
  round(dt / period) - 1 missed samples: the unit's sequence number skips that many (the
  close-loop's data-quality step reads a stamp gap with a sequence gap as missing data,
  ``twin_core.closeloop.quality``) and a :class:`Gap` is returned for the bridge to mark on
  the bus (:func:`gap_event`).
- Time at the plant boundary (live samples, ``received_s`` given): the *plant clock* of a unit
  at the bridge's receive time w is the latest stamp any **other** unit reported (accepted, or
  held as below), advanced at real time since it was received: C_U(w) = max over V != U of
  t_V + (w - w_V). A sample stamped more than ``future_tolerance_s`` ahead of it is **held**,
  not assembled, and released in stamp order once the clock reaches it (notifications grouped
  by node in one publish, a source's clock a little fast; the whole plant jumping ahead
  together, after an outage, is followed: the units support each other; before any other
  unit reported there is no clock). It is **refused** (``future``, listed in
  :attr:`MessageAssembler.refused`) as soon as its node reports an earlier or equal stamp (one
  node's notifications come in order: the later one with the earlier stamp is the PLC's, the
  held one was out of time), when more than :data:`HOLD_MAX` are held for its node, or at
  :meth:`MessageAssembler.flush`.
  A held sample never sets its unit's last time, so the real samples after a forged or
  clock-jumped one are not taken for ``late``. An export (``twin import``) has no live clock:
  without ``received_s`` nothing is held.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from schemas import keys
from schemas.base import Message
from schemas.messages import BlenderDrive, Event, FeederFlow, MeasuredConcentration
from schemas.opcua import UNITS, BridgeConfig, NodeMap

__all__ = [
    "BadValue",
    "Future",
    "Gap",
    "MessageAssembler",
    "convert",
    "gap_event",
    "plant_time_s",
]

#: marks a field whose value at a time was refused (the time is dropped, not filled in)
_REJECTED = object()
#: a stamp gap longer than this many sample periods is missing data (the close-loop's rule)
GAP_PERIODS = 1.5
#: live samples held ahead of the plant clock per node (ten times the bridge's server queue of
#: a node: one publish after a stall); beyond, the one furthest ahead is refused
HOLD_MAX = 10000


class BadValue(ValueError):
    """A node value the twin must not use; ``reason`` is the counter it goes to."""

    def __init__(self, reason: str, text: str) -> None:
        super().__init__(text)
        self.reason = reason


def convert(node: NodeMap, raw: Any) -> float | bool:
    """The value of ``raw`` in the contract's unit of the node's quantity (module docstring);
    raises :class:`BadValue` for a wrong type, NaN/inf or a value out of the valid range."""
    quantity, factor = UNITS[node.unit]
    if quantity == "flag":
        if isinstance(raw, bool) or (isinstance(raw, int) and raw in (0, 1)):
            return bool(raw)
        raise BadValue("rejected_type", f"{node.node_id}: expected a boolean, got {raw!r}")
    if isinstance(raw, bool) or not isinstance(raw, (int, float)):
        raise BadValue("rejected_type", f"{node.node_id}: expected a number, got {raw!r}")
    if not math.isfinite(raw):
        raise BadValue("rejected_nan", f"{node.node_id}: not a finite number, got {raw!r}")
    value = raw * node.scale + node.offset
    lo, hi = node.valid_min, node.valid_max
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise BadValue(
            "rejected_range",
            f"{node.node_id}: {value!r} {node.unit} outside [{lo}, {hi}]",
        )
    return value * factor


def plant_time_s(source: datetime, epoch: datetime) -> float:
    """Plant time of a sample: its source timestamp minus the plant's epoch, s (both aware)."""
    return (source - epoch).total_seconds()


@dataclass(frozen=True)
class Gap:
    """Samples of one unit that never came: ``n_missed`` between ``t_before_s`` and ``t_after_s``."""

    unit: str
    key: str
    t_before_s: float
    t_after_s: float
    n_missed: int


def gap_event(gap: Gap, seq: int) -> Event:
    """The bus mark of a gap: a ``note`` Event at the first time after it, naming the unit,
    the stretch and the samples missed."""
    return Event(
        t=gap.t_after_s,
        seq=seq,
        kind="note",
        source="opcua",
        detail=f"gap: {gap.unit} missed {gap.n_missed} samples between "
        f"{gap.t_before_s:.3f} s and {gap.t_after_s:.3f} s ({gap.key})",
    )


@dataclass(frozen=True)
class Future:
    """A live sample refused for its stamp ahead of the plant clock (module docstring)."""

    unit: str
    node_id: str
    t_s: float
    why: str


@dataclass(frozen=True)
class _Held:
    """A live sample held ahead of the plant clock: stamp, field, raw value, receive time."""

    t: float
    name: str
    raw: Any
    received_s: float


def _ahead(queue: deque[_Held], limit: float) -> int:
    """How many of a node's held samples (stamp order) the plant clock has reached."""
    n = 0
    for h in queue:
        if h.t > limit:
            break
        n += 1
    return n


@dataclass
class _Unit:
    """One message source: its key, its fields' nodes, its pending times and state."""

    name: str
    key: str
    fields: dict[str, NodeMap]
    period_s: float | None
    build: Any
    pending: dict[float, dict[str, Any]] = field(default_factory=dict)
    last: dict[str, Any] = field(default_factory=dict)
    last_t: float | None = None
    seq: int = 0
    node_t: dict[str, float] = field(default_factory=dict)
    #: the latest stamp past the time checks and its receive time (the others' plant clock)
    clock_t: float | None = None
    clock_w: float = 0.0
    #: per field, the samples held ahead of the plant clock, in stamp (and arrival) order
    held: dict[str, deque[_Held]] = field(default_factory=dict)

    def seen(self, now: float) -> float | None:
        """This unit's latest stamp (accepted, or each node's latest held), advanced at real
        time to ``now``."""
        points = [q[-1] for q in self.held.values() if q]
        out = [h.t + (now - h.received_s) for h in points]
        if self.clock_t is not None:
            out.append(self.clock_t + (now - self.clock_w))
        return max(out, default=None)


class MessageAssembler:
    """Samples ``(node id, plant time, raw)`` in, ``(key, message)`` pairs and gaps out (module
    docstring). ``counters`` counts ``samples``, ``rejected_*``, ``incomplete``, ``missing``,
    ``dropped``, ``samples_missed``, ``late`` (a time at or before the unit's last emitted
    one), ``future`` (a live sample refused ahead of the plant clock), ``future_held`` (held
    ahead of it, then released); :attr:`refused` lists the ``future`` ones until the caller
    takes them."""

    def __init__(self, config: BridgeConfig) -> None:
        self.config = config
        self.tolerance_s = config.future_tolerance_s
        self.counters: dict[str, int] = {}
        self.refused: list[Future] = []
        self.units: list[_Unit] = []
        self._by_node: dict[str, tuple[_Unit, str]] = {}
        line = config.line
        for f in config.feeders:
            self._add(
                _Unit(
                    f"feeder {f.id}",
                    keys.feeder_flow(line, f.id),
                    dict(f.nodes),
                    f.sample_period_s,
                    self._feeder_builder(f.id, f.component),
                )
            )
        s = config.sensor
        self._add(
            _Unit(
                f"sensor {s.id}",
                keys.measured_concentration(line, s.id),
                {"concentration_pct_w_w": s.node},
                s.sample_period_s,
                self._sensor_builder(s.id, s.component),
            )
        )
        if config.tracer is not None:
            tr = config.tracer
            self._add(
                _Unit(
                    f"tracer {tr.component}",
                    keys.event(line, "tracer", tr.component),
                    {"mass_kg": tr.node},
                    None,
                    self._tracer_builder(tr.component, tr.duration_s),
                )
            )

        if config.blender is not None:
            b = config.blender
            self._add(
                _Unit(
                    f"blender {b.id}",
                    keys.blender_drive(line, b.id),
                    {"blade_speed_rpm": b.node},
                    b.sample_period_s,
                    lambda t, seq, v: BlenderDrive(
                        t=t, seq=seq, blade_speed_rpm=v["blade_speed_rpm"]
                    ),
                )
            )

    def _add(self, unit: _Unit) -> None:
        self.units.append(unit)
        for name, node in unit.fields.items():
            self._by_node[node.node_id] = (unit, name)

    def _count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    @staticmethod
    def _feeder_builder(feeder_id: str, component: str):
        def build(t: float, seq: int, v: dict[str, Any]) -> FeederFlow:
            q, n = v["mass_flow_kg_h"], v["screw_speed_rpm"]
            ff = v.get("feed_factor_g_rev", 1000.0 * q / (60.0 * n) if n > 0 else 0.0)
            return FeederFlow(
                t=t,
                seq=seq,
                component=component,
                mass_flow_kg_h=q,
                setpoint_kg_h=v.get("setpoint_kg_h"),
                screw_speed_rpm=n,
                hopper_mass_kg=v["hopper_mass_kg"],
                feed_factor_g_rev=ff,
                refilling=v.get("refilling", False),
            )

        return build

    @staticmethod
    def _sensor_builder(sensor_id: str, component: str):
        def build(t: float, seq: int, v: dict[str, Any]) -> MeasuredConcentration:
            return MeasuredConcentration(
                t=t,
                seq=seq,
                sensor=sensor_id,
                component=component,
                concentration_pct_w_w=v["concentration_pct_w_w"],
            )

        return build

    @staticmethod
    def _tracer_builder(component: str, duration_s: float):
        def build(t: float, seq: int, v: dict[str, Any]) -> Event | None:
            mass = v["mass_kg"]
            if mass <= 0:
                return None
            return Event(
                t=t,
                seq=seq,
                kind="tracer_pulse",
                source=component,
                component=component,
                mass_kg=mass,
                duration_s=duration_s,
                detail=f"{mass * 1000:g} g {component} tracer pulse",
            )

        return build

    def node_ids(self) -> list[str]:
        """The nodes the assembler takes samples of."""
        return list(self._by_node)

    def add(
        self, node_id: str, t: float, raw: Any, received_s: float | None = None
    ) -> tuple[list[tuple[str, Message]], list[Gap]]:
        """One sample: the messages and gaps it releases (module docstring). A bad value is
        counted by reason; its time is dropped (a missed sample, seen as a gap).
        ``received_s``: a live sample's receive time (seconds of any steady clock, e.g.
        ``time.monotonic()``), checked against the plant clock; None (an export): not."""
        if node_id not in self._by_node:
            self._count("rejected_unknown")
            return [], []
        unit, name = self._by_node[node_id]
        self._count("samples")
        if not math.isfinite(t) or t < 0:
            self._count("rejected_time")
            return [], []
        if received_s is None:
            return self._take(unit, name, t, raw, None)
        out, gaps = self.tick(received_s)
        # one node's notifications come in its order: its held samples stamped at or after
        # this one were out of time
        queue = unit.held.setdefault(name, deque())
        while queue and queue[-1].t >= t:
            self._refuse(unit, queue.pop(), f"its node then reported {t:.3f} s")
        clock = self._clock(unit, received_s)
        if queue or (clock is not None and t > clock + self.tolerance_s):
            queue.append(_Held(t, name, raw, received_s))
            if len(queue) > HOLD_MAX:
                self._refuse(unit, queue.pop(), f"more than {HOLD_MAX} samples of it held")
            return out, gaps
        m, g = self._take(unit, name, t, raw, received_s)
        m2, g2 = self.tick(received_s)
        return out + m + m2, gaps + g + g2

    def _clock(self, unit: _Unit, now: float) -> float | None:
        """The plant clock of ``unit`` at ``now`` (module docstring); None before any other
        unit reported."""
        return max(
            (s for u in self.units if u is not unit if (s := u.seen(now)) is not None), default=None
        )

    def _refuse(self, unit: _Unit, h: _Held, why: str) -> None:
        self._count("future")
        self.refused.append(Future(unit.name, unit.fields[h.name].node_id, h.t, why))

    def tick(self, now: float) -> tuple[list[tuple[str, Message]], list[Gap]]:
        """Release, in stamp order per unit, the held samples the plant clock has reached by
        ``now`` (also called as time passes without samples)."""
        out: list[tuple[str, Message]] = []
        gaps: list[Gap] = []
        moved = True
        while moved:
            moved = False
            for unit in self.units:
                if not any(unit.held.values()):
                    continue
                clock = self._clock(unit, now)
                limit = math.inf if clock is None else clock + self.tolerance_s
                ready = [q.popleft() for q in unit.held.values() for _ in range(_ahead(q, limit))]
                for h in sorted(ready, key=lambda h: h.t):
                    self._count("future_held")
                    m, g = self._take(unit, h.name, h.t, h.raw, h.received_s)
                    out += m
                    gaps += g
                    moved = True
        return out, gaps

    def _take(
        self, unit: _Unit, name: str, t: float, raw: Any, received_s: float | None
    ) -> tuple[list[tuple[str, Message]], list[Gap]]:
        """A sample past the time checks, into its unit's pending times."""
        if unit.last_t is not None and t <= unit.last_t:
            self._count("late")
            return [], []
        if received_s is not None and (unit.clock_t is None or t >= unit.clock_t):
            unit.clock_t, unit.clock_w = t, received_s
        try:
            value = convert(unit.fields[name], raw)
        except BadValue as exc:
            self._count(exc.reason)
            value = _REJECTED
        unit.pending.setdefault(t, {})[name] = value
        unit.node_t[name] = max(unit.node_t.get(name, -math.inf), t)
        # every node stamped each sample has reported this far (each node's samples come in
        # time order); a node stamped on change only is not waited for
        waited = [f for f, n in unit.fields.items() if n.stamped == "every_sample"] or [name]
        ready = min(unit.node_t.get(f, -math.inf) for f in waited)
        if any(f not in unit.node_t for f in unit.fields):  # an on-change node's first value
            ready = -math.inf
        if min(unit.pending) <= ready:
            return self._release(unit, ready)
        return [], []

    def _release(self, unit: _Unit, upto: float) -> tuple[list[tuple[str, Message]], list[Gap]]:
        out: list[tuple[str, Message]] = []
        gaps: list[Gap] = []
        for t in sorted(x for x in unit.pending if x <= upto):
            values = unit.pending.pop(t)
            # an on-change node's value stands from its stamp on, whether or not this time
            # becomes a message
            unit.last.update(
                {
                    f: v
                    for f, v in values.items()
                    if v is not _REJECTED and unit.fields[f].stamped == "on_change"
                }
            )
            if any(v is _REJECTED for v in values.values()):
                self._count("dropped")  # a bad value is never replaced by a guess
                continue
            if len(values) < len(unit.fields):
                # a node stamped each sample that has no value at this time: the time is lost
                # (never the node's previous value); an on-change node lends its last value
                lost = [
                    f
                    for f, n in unit.fields.items()
                    if f not in values and (n.stamped == "every_sample" or f not in unit.last)
                ]
                if lost:
                    self._count("missing")
                    continue
                self._count("incomplete")
            values = {**unit.last, **values}
            unit.last = values
            gap = self._gap(unit, t)
            if gap is not None:
                gaps.append(gap)
                unit.seq += gap.n_missed
            msg = unit.build(t, unit.seq, values)
            unit.last_t = t
            if msg is None:
                continue
            unit.seq += 1
            out.append((unit.key, msg))
        return out, gaps

    def _gap(self, unit: _Unit, t: float) -> Gap | None:
        if unit.period_s is None or unit.last_t is None:
            return None
        dt = t - unit.last_t
        if dt <= GAP_PERIODS * unit.period_s:
            return None
        n = max(1, round(dt / unit.period_s) - 1)
        self._count("samples_missed", n)
        return Gap(unit.name, unit.key, unit.last_t, t, n)

    def flush(self) -> tuple[list[tuple[str, Message]], list[Gap]]:
        """Release every pending time (end of an export, a bridge stopping); live samples
        still held ahead of the plant clock are refused."""
        out: list[tuple[str, Message]] = []
        gaps: list[Gap] = []
        for unit in self.units:
            for h in [h for q in unit.held.values() for h in q]:
                self._refuse(unit, h, "still ahead of the plant clock at the end")
            unit.held.clear()
            if unit.pending:
                m, g = self._release(unit, max(unit.pending))
                out += m
                gaps += g
        return out, gaps
