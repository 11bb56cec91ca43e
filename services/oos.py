"""OOS diverter service: OOS alerts with stable ids and divert commands.

Shell over :class:`twin_core.online.oos.OosCore` (inlet funnel flag, predicted and measured
outlet, merged in plant time; see there). Subscribes the feeder flows
``twin/<line>/feeder/*/flow``, the measured concentration
``twin/<line>/pat/<sensor>/concentration``, when the blender runs its predictions
``twin/<line>/blender/outlet/predicted``, the plant's events ``twin/<line>/*/*/event`` (tracer
pulses, the replay's end of stream) and, as the blender does (``blender.adopt_rtd_estimates``,
``blender.adopt_findings``), RTD estimates and closeloop findings: the diverter follows the
model the blender adopted, and a finding with the product at risk whose product-side reading
leaves the specification diverts its window (``OosCore.finding``). The model follows the
estimates and findings in plant time, as the blender's does: each applies from its
``applies_from_s``, and the decisions at a plant time wait until every service adopted from has
reported (``AdoptionProgress``) that the updates applying up to there are out (two more streams
of the merge; the wall-clock releases below decide only up to there, unless the producers have
been silent for ``blender.adoption_wait_s``: ``adoption_bypassed``); one that comes late all
the same is counted in ``adopted_late`` (largest lateness in ``adopted_late_max_ms``) and
logged. Publishes :class:`~schemas.messages.OosAlert` on
``twin/<line>/oos/alert`` (one per episode, when its window is complete) and
:class:`~schemas.messages.DivertCommand` on ``twin/<line>/divert/command`` (``<alert>.open`` as
soon as an episode is known, early for feeder disturbances; ``<alert>.final`` with the final
window).

If one input stream stalls (the blender down) while the others keep coming, decisions are held
back for at most ``oos.stall_release_s`` wall seconds, then made on the streams present
(``degraded_releases``): a dead model never blocks a measured OOS alert. The replay's
``END_OF_STREAM`` event (``schemas.messages``) closes what is open once every input stream has
reached its time, or after ``idle_release_s`` of silence. Restart: inputs come back from the
publishers' history, the decisions are recomputed, and outputs already published (ids in the
run's output log) are not sent again.

The diverter decides only on the line it is configured for: the first flow of each feeder and
the first measurement are checked against the configuration (``twin_core.online.feed``:
feeders, components, set points, sensor). On a mismatch it refuses the feed before any
decision: it logs the mismatch as an error, counts every message after it (``rejected_mismatch``)
instead of deciding on it, and reports ``degraded`` with the mismatch as its last error (``twin
status``), until it is restarted with a configuration that matches.
"""

from __future__ import annotations

import logging
import math
from functools import partial
from typing import Any

from schemas import keys
from schemas.closeloop import ModelFinding
from schemas.line import LineSpec
from schemas.messages import (
    END_OF_STREAM,
    AdoptionProgress,
    BlenderDrive,
    BlenderModelUpdate,
    DivertCommand,
    Event,
    FeederFlow,
    MeasuredConcentration,
    OosAlert,
    PredictedConcentration,
    RtdEstimate,
)
from services.common import (
    OutputLog,
    ProducerProgress,
    applies_from,
    follow_operating_point,
    publish_once,
    record_late,
)
from services.service import Service
from twin_core.online.diverter import DiverterOutput
from twin_core.online.drive import OperatingPointTracker
from twin_core.online.feed import FeedCheck
from twin_core.online.inlet import event_record
from twin_core.online.oos import OosCore

log = logging.getLogger(__name__)


def to_message(
    o: DiverterOutput, seq: int, model_version: str | None = None
) -> OosAlert | DivertCommand:
    """The wire message of a diverter output, naming the version of the blender model it was
    decided with."""
    if o.kind == "alert":
        return OosAlert(
            t=o.t,
            seq=seq,
            alert_id=o.id,
            component=o.component,
            t_start_s=o.t_start,
            t_end_s=max(o.t_end, o.t_start),
            peak_deviation_pct_w_w=o.peak_deviation,
            limit_pct_w_w=o.limit,
            cause=o.cause,
            model_version=model_version,
        )
    return DivertCommand(
        t=o.t,
        seq=seq,
        command_id=o.id,
        action="divert",
        t_start_s=o.t_start,
        t_end_s=max(o.t_end, o.t_start),
        alert_id=o.alert_id,
        reason=o.cause,
        model_version=model_version,
    )


class OosService(Service):
    """See the module docstring."""

    idle_release_s = 2.0
    #: wall seconds every inlet tick waits for late tracer events (two publisher heartbeats)
    inlet_grace_s = 1.0

    def __init__(self, spec: LineSpec, **kwargs: Any) -> None:
        super().__init__("oos", spec=spec, **kwargs)
        self.core = OosCore(spec)
        # fast replays: a tracer event the bus delivers late (recovered on the publisher's
        # 0.5 s miss-detection heartbeat) must still find its inlet tick unreleased
        self.core.inlet_grace_s = self.inlet_grace_s
        self.log_ids = OutputLog(self.state_path / "oos.published")
        self.feed = FeedCheck(spec)
        self.producers = ProducerProgress(self.core.adoption_sources)
        self.drive = OperatingPointTracker(spec)
        self._idle = 0.0

    def setup(self) -> None:
        line, b = self.spec.name, self.spec.blender
        self.alert_pub = self.publisher(keys.oos_alert(line), OosAlert, history=True)
        self.divert_pub = self.publisher(keys.divert_command(line), DivertCommand, history=True)
        # a restarted diverter goes on with the positions of the outputs it had published
        self.alert_pub.seq = self.log_ids.next_seq("alert")
        self.divert_pub.seq = self.log_ids.next_seq("divert")
        self.history_subscribe(keys.feeder_flows(line), FeederFlow)
        self.history_subscribe(
            keys.measured_concentration(line, self.spec.sensor.id), MeasuredConcentration
        )
        if self.core.use_predicted:
            self.history_subscribe(
                keys.predicted_concentration(line, "outlet"), PredictedConcentration
            )
        self.history_subscribe(keys.events(line), Event)
        self.history_subscribe(keys.blender_drives(line), BlenderDrive)
        self.history_subscribe(keys.blender_model_updates(line), BlenderModelUpdate)
        if b.adopt_rtd_estimates:
            self.history_subscribe(keys.rtd_estimate(line), RtdEstimate)
        if b.adopt_findings:
            self.history_subscribe(keys.model_finding(line), ModelFinding)
        for source in self.core.adoption_sources:
            self.history_subscribe(keys.adoption_progress(line, source), AdoptionProgress)

    def _check_feed(self, key: str, msg: Any) -> bool:
        """Whether the feed matches the configuration (module docstring); refuse it if not."""
        found = []
        if isinstance(msg, FeederFlow):
            found = self.feed.flow(keys.parse_key(key).id, msg.component, msg.setpoint_kg_h)
        elif isinstance(msg, MeasuredConcentration):
            found = self.feed.measured(msg.sensor, msg.component)
        if found:
            self.refuse(
                "the feed does not match the line configuration: "
                + "; ".join(str(x) for x in found)
                + " (no decision on it; restart the twin with the line's configuration)"
            )
        if self.feed.mismatches and isinstance(msg, (FeederFlow, MeasuredConcentration)):
            self.counters.inc("rejected_mismatch")
            return False
        return True

    def handle(self, key: str, msg: Any) -> None:
        self._idle = 0.0
        if not self._check_feed(key, msg):
            return
        outs = self._decide(key, msg)
        if outs is None:
            return
        core = self.core
        self.emit(outs + (core.release_inlet() if not core.finished else []))
        if core.end_t is not None:
            self.emit(core.finish_if_complete())
        if not len(core.merger):
            return
        now = core.clock()
        if core.last_release is None:
            core.last_release = now  # the clock starts with the first pending input
        elif now - core.last_release > self.spec.oos.stall_release_s:
            # an input stream (e.g. the blender's predictions) has stalled for long: decide on
            # what is there rather than hold measured OOS decisions back (counted, logged)
            self.counters.inc("degraded_releases")
            log.warning(
                "oos: a stream stalled for %.0f s; deciding on the streams present",
                self.spec.oos.stall_release_s,
            )
            self.emit(core.release_all(self._release_bound()))

    def _release_bound(self) -> float:
        """Merge time up to which the wall-clock releases may decide: where the model updates
        are known complete, or anywhere once the producers have been silent for
        ``blender.adoption_wait_s`` (counted in ``adoption_bypassed``)."""
        p = self.producers
        waiting_since = self.core.last_release or -math.inf  # decisions pending since
        if p.complete_to_s == math.inf or not p.silent_for(
            self.spec.blender.adoption_wait_s, waiting_since
        ):
            return p.complete_to_s
        self.counters.inc("adoption_bypassed")
        return math.inf

    def _decide(self, key: str, msg: Any) -> list[DiverterOutput] | None:
        """The core's outputs for one message (None: nothing to decide on)."""
        core = self.core
        if isinstance(msg, (FeederFlow, BlenderDrive, BlenderModelUpdate)):
            follow_operating_point(self, self.drive, key, msg)
        if isinstance(msg, FeederFlow):
            return core.flow(keys.parse_key(key).id, msg.t, msg.mass_flow_kg_h, msg.refilling)
        if isinstance(msg, MeasuredConcentration):
            if msg.quality == "bad":
                self.counters.inc("ignored_bad_quality")
                return None
            return core.measured(msg.component, msg.t, msg.concentration_pct_w_w)
        if isinstance(msg, PredictedConcentration):
            return core.predicted(msg.component, msg.t, msg.concentration_pct_w_w)
        if isinstance(msg, Event):
            if msg.kind == "note" and msg.detail == END_OF_STREAM:
                return core.announce_end(msg.t)
            if core.add_event(event_record(msg)):
                self.counters.inc("tracer_pulses")
            return None
        if isinstance(msg, AdoptionProgress):
            unit = keys.parse_key(key).unit
            return self._progress(
                unit, self.producers.report(unit, msg.complete_to_s, msg.last_update_t_s)
            )
        if isinstance(msg, RtdEstimate):
            late = core.schedule(applies_from(msg, self.spec), "estimate", (msg.model, msg.params))
            record_late(self, late, msg)
            self.counters.inc("rtd_adopted")
            return self._progress("rtd", self.producers.update("rtd", msg.t))
        if isinstance(msg, ModelFinding):
            new = [e.model_dump() for e in msg.model_effects]
            if new != core.kernel.latest_effects:
                record_late(self, core.schedule(applies_from(msg, self.spec), "effects", new), msg)
                self.counters.inc("findings_adopted")
            outs = core.finding(msg.model_dump())
            outs += self._progress("closeloop", self.producers.update("closeloop", msg.t))
            if msg.product_at_risk:
                self.counters.inc("product_at_risk")
            return outs
        return None

    def _progress(self, source: str, moved: bool) -> list[DiverterOutput]:
        """The decisions a producer's progress frees (when it moved)."""
        if not moved:
            return []
        return self.core.progress(source, self.producers.complete[source])

    def emit(self, outs: list[DiverterOutput]) -> None:
        version = self.core.kernel.version  # the model the outputs were decided with
        for o in outs:
            pub = self.alert_pub if o.kind == "alert" else self.divert_pub
            message = partial(to_message, o, model_version=version)
            sent = publish_once(self.log_ids, pub, o.id, o.kind, message, self.counters)
            if sent is not None:
                self.counters.inc("alerts" if o.kind == "alert" else "divert_commands")
        if self.core.finished and not self.counters.get("stream_ended"):
            self.counters.inc("stream_ended")  # the replay's end: every decision is out

    def caught_up(self) -> None:
        # the history is complete: what it held needs no wall-time grace (OosCore)
        self.emit(self.core.history_complete())

    def idle(self) -> None:
        # a stream that went quiet (e.g. no blender) must not hold decisions back forever
        self._idle += self.idle_s
        if self._idle >= self.idle_release_s:
            bound = self._release_bound()
            if self.core.end_t is not None and bound >= self.core.end_t:
                self.emit(self.core.end_of_stream())  # a stream never reached the end
            elif self.core.pending:
                # everything went quiet: release the held inlet ticks too (up to where the
                # model updates are known)
                self.emit(self.core.release_all(bound))

    def finish(self) -> None:
        self.log_ids.close()
