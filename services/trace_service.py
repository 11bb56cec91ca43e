"""The trace service: the lot composition of the product at the blender outlet, every tick, on
``twin/<line>/trace/outlet`` (``schemas.tracking.LotComposition``; the recorder records it).

Thin shell over ``twin_core.online.trace.LiveTracker``: the feeders' flows and hopper masses,
the plant's refill events (their ``lot_id``), and the blender model updates the blender adopts
(RTD estimates with ``blender.adopt_rtd_estimates``, close-loop effects with
``blender.adopt_findings``, from their ``applies_from_s``). Like the blender, a restarted trace
service rebuilds its state from the publishers' history and publishes again only from the last
tick it marked (``services.common.TickMark``) less ``republish_ticks``. With the line config's
``batch:`` it also publishes each batch's start and end on ``twin/<line>/trace/batch``
(``schemas.tracking.BatchBoundary``; ``twin_core.tracking.batches.BatchCounter``, the rule
``twin batch report`` cuts a recording with).
"""

from __future__ import annotations

from typing import Any

from schemas import keys
from schemas.closeloop import ModelFinding
from schemas.line import LineSpec
from schemas.messages import Event, FeederFlow, RtdEstimate
from schemas.tracking import BatchBoundary, LotComposition
from services.common import TickMark, applies_from
from services.service import Service
from twin_core.online.trace import LiveTracker


class TraceService(Service):
    """See the module docstring."""

    republish_ticks = 300

    def __init__(self, spec: LineSpec, **kwargs: Any) -> None:
        super().__init__("trace", spec=spec, **kwargs)
        self.core = LiveTracker(spec, max_lag=max(1, int(spec.inlet_max_lag_s / spec.dt_s)))
        self._mark = TickMark(self.state_path / "trace.last_t")
        self.last_published_t = self._mark.read()
        self._last_effects: list[dict] = []

    def setup(self) -> None:
        line = self.spec.name
        self.pub = self.publisher(keys.trace_outlet(line), LotComposition, history=True)
        self.batch_pub = self.publisher(keys.trace_batch(line), BatchBoundary, history=True)
        self.history_subscribe(keys.feeder_flows(line), FeederFlow)
        self.history_subscribe(keys.events(line), Event)
        if self.spec.blender.adopt_rtd_estimates:
            self.history_subscribe(keys.rtd_estimate(line), RtdEstimate)
        if self.spec.blender.adopt_findings:
            self.history_subscribe(keys.model_finding(line), ModelFinding)

    def handle(self, key: str, msg: Any) -> None:
        if isinstance(msg, FeederFlow):
            self._flow(key, msg)
        elif isinstance(msg, Event):
            if self.core.add_event(msg):
                self.counters.inc("refill_events")
        elif isinstance(msg, RtdEstimate):
            self.core.schedule(applies_from(msg, self.spec), "estimate", (msg.model, msg.params))
        elif isinstance(msg, ModelFinding):
            effects = [e.model_dump() for e in msg.model_effects]
            if effects != self._last_effects:
                self._last_effects = effects
                self.core.schedule(applies_from(msg, self.spec), "effects", effects)

    def _flow(self, key: str, msg: FeederFlow) -> None:
        feeder = keys.parse_key(key).id
        if feeder not in self.spec.components:
            self.counters.inc("rejected_unknown")
            return
        for t, lots, comps, outlet, boundaries in self.core.push(
            feeder, msg.t, msg.mass_flow_kg_h, msg.hopper_mass_kg
        ):
            if t <= self.last_published_t - self.republish_ticks * self.spec.dt_s:
                continue  # published before a restart (the last ticks are sent again)
            self.pub.publish(
                LotComposition(
                    t=t,
                    seq=int(round(t / self.spec.dt_s)),
                    lots=lots,
                    components=comps,
                    outlet_kg_h=outlet,
                    hopper_model=self.spec.tracking.hopper,
                )
            )
            for kind, batch, total in boundaries:
                self.batch_pub.publish(
                    BatchBoundary(
                        t=t,
                        seq=2 * batch + (kind == "end"),
                        batch=batch,
                        boundary=kind,
                        by=self.spec.batch.by,  # type: ignore[union-attr]
                        total=total,
                    )
                )
                self.counters.inc(f"batch_{kind}s")
            self.last_published_t = t
            self._mark.write(t)

    def finish(self) -> None:
        self._mark.close()
