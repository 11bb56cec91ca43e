"""RTD service: tracer-pulse experiments in the NIR signal -> fitted RTD estimates.

Shell over :class:`twin_core.online.rtd.RtdCore` (pulse detection, outliers, denoising,
truncation, fit; pulses found by themselves while a known disturbance or refill can reach the
outlet are skipped). Subscribes the NIR readings ``twin/<line>/pat/<sensor>/concentration``, the
plant's events ``twin/<line>/*/*/event`` (tracer pulses, disturbances) and the feeder flows
``twin/<line>/feeder/*/flow`` (their refill flags). Publishes
:class:`~schemas.messages.RtdEstimate` on ``twin/<line>/rtd/estimate`` (parameters of the
``twin_core.rtd.models`` function named in ``model``); the blender adopts it when
``blender.adopt_rtd_estimates`` is set.
"""

from __future__ import annotations

import logging
from typing import Any

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import Event, FeederFlow, MeasuredConcentration, RtdEstimate
from services.service import Service
from twin_core.online.inlet import event_record
from twin_core.online.rtd import PulseOutcome, RtdCore

log = logging.getLogger(__name__)


class RtdService(Service):
    """See the module docstring."""

    def __init__(self, spec: LineSpec, **kwargs: Any) -> None:
        super().__init__("rtd", spec=spec, **kwargs)
        self.core = RtdCore(spec)

    def setup(self) -> None:
        line = self.spec.name
        self.pub = self.publisher(keys.rtd_estimate(line), RtdEstimate, history=True)
        self.history_subscribe(
            keys.measured_concentration(line, self.spec.sensor.id), MeasuredConcentration
        )
        self.history_subscribe(keys.events(line), Event)
        self.history_subscribe(keys.feeder_flows(line), FeederFlow)

    def handle(self, key: str, msg: Any) -> None:
        if isinstance(msg, Event):
            if self.core.add_event(event_record(msg)):
                self.counters.inc("tracer_events")
        elif isinstance(msg, FeederFlow):
            self.core.flow(keys.parse_key(key).id, msg.t, msg.refilling)
        elif isinstance(msg, MeasuredConcentration) and msg.quality != "bad":
            outcome = self.core.measured(msg.t, msg.concentration_pct_w_w)
            if outcome is not None:
                self.publish_outcome(outcome)

    def publish_outcome(self, o: PulseOutcome) -> None:
        if o.kind == "skipped_disturbance":
            self.counters.inc("pulses_skipped_disturbance")
            return
        if o.result is None:
            self.counters.inc("fit_failed")
            self.counters.last_error = o.error
            log.warning("%s", o.error)
            return
        r = o.result
        self.pub.publish(
            RtdEstimate(
                t=float(o.segment.t[-1]),
                seq=self.pub.seq,
                model=r.model,
                params=r.params,
                stderr=r.stderr,
                mean_residence_time_s=r.mean_residence_time_s,
                pulse_t_s=r.pulse_t_s,
                n_points=r.n_points,
                rmse=r.rmse,
            )
        )
        self.counters.inc("estimates")
