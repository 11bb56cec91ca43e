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

__all__ = ["InletAligner", "composition_pct"]


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
