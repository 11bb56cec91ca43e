"""The blender inlet, tick by tick: per-feeder samples aligned into complete ticks, tracer pulses
added to the ticks they cover.

Feeders publish independently; the blender inlet at tick n (t = n dt) is known once every feeder
has reported tick n. The mass fraction of component i at the inlet is the flow-weighted mix

    x_i = 100 * sum_{f feeds i} F_f / sum_f F_f   (% w/w),                          (1)

the steady mass balance of a mixing point (Fogler, ch. 1). :class:`InletAligner` buffers
samples by tick, releases complete ticks in order, and, when one feeder lags more than
``max_lag`` ticks behind the others (a lost or late message), releases the old tick holding that
feeder's last value (counted in ``held_``) so the stream never stalls. It is the one alignment of
the inlet: the blender prediction, the diverter (through :class:`InletStream`) and the
close-loop's record (``twin_core.closeloop.record.LineRecord``, online and offline) all use it.

A tracer pulse of ``mass_kg`` over [t0, t0 + duration) enters the inlet as the flow
mass/duration spread over the tick bins [t - dt/2, t + dt/2) it overlaps
(``twin_core.plant.model.pulse_bin_flow``, the binning of the declared line model), so the mass
is exact. :class:`TracerInjector` does this on a stream of ticks; :func:`tracer_pulse` reads the
pulse an event announces (the one reading of tracer events, used by every consumer).
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from schemas.line import TracerPulse
from twin_core.plant.model import pulse_bin_flow

__all__ = [
    "FeederSample",
    "InletAligner",
    "InletStream",
    "InletTick",
    "TracerInjector",
    "composition_pct",
    "event_record",
    "tracer_pulse",
]


def composition_pct(flows: Mapping[str, float], components: Mapping[str, str]) -> dict[str, float]:
    """Eq. (1): inlet composition (% w/w) per component from feeder flows (any unit).

    ``components`` maps feeder id -> component. A zero total flow raises ValueError.
    """
    total = float(sum(flows.values()))
    if not total > 0:
        raise ValueError(f"total flow must be > 0, got {total!r}")
    out: dict[str, float] = {}
    for feeder, flow in flows.items():
        comp = components[feeder]
        out[comp] = out.get(comp, 0.0) + 100.0 * flow / total
    return out


class FeederSample(NamedTuple):
    """What one feeder reported for one tick: mass flow (kg/h), its refill flag (the one source
    of refill state), screw speed (rpm, NaN if not reported)."""

    flow_kg_h: float
    refilling: bool = False
    screw_speed_rpm: float = math.nan


class InletAligner:
    """Buffer per-feeder samples by tick and release complete ticks in time order.

    Args:
        feeders: feeder ids expected at every tick.
        dt: tick interval, s.
        max_lag: ticks a feeder may lag before its last value is held in its place.

    Samples are any value (a flow, a :class:`FeederSample`); a released tick maps every feeder
    to its sample.

    Attributes:
        held_: number of (tick, feeder) values filled by holding the last value.
        late_: samples dropped because their tick was already released.
    """

    def __init__(self, feeders: Sequence[str], dt: float, max_lag: int = 20) -> None:
        if not feeders:
            raise ValueError("feeders must not be empty, got []")
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be > 0, got {dt!r}")
        if max_lag < 1:
            raise ValueError(f"max_lag must be >= 1, got {max_lag!r}")
        self.feeders = tuple(feeders)
        self.dt = float(dt)
        self.max_lag = int(max_lag)
        self._pending: dict[int, dict[str, Any]] = {}
        self._last: dict[str, Any] = {}
        self._next: int | None = None  # next tick to release
        self.held_ = 0
        self.late_ = 0

    def tick(self, t: float) -> int:
        """Tick index of plant time t."""
        return int(round(t / self.dt))

    def push(self, feeder: str, t: float, sample: Any) -> list[tuple[float, dict[str, Any]]]:
        """Add one feeder sample; return the ticks that became complete, as (t, samples)."""
        if feeder not in self.feeders:
            raise ValueError(f"feeder must be one of {self.feeders}, got {feeder!r}")
        n = self.tick(t)
        if self._next is not None and n < self._next:
            self.late_ += 1
            return []
        self._pending.setdefault(n, {})[feeder] = sample
        if self._next is None:
            self._next = n
        out = []
        while self._pending:
            k = self._next
            row = self._pending.get(k)
            newest = max(self._pending)
            if row is not None and len(row) == len(self.feeders):
                pass
            elif newest - k >= self.max_lag:
                row = dict(row or {})
                for f in self.feeders:
                    if f not in row:
                        if f not in self._last:
                            break
                        row[f] = self._last[f]
                        self.held_ += 1
                else:
                    self._pending[k] = row
                if len(row) < len(self.feeders):
                    # a feeder never seen yet: drop this tick
                    self._pending.pop(k, None)
                    self._next = k + 1
                    continue
            else:
                break
            self._pending.pop(k, None)
            self._last.update(row)
            out.append((k * self.dt, row))
            self._next = k + 1
        return out

    def flush(self) -> list[tuple[float, dict[str, Any]]]:
        """Release every pending tick in time order, as it is: a feeder whose sample never
        came is missing from its row (no value held in its place). For the end of a complete
        record, where a feeder's gap must not hold back every later tick."""
        out = [(k * self.dt, self._pending[k]) for k in sorted(self._pending)]
        if out:
            self._next = int(round(out[-1][0] / self.dt)) + 1
        self._pending.clear()
        return out


def event_record(event: Any) -> dict[str, Any]:
    """The dict form of a plant event (a ``schemas.messages.Event``): ``t_s``, ``kind``,
    ``source``, ``component``, ``mass_kg``, ``duration_s``, ``detail`` (what the close-loop keeps
    and :func:`tracer_pulse` reads)."""
    return {
        "t_s": float(event.t),
        "kind": event.kind,
        "source": event.source,
        "component": event.component,
        "mass_kg": event.mass_kg,
        "duration_s": event.duration_s,
        "detail": event.detail,
    }


def tracer_pulse(event: Mapping[str, Any], default_duration_s: float = 1.0) -> TracerPulse | None:
    """The tracer pulse an event announces, or None if it announces none.

    A ``tracer_pulse`` event with a positive ``mass_kg`` injects that mass of ``component``
    (``source`` when the event names no component) at ``t_s`` over ``duration_s``
    (``default_duration_s`` when not given or not positive).
    """
    if event.get("kind") != "tracer_pulse":
        return None
    mass = event.get("mass_kg")
    if mass is None or not math.isfinite(float(mass)) or float(mass) <= 0:
        return None
    dur = event.get("duration_s")
    if dur is None or not math.isfinite(float(dur)) or float(dur) <= 0:
        dur = default_duration_s
    comp = event.get("component") or event.get("source")
    return TracerPulse(
        t_s=float(event["t_s"]), mass_kg=float(mass), component=str(comp), duration_s=float(dur)
    )


class TracerInjector:
    """Adds announced tracer pulses to the inlet mass flows of a tick stream.

    A pulse enters as the flow mass/duration over the tick bins it overlaps
    (``twin_core.plant.model.pulse_bin_flow``). The part of a pulse that falls in ticks already
    released when it is announced is returned by :meth:`add_pulse` (tick time -> kg/h) for the
    caller to correct those ticks, or added to the next tick by :meth:`carry` (one tick late,
    mass kept).
    """

    def __init__(self, dt: float) -> None:
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be > 0, got {dt!r}")
        self.dt = float(dt)
        self._pulses: list[tuple[str, float, float, float]] = []  # component, t0, t1, kg/h
        self._carry: dict[str, float] = {}
        self._last_tick: float | None = None

    def add_pulse(
        self, component: str, t_s: float, mass_kg: float, duration_s: float
    ) -> dict[float, float]:
        """Announce a pulse (kg over s) of ``component`` starting at ``t_s``; return its flow
        (kg/h) in the ticks already released, by tick time (empty when announced in time)."""
        if not (duration_s > 0 and mass_kg >= 0 and math.isfinite(t_s)):
            raise ValueError(
                f"tracer pulse needs duration_s > 0, mass_kg >= 0 and a finite t_s, got "
                f"{duration_s!r}, {mass_kg!r}, {t_s!r}"
            )
        rate_kg_h = mass_kg / duration_s * 3600.0
        t1 = t_s + duration_s
        late: dict[float, float] = {}
        if self._last_tick is not None:
            edge = self._last_tick + 0.5 * self.dt
            k = math.floor((t_s + 0.5 * self.dt) / self.dt)
            while k * self.dt <= self._last_tick + 1e-9 * self.dt and (k - 0.5) * self.dt < t1:
                q = float(pulse_bin_flow(k * self.dt, self.dt, t_s, t1, rate_kg_h))
                if q > 0:
                    late[k * self.dt] = q
                k += 1
            t_s = min(max(edge, t_s), t1)
        if t1 > t_s:
            self._pulses.append((component, t_s, t1, rate_kg_h))
        return late

    def carry(self, component: str, late: Mapping[float, float]) -> None:
        """Add the late part of a pulse (:meth:`add_pulse`) to the next tick."""
        if late:
            self._carry[component] = self._carry.get(component, 0.0) + sum(late.values())

    def apply(self, t: float, mass_kg_h: dict[str, float]) -> dict[str, float]:
        """Add the tracer flows (kg/h) of tick ``t`` to ``mass_kg_h`` (in place; returned)."""
        self._last_tick = t
        if not self._pulses and not self._carry:
            return mass_kg_h
        hi = t + 0.5 * self.dt
        keep = []
        for comp, a, b, rate in self._pulses:
            mass_kg_h[comp] = mass_kg_h.get(comp, 0.0) + float(
                pulse_bin_flow(t, self.dt, a, b, rate)
            )
            if b > hi:
                keep.append((comp, a, b, rate))
        self._pulses = keep
        for comp, q in self._carry.items():
            mass_kg_h[comp] = mass_kg_h.get(comp, 0.0) + q
        self._carry.clear()
        return mass_kg_h


class InletTick(NamedTuple):
    """One released inlet tick: every feeder's sample and the tracer mass flows (kg/h) per
    component that enter in it."""

    t: float
    feeders: dict[str, FeederSample]
    tracer_kg_h: dict[str, float]

    def mass_kg_h(self, components: Mapping[str, str]) -> dict[str, float]:
        """Inlet mass flow per component (kg/h): the reported feeder flows summed per component
        (``components``: feeder id -> component), plus the tracer."""
        mass: dict[str, float] = {}
        for f, s in self.feeders.items():
            c = components[f]
            mass[c] = mass.get(c, 0.0) + s.flow_kg_h
        for c, q in self.tracer_kg_h.items():
            mass[c] = mass.get(c, 0.0) + q
        return mass


@dataclass
class InletStream:
    """Feeder samples -> inlet ticks in plant-time order, each with the tracer mass it holds.

    Samples are aligned (:class:`InletAligner`); a complete tick is held until the newest
    complete tick is ``hold_s`` of plant time later and ``grace_s`` of wall time has passed since
    it completed, so that a tracer event arriving after the flows of its tick (another route,
    another publisher) still counts in its own tick, then released with the tracer flows
    (:class:`TracerInjector`). A pulse announced after its ticks were released is added to the
    next tick (:meth:`add_pulse` with ``carry``) or returned for the caller to correct them.

    Args:
        components: feeder id -> component.
        dt: tick, s.
        max_lag: ticks a feeder may lag before its last value is held (:class:`InletAligner`).
        hold_s: plant time a complete tick waits for late tracer events, s.
        grace_s: wall time a complete tick also waits, s.
        clock: wall clock (seconds), for ``grace_s``.
    """

    components: Mapping[str, str]
    dt: float
    max_lag: int = 20
    hold_s: float = 0.0
    grace_s: float = 0.0
    clock: Callable[[], float] = time.monotonic
    _aligner: InletAligner = field(init=False, repr=False)
    _tracer: TracerInjector = field(init=False, repr=False)
    _held: deque[tuple[float, dict[str, FeederSample], float]] = field(init=False, repr=False)
    _pulses_seen: set[tuple[float, str]] = field(default_factory=set, repr=False)

    def __post_init__(self) -> None:
        self.components = dict(self.components)
        self._aligner = InletAligner(list(self.components), self.dt, max_lag=self.max_lag)
        self._tracer = TracerInjector(self.dt)
        self._held = deque()

    @property
    def pending(self) -> int:
        """Complete ticks held, not yet released."""
        return len(self._held)

    @property
    def oldest_held_t(self) -> float | None:
        """Plant time of the oldest held tick: no tick released later is older (None when
        nothing is held)."""
        return self._held[0][0] if self._held else None

    @property
    def newest_held_t(self) -> float | None:
        """Plant time of the newest held tick (None when nothing is held)."""
        return self._held[-1][0] if self._held else None

    def push(self, feeder: str, t: float, sample: FeederSample) -> list[InletTick]:
        """One feeder sample; return the ticks released (see the class docstring)."""
        ticks = self._aligner.push(feeder, t, sample)
        if not ticks:
            return []
        if self.hold_s <= 0 and self.grace_s <= 0 and not self._held:  # nothing to wait for
            return [InletTick(tt, row, self._tracer.apply(tt, {})) for tt, row in ticks]
        now = self.clock() if self.grace_s > 0 else 0.0
        self._held.extend((tt, row, now) for tt, row in ticks)
        return self.release(now)

    def add_pulse(self, pulse: TracerPulse, carry: bool = True) -> dict[float, float] | None:
        """Announce a tracer pulse; the same pulse again (history after a restart) is ignored
        (returns None). Its flow in ticks already released is carried to the next tick
        (``carry``) or returned (tick time -> kg/h) for the caller to correct them."""
        ident = (pulse.t_s, pulse.component)
        if ident in self._pulses_seen:
            return None
        self._pulses_seen.add(ident)
        late = self._tracer.add_pulse(pulse.component, pulse.t_s, pulse.mass_kg, pulse.duration_s)
        if carry:
            self._tracer.carry(pulse.component, late)
            return {}
        return late

    def release(self, now: float | None = None) -> list[InletTick]:
        """Release the held ticks that are ``hold_s`` of plant time older than the newest and
        have waited ``grace_s`` of wall time (``now``: the wall clock, read when not given)."""
        out: list[InletTick] = []
        if now is None:
            now = self.clock() if self.grace_s > 0 else 0.0
        while self._held:
            t0, _, arrived = self._held[0]
            if self._held[-1][0] - t0 < self.hold_s - 1e-9:
                break
            if now - arrived < self.grace_s:
                break
            out.append(self._release_oldest())
        return out

    def waive_grace(self) -> None:
        """The ticks held now need no more wall time: their samples came from history that is
        complete (a start or restart's catch-up), not from a live stream a missed sample may
        still be recovered into. They wait for ``hold_s`` of plant time only."""
        self._held = deque((t, row, -math.inf) for t, row, _ in self._held)

    def release_all(self) -> list[InletTick]:
        """Release every held tick (end of stream, or the input went quiet)."""
        return [self._release_oldest() for _ in range(len(self._held))]

    def _release_oldest(self) -> InletTick:
        tt, row, _ = self._held.popleft()
        return InletTick(tt, row, self._tracer.apply(tt, {}))
