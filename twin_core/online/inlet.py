"""Alignment of per-feeder flow streams into the blender inlet composition.

Feeders publish independently; the blender inlet at tick n (t = n dt) is known once every feeder
has reported tick n. The mass fraction of component i at the inlet is the flow-weighted mix

    x_i = 100 * sum_{f feeds i} F_f / sum_f F_f   (% w/w),                          (1)

the steady mass balance of a mixing point (Fogler, ch. 1). :class:`InletAligner` buffers flows
by tick, releases complete ticks in order, and, when one feeder lags more than ``max_lag``
ticks behind the others (a lost or late message), releases the old tick holding that feeder's
last value (counted in ``held_``) so the stream never stalls.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

__all__ = ["InletAligner", "TracerInjector", "composition_pct"]


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


class InletAligner:
    """Buffer per-feeder samples by tick and release complete ticks in time order.

    Args:
        feeders: feeder ids expected at every tick.
        dt: tick interval, s.
        max_lag: ticks a feeder may lag before its last value is held in its place.

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
        self._pending: dict[int, dict[str, float]] = {}
        self._last: dict[str, float] = {}
        self._next: int | None = None  # next tick to release
        self.held_ = 0
        self.late_ = 0

    def tick(self, t: float) -> int:
        """Tick index of plant time t."""
        return int(round(t / self.dt))

    def push(self, feeder: str, t: float, flow: float) -> list[tuple[float, dict[str, float]]]:
        """Add one feeder sample; return the ticks that became complete, as (t, flows)."""
        if feeder not in self.feeders:
            raise ValueError(f"feeder must be one of {self.feeders}, got {feeder!r}")
        n = self.tick(t)
        if self._next is not None and n < self._next:
            self.late_ += 1
            return []
        self._pending.setdefault(n, {})[feeder] = float(flow)
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


class TracerInjector:
    """Adds announced tracer pulses to the inlet mass flows of a tick stream.

    A pulse of ``mass_kg`` over [t0, t0 + duration) enters as the rate mass/duration spread over
    the tick bins [t - dt/2, t + dt/2) it overlaps (the binning of ``twin_core.plant.model``), so
    the mass is exact. Mass falling in bins already released when the pulse is announced is added
    to the next tick (one tick late) rather than lost.
    """

    def __init__(self, dt: float) -> None:
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be > 0, got {dt!r}")
        self.dt = float(dt)
        self._pulses: list[tuple[str, float, float, float]] = []  # component, t0, t1, kg/h
        self._carry: dict[str, float] = {}
        self._last_tick: float | None = None

    def add_pulse(self, component: str, t_s: float, mass_kg: float, duration_s: float) -> None:
        """Announce a pulse (kg over s) of ``component`` starting at ``t_s``."""
        if not (duration_s > 0 and mass_kg >= 0 and math.isfinite(t_s)):
            raise ValueError(
                f"tracer pulse needs duration_s > 0, mass_kg >= 0 and a finite t_s, got "
                f"{duration_s!r}, {mass_kg!r}, {t_s!r}"
            )
        rate_kg_h = mass_kg / duration_s * 3600.0
        t1 = t_s + duration_s
        if self._last_tick is not None:
            edge = self._last_tick + 0.5 * self.dt
            missed = max(0.0, min(edge, t1) - t_s)
            if missed > 0:
                self._carry[component] = (
                    self._carry.get(component, 0.0) + rate_kg_h * missed / self.dt
                )
                t_s = min(edge, t1)
        if t1 > t_s:
            self._pulses.append((component, t_s, t1, rate_kg_h))

    def apply(self, t: float, mass_kg_h: dict[str, float]) -> dict[str, float]:
        """Add the tracer flows (kg/h) of tick ``t`` to ``mass_kg_h`` (in place; returned)."""
        lo, hi = t - 0.5 * self.dt, t + 0.5 * self.dt
        keep = []
        for comp, a, b, rate in self._pulses:
            overlap = max(0.0, min(hi, b) - max(lo, a))
            mass_kg_h[comp] = mass_kg_h.get(comp, 0.0) + rate * overlap / self.dt
            if b > hi:
                keep.append((comp, a, b, rate))
        self._pulses = keep
        for comp, q in self._carry.items():
            mass_kg_h[comp] = mass_kg_h.get(comp, 0.0) + q
        self._carry.clear()
        self._last_tick = t
        return mass_kg_h
