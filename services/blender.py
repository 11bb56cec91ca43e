"""Blender service: the predicted outlet concentration of every component, tick by tick.

Shell over :class:`twin_core.online.blender.BlenderPredictor` (mass-flow-weighted streaming
RTD convolution of the feeder flows, tracer pulses included). Subscribes
``twin/<line>/feeder/*/flow`` and the plant's events ``twin/<line>/*/*/event`` (tracer pulses);
with ``blender.adopt_rtd_estimates`` the rtd service's ``twin/<line>/rtd/estimate``, with
``blender.adopt_findings`` the closeloop service's ``twin/<line>/closeloop/finding`` (the
effects the blender cannot adopt are counted in ``not_adopted``). Publishes one
:class:`~schemas.messages.PredictedConcentration` per component per tick on
``twin/<line>/blender/outlet/predicted``.

A restarted blender recomputes from the flow history and does not publish a tick again: the last
published tick is written to the run's state directory after each tick (one ``pwrite`` of a
fixed-width number: a crash between a publication and its mark repeats at most that tick, which
the subscribers and the recorder drop as a duplicate).
"""

from __future__ import annotations

import logging
from typing import Any

from schemas import keys
from schemas.closeloop import ModelFinding
from schemas.line import LineSpec
from schemas.messages import Event, FeederFlow, PredictedConcentration, RtdEstimate
from services.common import TickMark
from services.service import Service
from twin_core.online.blender import BlenderPredictor
from twin_core.online.inlet import event_record

log = logging.getLogger(__name__)


class BlenderService(Service):
    """See the module docstring."""

    def __init__(self, spec: LineSpec, **kwargs: Any) -> None:
        super().__init__("blender", spec=spec, **kwargs)
        self.core = BlenderPredictor(spec)
        self._mark = TickMark(self.state_path / "blender.last_t")
        self.last_published_t = self._mark.read()

    def setup(self) -> None:
        line = self.spec.name
        self.pub = self.publisher(
            keys.predicted_concentration(line, "outlet"), PredictedConcentration, history=True
        )
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
            if self.core.add_event(event_record(msg)):
                self.counters.inc("tracer_pulses")
        elif isinstance(msg, RtdEstimate):
            self.core.adopt_estimate(msg.model, msg.params)
            self.counters.inc("rtd_adopted")
        elif isinstance(msg, ModelFinding):
            self._finding(msg)

    def _finding(self, msg: ModelFinding) -> None:
        new = [e.model_dump() for e in msg.model_effects]
        if self.core.kernel.same_effects(new):
            return
        left = self.core.set_effects(new)
        self.counters.inc("findings_adopted")
        if left:
            self.counters.inc("not_adopted", len(left))
            log.info(
                "blender: finding %s: not adopted: %s",
                msg.finding_id,
                ", ".join(e.label() for e in left),
            )

    def _flow(self, key: str, msg: FeederFlow) -> None:
        feeder = keys.parse_key(key).id
        if feeder not in self.core.components:
            self.counters.inc("rejected_unknown")
            return
        n_comp = len(self.core.comp_names)
        for t, conc in self.core.push(feeder, msg.t, msg.mass_flow_kg_h, msg.refilling):
            if t <= self.last_published_t:
                continue  # already published before a restart
            for i, c in enumerate(self.core.comp_names):
                self.pub.publish(
                    PredictedConcentration(
                        t=t,
                        seq=int(round(t / self.spec.dt_s)) * n_comp + i,
                        model=self.core.kernel.model_name,
                        component=c,
                        concentration_pct_w_w=conc[c],
                    )
                )
            self.last_published_t = t
            self._mark.write(t)

    def finish(self) -> None:
        self._mark.close()
