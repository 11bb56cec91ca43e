"""The material tracking of a running line: the trace service's core (no bus;
``twin_core.tracking`` is the model).

Feeder samples come one message at a time; :class:`~twin_core.online.inlet.InletAligner`
releases complete ticks in order (as for the blender); refill events apply to the first tick
at or after their time; the E(t) is the blender's own ``BlenderKernel`` with the updates the
blender adopts (:meth:`LiveTracker.schedule`: RTD estimates, close-loop effects, from their
``applies_from_s``), set on the tracker from the tick it applies to. Each tick gives the lot
composition of the product leaving (``MaterialTracker.push``), equal to ``track_lots`` on the
same record. The trace service does not wait for the rtd and closeloop services' progress as
the blender does: under load an update may apply a few ticks later than in the blender.
"""

from __future__ import annotations

import bisect
from typing import Any

import numpy as np

from schemas.line import LineSpec
from twin_core.online.blender import BlenderKernel
from twin_core.online.inlet import InletAligner
from twin_core.tracking.batches import BatchCounter
from twin_core.tracking.hopper import mixed_fraction
from twin_core.tracking.tracker import MaterialTracker

__all__ = ["LiveTracker", "TraceTick"]

#: (plant time, lot -> fraction of the product, lot -> component, outlet kg/h, batch
#: boundaries at this tick: ("start" | "end", batch, quantity since the first batch started))
TraceTick = tuple[float, dict[str, float], dict[str, str], float, list[tuple[str, int, float]]]


class LiveTracker:
    """See the module docstring. ``min_fraction``: lots at or below it are left out of a
    tick's composition."""

    def __init__(self, spec: LineSpec, max_lag: int = 600, min_fraction: float = 1e-6) -> None:
        self.spec = spec
        self.kernel = BlenderKernel(spec)
        alpha = mixed_fraction(spec.tracking.hopper, spec.tracking.mixed_fraction)
        self.tracker = MaterialTracker(
            spec.components,
            spec.dt_s,
            self.kernel.e,
            alpha,
            {f.id: f.initial_lot for f in spec.feeders},
        )
        self.aligner = InletAligner(list(spec.components), spec.dt_s, max_lag)
        self.min_fraction = float(min_fraction)
        #: refill events not applied yet: (t, order, kind, feeder, lot, mass)
        self._events: list[tuple[float, int, str, str, str | None, float | None]] = []
        self._n = 0
        b = spec.batch
        self.batches = BatchCounter(b.size, b.start_s) if b is not None else None
        self._api = [
            f for f, c in spec.components.items() if b is not None and c == b.api_component
        ]

    def add_event(self, event: Any) -> bool:
        """A plant ``Event``; a refill of a known feeder is kept for its tick (True)."""
        if event.kind not in ("refill_start", "refill_stop"):
            return False
        if event.source not in self.spec.components:
            return False
        item = (float(event.t), self._n, event.kind, event.source, event.lot_id, event.mass_kg)
        self._n += 1
        bisect.insort(self._events, item)
        return True

    def schedule(self, t_from: float, kind: str, payload: Any) -> None:
        """A blender model update from plant time ``t_from`` (``BlenderKernel.schedule``)."""
        self.kernel.schedule(t_from, kind, payload)

    def push(self, feeder: str, t: float, flow_kg_h: float, hopper_kg: float) -> list[TraceTick]:
        """One feeder sample; returns the ticks it completed."""
        out = []
        for tick, row in self.aligner.push(feeder, t, (flow_kg_h, hopper_kg)):
            eps = 1e-9 * self.spec.dt_s
            while self._events and self._events[0][0] <= tick + eps:
                _, _, kind, f, lot, mass = self._events.pop(0)
                if kind == "refill_start":
                    self.tracker.refill_start(f, lot)
                else:
                    self.tracker.refill_stop(f, mass)
            if self.kernel.apply_due(tick):
                self.tracker.set_kernel(self.kernel.e)
            y = self.tracker.push(
                tick, {f: v[0] for f, v in row.items()}, {f: v[1] for f, v in row.items()}
            )
            total = float(y.sum())
            lots: dict[str, float] = {}
            comps: dict[str, str] = {}
            if total > 0:
                for j in np.nonzero(y > self.min_fraction * total)[0]:
                    name = self.tracker.lots[j]
                    lots[name] = min(1.0, float(y[j] / total))
                    comps[name] = self.tracker.lot_component[j]
            out.append((tick, lots, comps, total * 3600.0, self._boundaries(tick, row, total)))
        return out

    def _boundaries(
        self, tick: float, row: dict[str, Any], outlet_kg_s: float
    ) -> list[tuple[str, int, float]]:
        """The batch boundaries at this tick (``BatchCounter`` on the configured quantity)."""
        if self.batches is None:
            return []
        by, dt = self.spec.batch.by, self.spec.dt_s  # type: ignore[union-attr]
        if by == "run_time":
            q = dt
        elif by == "product_mass":
            q = outlet_kg_s * dt
        else:  # api_mass: the API feeders' measured discharge
            q = sum(max(0.0, float(row[f][0])) for f in self._api) / 3600.0 * dt
        return [(kind, k, self.batches.total) for kind, k, _ in self.batches.push(tick, q)]
