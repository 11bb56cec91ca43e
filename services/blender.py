"""Blender service: the predicted outlet concentration of every component, tick by tick.

Shell over :class:`twin_core.online.blender.BlenderPredictor` (mass-flow-weighted streaming
RTD convolution of the feeder flows, tracer pulses included). Subscribes
``twin/<line>/feeder/*/flow`` and the plant's events ``twin/<line>/*/*/event`` (tracer pulses);
with ``blender.adopt_rtd_estimates`` the rtd service's ``twin/<line>/rtd/estimate``, with
``blender.adopt_findings`` the closeloop service's ``twin/<line>/closeloop/finding`` (the
effects the blender cannot adopt are counted in ``not_adopted``). Publishes one
:class:`~schemas.messages.PredictedConcentration` per component per tick on
``twin/<line>/blender/outlet/predicted``.

Adoption is a function of plant time only: an estimate or a finding applies from its
``applies_from_s`` (``twin_core.online.blender.BlenderKernel.schedule``), and a tick is predicted
only once every service it adopts from (``LineSpec.adoption_sources``) has said, with its
``AdoptionProgress``, that every update applying up to that tick is out; until then the feeder
flows wait (counted in ``held_for_adoption``). An update that comes after its tick was predicted
all the same (a producer that does not report its progress) is applied from the next tick,
counted in ``adopted_late`` with the largest lateness in ``adopted_late_max_ms`` (plant time)
and logged. A producer that reports nothing for ``blender.adoption_wait_s`` wall seconds (down)
holds the predictions back no longer (``adoption_bypassed``) until it reports again.

A restarted blender recomputes from the flow history and publishes again only the last
``republish_ticks`` ticks before the last one it marked: the last published tick is written to
the run's state directory after each tick (one ``pwrite`` of a fixed-width number), and a crash
can come between a publication and its mark, or after the mark while the tick is still in the
process's send queue; the subscribers and the recorder drop what they had as duplicates.
"""

from __future__ import annotations

import logging
from typing import Any

from schemas import keys
from schemas.closeloop import ModelFinding
from schemas.line import LineSpec
from schemas.messages import (
    AdoptionProgress,
    BlenderDrive,
    BlenderModelInUse,
    BlenderModelUpdate,
    DemJobRequest,
    Event,
    FeederFlow,
    PredictedConcentration,
    RtdEstimate,
)
from services.common import (
    AdoptionGate,
    TickMark,
    applies_from,
    follow_operating_point,
    record_late,
)
from services.service import Service
from twin_core.online.blender import BlenderPredictor
from twin_core.online.drive import OperatingPointTracker
from twin_core.online.inlet import event_record
from twin_core.plant.effects import make_effect

log = logging.getLogger(__name__)


class BlenderService(Service):
    """See the module docstring."""

    #: ticks before the last one marked that a restarted blender publishes again: a crash just
    #: after the mark can lose what was still in the process's send queue (the subscribers and
    #: the recorder drop the ones they had as duplicates). Under a CPU hog at 200x the queue
    #: held ~70 ticks when the blender was killed (20 lost 51 predictions); 300 ticks is 1.5 s
    #: of wall time at 200x, a few hundred duplicates at a restart
    republish_ticks = 300

    def __init__(self, spec: LineSpec, **kwargs: Any) -> None:
        super().__init__("blender", spec=spec, **kwargs)
        self.core = BlenderPredictor(spec)
        self._mark = TickMark(self.state_path / "blender.last_t")
        self.last_published_t = self._mark.read()
        self.gate = AdoptionGate(spec.adoption_sources())
        self.drive = OperatingPointTracker(spec)
        #: blade speeds a section run was requested for
        self._requested: set[float] = set()

    def setup(self) -> None:
        line = self.spec.name
        self.pub = self.publisher(
            keys.predicted_concentration(line, "outlet"), PredictedConcentration, history=True
        )
        self.model_pub = self.publisher(
            keys.blender_model_in_use(line), BlenderModelInUse, history=True
        )
        self.history_subscribe(keys.feeder_flows(line), FeederFlow)
        self.history_subscribe(keys.events(line), Event)
        self.history_subscribe(keys.blender_drives(line), BlenderDrive)
        self.history_subscribe(keys.blender_model_updates(line), BlenderModelUpdate)
        if self.spec.blender.adopt_rtd_estimates:
            self.history_subscribe(keys.rtd_estimate(line), RtdEstimate)
        if self.spec.blender.adopt_findings:
            self.history_subscribe(keys.model_finding(line), ModelFinding)
        for source in self.gate.sources:
            self.history_subscribe(keys.adoption_progress(line, source), AdoptionProgress)

    def handle(self, key: str, msg: Any) -> None:
        if isinstance(msg, (FeederFlow, BlenderDrive, BlenderModelUpdate)):
            follow_operating_point(self, self.drive, key, msg)
        if isinstance(msg, BlenderDrive):
            self._request_section_run(msg)
        if isinstance(msg, FeederFlow):
            if self.gate.hold(key, msg):
                self.counters.inc("held_for_adoption")
            else:
                self._flow(key, msg)
        elif isinstance(msg, Event):
            if self.core.add_event(event_record(msg)):
                self.counters.inc("tracer_pulses")
        elif isinstance(msg, RtdEstimate):
            late = self.core.schedule(
                applies_from(msg, self.spec), "estimate", (msg.model, msg.params)
            )
            record_late(self, late, msg)
            self.counters.inc("rtd_adopted")
            self._progress(self.gate.update("rtd", msg.t))
        elif isinstance(msg, ModelFinding):
            self._finding(msg)
            self._progress(self.gate.update("closeloop", msg.t))
        elif isinstance(msg, AdoptionProgress):
            unit = keys.parse_key(key).unit
            self._progress(self.gate.report(unit, msg.complete_to_s, msg.last_update_t_s))

    def _request_section_run(self, msg: BlenderDrive) -> None:
        """A blade speed more than 5 % outside the table of section models: ask the dem service
        (when it runs) for a section run there with the packaged scene ``blender.dem_preset``;
        the model it publishes joins the table (``BlenderModelUpdate``). Once per speed (2 %)."""
        b, table = self.spec.blender, self.core.kernel.table
        if table is None or b.dem_preset is None or "dem" not in self.spec.services:
            return
        rpm = float(msg.blade_speed_rpm)
        speeds = table.speeds
        if 0.95 * speeds[0] <= rpm <= 1.05 * speeds[-1]:
            return
        if any(abs(rpm - r) <= 0.02 * r for r in self._requested):
            return  # requested already (within 2 %)
        from schemas.dem_scene import load_scene
        from twin_core.scenes.presets import scene_data

        self._requested.add(rpm)
        job = f"blender_{round(rpm, 1):g}rpm"
        params = {"preset": b.dem_preset, "rpm": rpm, "analysis": True}
        scene = load_scene(scene_data("blender", job, {"preset": b.dem_preset}, None))
        req = DemJobRequest(
            t=msg.t,
            seq=len(self._requested),
            job_id=job,
            scene="blender",
            params=params,
            duration_s=scene.settle_s + scene.mix_s,
        )
        self.publish_request(req)
        self.counters.inc("dem_runs_requested")
        log.warning(
            "blender: %g rpm is outside the section models' %g-%g rpm: extrapolating, and a "
            "DEM run of the section (%s) was requested as job %s",
            rpm,
            speeds[0],
            speeds[-1],
            b.dem_preset,
            job,
        )

    def publish_request(self, req: DemJobRequest) -> None:
        """Put a DEM job request on its key (the dem service accepts puts)."""
        key = keys.dem_job(self.spec.name, req.job_id, "request")
        self.publisher(key, DemJobRequest).publish(req)

    def idle(self) -> None:
        # a producer down for long must not stop the predictions (module docstring)
        if self.gate.stalled(self.spec.blender.adoption_wait_s):
            self.counters.inc("adoption_bypassed")
            log.warning(
                "blender: no progress of %s for %.0f s; predicting without waiting for them",
                "/".join(self.gate.sources),
                self.spec.blender.adoption_wait_s,
            )
            for k, flow in self.gate.release_all():
                self._flow(k, flow)

    def _progress(self, moved: bool) -> None:
        """The flows the gate frees when a producer's progress moved."""
        if moved:
            for k, flow in self.gate.free():
                self._flow(k, flow)

    def _finding(self, msg: ModelFinding) -> None:
        new = [e.model_dump() for e in msg.model_effects]
        if new == self.core.kernel.latest_effects:
            return
        late = self.core.schedule(applies_from(msg, self.spec), "effects", new)
        record_late(self, late, msg)
        effs = [make_effect(e) for e in new]
        left = [e for e in effs if not self.core.kernel.adoptable(e)]
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
            if t <= self.last_published_t - self.republish_ticks * self.spec.dt_s:
                continue  # published before a restart (the last ticks are sent again)
            for i, c in enumerate(self.core.comp_names):
                self.pub.publish(
                    PredictedConcentration(
                        t=t,
                        seq=int(round(t / self.spec.dt_s)) * n_comp + i,
                        model=self.core.kernel.model_name,
                        component=c,
                        concentration_pct_w_w=conc[c],
                        model_version=self.core.kernel.version,
                    )
                )
            self.last_published_t = t
            self._mark.write(t)
            self._announce_switches(t)

    def _announce_switches(self, t: float) -> None:
        """A ``BlenderModelInUse`` for each model switch applied up to tick ``t`` (the start's
        at the first tick; seq from the tick, so a restarted blender's repeats are duplicates)."""
        k = self.core.kernel
        for i, (t_switch, reason) in enumerate(k.take_switches()):
            t_from = t if reason == "start" else t_switch
            point = k.point
            self.model_pub.publish(
                BlenderModelInUse(
                    t=t,
                    seq=int(round(t / self.spec.dt_s)) * 8 + min(i, 7),
                    kind="compartment" if k.table is not None else "rtd",
                    name=k.describe(),
                    reason=reason,
                    applies_from_s=t_from,
                    blade_speed_rpm=point.rpm if point is not None else None,
                    throughput_kg_h=point.throughput_kg_h if point is not None else None,
                    mean_residence_time_s=k.mean_residence_time_s(),
                    rule=k.rule_text(),
                    model_version=k.version,
                )
            )
            self.counters.inc("model_switches")

    def finish(self) -> None:
        self._mark.close()
