"""RTD service: tracer-pulse experiments in the NIR signal -> fitted RTD estimates.

Shell over :class:`twin_core.online.rtd.RtdCore` (pulse detection, outliers, denoising,
truncation, fit; pulses found by themselves while a known disturbance or refill can reach the
outlet are skipped). Subscribes the NIR readings ``twin/<line>/pat/<sensor>/concentration``, the
plant's events ``twin/<line>/*/*/event`` (tracer pulses, disturbances) and the feeder flows
``twin/<line>/feeder/*/flow`` (their refill flags). Publishes
:class:`~schemas.messages.RtdEstimate` on ``twin/<line>/rtd/estimate`` (parameters of the
``twin_core.rtd.models`` function named in ``model``); the blender adopts it when
``blender.adopt_rtd_estimates`` is set. A pulse that gives no estimate is published too, with
the reason (:class:`~schemas.messages.RtdSkipped` on ``twin/<line>/rtd/skipped``: the fit
failed, or an excursion of unknown cause while a known disturbance could reach the outlet), so
that a report lists it rather than missing it silently.

Each estimate applies from the plant time of the NIR sample that completed it plus
``blender.adoption_delay_s`` (``applies_from_s``); after each NIR sample the service reports on
``twin/<line>/rtd/progress`` (:class:`~schemas.messages.AdoptionProgress`, every
``progress_step_s`` of plant time and when idle) that every estimate applying up to that time is
out, so the blender and the diverter adopt it at that plant time whatever the machine load.

The estimates are a function of the plant data only: inputs are handled in plant-time order
after ``reorder_s`` (``services.service.Service``), so a tracer event that arrives a little after
the NIR samples of its time (another route) is still announced before them; a restarted service
recomputes from the history and does not publish an outcome again (ids in the run's output log).
"""

from __future__ import annotations

import logging
from typing import Any

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import (
    AdoptionProgress,
    Event,
    FeederFlow,
    MeasuredConcentration,
    RtdEstimate,
    RtdSkipped,
)
from services.common import OutputLog, ProgressReport, publish_once
from services.service import Service
from twin_core.online.inlet import event_record
from twin_core.online.rtd import PulseOutcome, RtdCore

log = logging.getLogger(__name__)


def outcome_id(line: str, pulse_t_s: float) -> str:
    """Stable id of the outcome of the pulse at ``pulse_t_s``."""
    return f"{line}.rtd-{int(round(pulse_t_s * 1000)):012d}"


class RtdService(Service):
    """See the module docstring."""

    #: inputs in plant-time order whatever their arrival, up to two publisher heartbeats late
    reorder_s = 1.0
    #: plant seconds between two progress reports
    progress_step_s = 5.0

    def __init__(self, spec: LineSpec, **kwargs: Any) -> None:
        super().__init__("rtd", spec=spec, **kwargs)
        self.core = RtdCore(spec)
        self.log_ids = OutputLog(self.state_path / "rtd.published")
        self.progress = ProgressReport(self.state_path / "rtd.progress", self.progress_step_s)

    def setup(self) -> None:
        line = self.spec.name
        self.pub = self.publisher(keys.rtd_estimate(line), RtdEstimate, history=True)
        self.skipped_pub = self.publisher(keys.rtd_skipped(line), RtdSkipped, history=True)
        self.pub.seq = self.log_ids.next_seq("estimate")
        self.skipped_pub.seq = self.log_ids.next_seq("skipped")
        self.progress.pub = self.publisher(
            keys.adoption_progress(line, "rtd"), AdoptionProgress, history=True
        )
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
        elif isinstance(msg, MeasuredConcentration):
            if msg.quality != "bad":
                outcome = self.core.measured(msg.t, msg.concentration_pct_w_w)
                if outcome is not None:
                    self.publish_outcome(outcome, msg.t)
            # every later outcome comes from a later sample: it applies after this time
            self.progress.advance(msg.t, msg.t + self.spec.blender.adoption_delay_s)

    def idle(self) -> None:
        self.progress.flush()

    def publish_outcome(self, o: PulseOutcome, t_data: float) -> None:
        """The estimate of a fitted pulse (applying from ``t_data``, the plant time of the sample
        that completed it, plus ``blender.adoption_delay_s``), or why a pulse gave none (once
        per pulse: ``services.common.publish_once``)."""
        oid = outcome_id(self.spec.name, o.segment.t0)
        t = float(o.segment.t[-1])
        if o.kind == "skipped_disturbance" or o.result is None:
            reason = "skipped_disturbance" if o.kind == "skipped_disturbance" else "fit_failed"
            detail = (
                f"pulse found by itself at {o.segment.t0:.1f} s while a known disturbance or "
                "refill could reach the outlet: not a tracer experiment"
                if reason == "skipped_disturbance"
                else o.error
            )

            def skipped(seq: int) -> RtdSkipped:
                return RtdSkipped(
                    t=t, seq=seq, pulse_t_s=o.segment.t0, reason=reason, detail=detail
                )

            if publish_once(self.log_ids, self.skipped_pub, oid, "skipped", skipped, self.counters):
                self.counters.inc(
                    "pulses_skipped_disturbance" if reason == "skipped_disturbance" else reason
                )
                if reason == "fit_failed":
                    self.counters.last_error = o.error
                    log.warning("%s", o.error)
            return
        r = o.result

        def estimate(seq: int) -> RtdEstimate:
            return RtdEstimate(
                t=t,
                seq=seq,
                model=r.model,
                params=r.params,
                stderr=r.stderr,
                mean_residence_time_s=r.mean_residence_time_s,
                pulse_t_s=r.pulse_t_s,
                n_points=r.n_points,
                rmse=r.rmse,
                applies_from_s=t_data + self.spec.blender.adoption_delay_s,
            )

        if publish_once(self.log_ids, self.pub, oid, "estimate", estimate, self.counters):
            self.counters.inc("estimates")
            self.progress.updated(t)

    def finish(self) -> None:
        self.progress.flush()
        self.progress.close()
        self.log_ids.close()
