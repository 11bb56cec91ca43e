"""What the live twin would have decided on a recording: the cores of the blender and the
diverter services (:class:`~twin_core.online.blender.BlenderPredictor`,
:class:`~twin_core.online.oos.OosCore`) fed a recording's plant messages in their order,
without a bus.

``twin dashboard --recording`` shows them beside the recording: a recording of the plant alone
holds no prediction, alert or divert command, and a page showing the NIR readings out of the
specification beside "OOS alerts: none" and "Diverter: accepting" would say what the twin never
said. The decisions are those of the declared line model with the diverter's own rules (funnel
flag, traced windows, hysteresis): no RTD estimate or close-loop finding is adopted (those come
from other services), and blade-speed or throughput switches of a compartment-model blender are
not followed (the declared operating point throughout).
"""

from __future__ import annotations

from typing import Any

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import END_OF_STREAM, Event, FeederFlow, MeasuredConcentration
from twin_core.online.blender import BlenderPredictor
from twin_core.online.diverter import DiverterOutput
from twin_core.online.inlet import event_record
from twin_core.online.oos import OosCore

#: one outlet prediction: (plant time, {component: % w/w})
Prediction = tuple[float, dict[str, float]]


class RecordedDecisions:
    """Feed a recording's messages one by one (:meth:`push`), then :meth:`finish`; each call
    returns the blender's predictions and the diverter's outputs (alerts, divert commands) that
    message completed. Messages of other kinds (health, recorded predictions or decisions) are
    ignored."""

    def __init__(self, spec: LineSpec) -> None:
        # the blender and the diverter alone: nothing to wait for from other services
        self.spec = spec.model_copy(update={"services": ["blender", "oos"]})
        self.blender = BlenderPredictor(self.spec)
        self.core = OosCore(self.spec)

    def push(self, key: str, msg: Any) -> tuple[list[Prediction], list[DiverterOutput]]:
        """The predictions and decisions one recorded message gives."""
        core, preds, outs = self.core, [], []
        if isinstance(msg, FeederFlow):
            feeder = keys.parse_key(key).id
            if feeder not in self.blender.components:
                return [], []
            outs += core.flow(feeder, msg.t, msg.mass_flow_kg_h, msg.refilling)
            for t, conc in self.blender.push(feeder, msg.t, msg.mass_flow_kg_h, msg.refilling):
                preds.append((t, conc))
                for component, c in conc.items():
                    outs += core.predicted(component, t, c)
        elif isinstance(msg, MeasuredConcentration):
            if msg.quality != "bad":
                outs += core.measured(msg.component, msg.t, msg.concentration_pct_w_w)
        elif isinstance(msg, Event):
            if msg.kind == "note" and msg.detail == END_OF_STREAM:
                return [], core.announce_end(msg.t)
            event = event_record(msg)
            self.blender.add_event(event)
            core.add_event(event)
        else:
            return [], []
        if not core.finished:
            outs += core.release_inlet()
        return preds, outs

    def finish(self) -> list[DiverterOutput]:
        """The end of the recording: what the diverter still held, open episodes closed."""
        return [] if self.core.finished else self.core.end_of_stream()
