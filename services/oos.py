"""OOS diverter service: OOS alerts with stable ids and divert commands.

Thin shell over :class:`twin_core.online.OosDecider` (one per specified component):

- inputs: feeder flows ``twin/<line>/feeder/*/flow`` and announced tracer pulses
  (``tracer_pulse`` events with their mass) give the inlet signal of the funnel early flag,
  the linearised composition ``x = c0 + 100 (m_i - c0/100 m_tot) / m_nom`` (c0 the target,
  m_nom the sum of the set points): the first-order perturbation of the mass-flow-weighted
  outlet ``100 (E * m_i) / (E * m_tot)`` is exactly the convolution of ``x - c0`` with E(t),
  so the funnel applies to flow pulses (tracer) as well as to composition changes;
  measured concentration ``twin/<line>/pat/<sensor>/concentration`` and, when the blender runs,
  predictions ``twin/<line>/blender/outlet/predicted``; the three streams are merged in plant
  time (:class:`twin_core.online.WatermarkMerger`) so decisions do not depend on arrival order;
- traceability: outlet windows from ``twin_core.quality.lots.diversion_window`` with the blender
  E(t) and the configured lot quantiles; funnel gain from the same E(t);
- outputs: :class:`~schemas.messages.OosAlert` on ``twin/<line>/oos/alert`` (one per episode,
  when its window is complete) and :class:`~schemas.messages.DivertCommand` on
  ``twin/<line>/divert/command`` (``<alert>.open`` as soon as an episode is known, early for
  feeder disturbances; ``<alert>.final`` with the final window).

If one input stream stalls (the blender down) while the others keep coming, decisions are held
back (deterministic order) for at most ``oos.stall_release_s`` wall seconds, then made on the streams
present (``degraded_releases``): a dead model never blocks a measured OOS alert.

An ``Event`` of kind ``note`` with detail ``end-of-stream`` on ``twin/<line>/plant/replay/event``
(end of a replay, at the plant time of the last sample) closes what is open once every input
stream has reached that time (flows and predictions come through other services, later than
the event), or after ``idle_release_s`` of silence. Restart: inputs come back from the publishers' history,
the decisions are recomputed, and outputs already published (ids in the run's output log) are
not sent again.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from typing import Any

import numpy as np

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import (
    DivertCommand,
    Event,
    FeederFlow,
    MeasuredConcentration,
    OosAlert,
    PredictedConcentration,
)
from services.blender import blender_kernel
from services.common import LiveService, OutputLog
from twin_core.online import (
    DiverterOutput,
    InletAligner,
    OosDecider,
    TracerInjector,
    WatermarkMerger,
)

log = logging.getLogger(__name__)

END_OF_STREAM = "end-of-stream"
#: the inlet stream enters the event-time merge at least this many ticks ahead of its plant time
INLET_LEAD_TICKS = 2


def replay_event_key(line: str) -> str:
    """Key of the virtual plant's replay events (end of stream)."""
    return keys.event(line, "plant", "replay")


def funnel_gain(tk: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Funnel boundary M(d) = max_t [F(t) - F(t - d)] for d = m dt, m = 0..K
    (``twin_core.quality.funnel.max_window_fraction``), indexed by the pulse length in ticks."""
    from twin_core.quality.funnel import max_window_fraction

    dt = float(tk[1] - tk[0])
    return np.maximum.accumulate(max_window_fraction(tk, e, np.arange(tk.size + 1) * dt))


class OosCore:
    """Stream logic of the diverter without the bus: feed messages, get outputs."""

    def __init__(self, spec: LineSpec, e: np.ndarray | None = None) -> None:
        from twin_core.quality.lots import diversion_window

        self.spec = spec
        dt = spec.dt_s
        e = blender_kernel(spec) if e is None else np.asarray(e, float)
        tk = np.arange(e.size) * dt
        o = spec.oos
        gain = funnel_gain(tk, e) if o.use_funnel else None

        def window(a: float, b: float) -> tuple[float, float]:
            return diversion_window(a, b, tk, e, o.lot_lower, o.lot_upper)

        self.deciders: dict[str, OosDecider] = {
            s.component: OosDecider(
                line=spec.name,
                component=s.component,
                target=s.target_pct_w_w,
                lower=s.lower_pct_w_w,
                upper=s.upper_pct_w_w,
                dt=dt,
                gain=gain,
                window=window,
                n_on=o.n_on,
                n_off=o.n_off,
                hysteresis=o.hysteresis_pct_w_w,
                inlet_detect=o.inlet_detect_pct_w_w,
                inlet_n_on=o.inlet_n_on,
                inlet_n_off=o.inlet_n_off,
            )
            for s in spec.spec
        }
        self.use_predicted = "blender" in spec.services
        streams = ["inlet", "measured"] + (["predicted"] if self.use_predicted else [])
        self.merger = WatermarkMerger(streams)
        self.aligner = InletAligner(
            [f.id for f in spec.feeders], dt, max_lag=max(1, int(spec.inlet_max_lag_s / dt))
        )
        self.tracer = TracerInjector(dt)
        self.m_nom = sum(f.setpoint_kg_h for f in spec.feeders)
        #: aligned inlet ticks not yet released (tracer events for them may still arrive)
        self._held: deque[tuple[float, dict[str, float], float]] = deque()
        self.end_t: float | None = None
        self.finished = False
        #: wall time of the last release of the merge (None before anything was pending)
        self.last_release: float | None = None
        # An outlet decision at t depends on the inlet only up to t - t(F = lot_lower), so an
        # inlet tick can wait that long (less one tick) before it enters the merge at no cost in
        # decision latency: a tracer event may arrive up to ``inlet_hold_s`` of plant time after
        # the flows of its tick (other route, other publisher) and still count in its own tick.
        f = np.cumsum(e) * dt
        t_lo = float(np.argmax(f >= o.lot_lower)) * dt if f[-1] >= o.lot_lower else 0.0
        lead_ticks = max(INLET_LEAD_TICKS, int(math.floor(t_lo / dt + 1e-9)) - 1)
        self.inlet_lead_s = lead_ticks * dt
        self.inlet_hold_s = (lead_ticks - 1) * dt
        #: wall seconds an inlet tick is also held after its flows arrived (0: plant time only):
        #: a sample the bus missed reaches a subscriber one publisher heartbeat later
        self.inlet_grace_s = 0.0
        self._pulse_ts: set[float] = set()
        self._last: dict[tuple[str, str], float] = {}
        self.duplicates = 0

    def _fresh(self, stream: str, sub: str, t: float) -> bool:
        k = (stream, sub)
        if t <= self._last.get(k, -1.0):
            self.duplicates += 1
            return False
        self._last[k] = t
        return True

    def _process(self, released: list[tuple[str, float, Any]]) -> list[DiverterOutput]:
        out: list[DiverterOutput] = []
        if released:
            self.last_release = time.monotonic()
        for stream, t, item in released:
            if stream == "inlet":
                t_in, xs = item
                for comp, x in xs.items():
                    out += self.deciders[comp].inlet(t_in, x)
            else:
                comp, c = item
                d = self.deciders.get(comp)
                if d is not None:
                    out += d.measured(t, c) if stream == "measured" else d.predicted(t, c)
        return out

    def flow(self, feeder: str, t: float, flow_kg_h: float) -> list[DiverterOutput]:
        if not self._fresh("flow", feeder, t):
            return []
        out: list[DiverterOutput] = []
        for tt, flows in self.aligner.push(feeder, t, flow_kg_h):
            self._held.append((tt, flows, time.monotonic()))
        return out + self.release_inlet()

    def release_inlet(self) -> list[DiverterOutput]:
        """Release the held inlet ticks that are ``inlet_hold_s`` of plant time older than the
        newest and have waited ``inlet_grace_s`` wall seconds since their flows arrived."""
        out: list[DiverterOutput] = []
        now = time.monotonic()
        while self._held:
            t0, _, arrived = self._held[0]
            if self._held[-1][0] - t0 < self.inlet_hold_s - 1e-9:
                break
            if now - arrived < self.inlet_grace_s:
                break
            out += self._push_inlet()
        return out

    def _push_inlet(self) -> list[DiverterOutput]:
        """Release the oldest held inlet tick, merged at t + ``inlet_lead_s``. Ticks are held
        ``inlet_hold_s`` of plant time so that a tracer event arriving after the flows of its
        tick still counts there; an outlet decision at t depends on the inlet only up to
        t - t(F = lot_lower), so this costs no decision latency."""
        if not self._held:
            return []
        tt, flows, _ = self._held.popleft()
        mass: dict[str, float] = {}
        for f, q in flows.items():
            c = self.spec.components[f]
            mass[c] = mass.get(c, 0.0) + q
        self.tracer.apply(tt, mass)
        total = sum(mass.values())
        x = {
            c: d.target + 100.0 * (mass.get(c, 0.0) - d.target / 100.0 * total) / self.m_nom
            for c, d in self.deciders.items()
        }
        return self._process(self.merger.push("inlet", tt + self.inlet_lead_s, (tt, x)))

    def tracer_pulse(self, component: str, t: float, mass_kg: float, duration_s: float) -> None:
        """An announced tracer pulse: its mass enters the inlet composition (funnel, tracing)."""
        if t in self._pulse_ts:
            return  # the same event again (history after a restart)
        self._pulse_ts.add(t)
        self.tracer.add_pulse(component, t, mass_kg, duration_s)

    def measured(self, component: str, t: float, c: float) -> list[DiverterOutput]:
        if not self._fresh("measured", component, t):
            return []
        return self._process(self.merger.push("measured", t, (component, c)))

    def predicted(self, component: str, t: float, c: float) -> list[DiverterOutput]:
        if not self.use_predicted or not self._fresh("predicted", component, t):
            return []
        return self._process(self.merger.push("predicted", t, (component, c)))

    def announce_end(self, t_end: float) -> list[DiverterOutput]:
        """The plant's last sample is at ``t_end``: finish once every stream has reached it
        (the streams through the feeder and blender services arrive later than the event)."""
        self.end_t = t_end
        return self.finish_if_complete()

    def finish_if_complete(self) -> list[DiverterOutput]:
        if self.end_t is None or self.finished:
            return []
        slack = max(self.spec.dt_s, self.spec.sensor.sample_period_s)
        last = dict(self.merger.last)
        if self._held:
            last["inlet"] = self._held[-1][0] + self.inlet_lead_s
        if all(last.get(s, -math.inf) >= self.end_t - slack for s in self.merger.order):
            return self.end_of_stream()
        return []

    def release_all(self) -> list[DiverterOutput]:
        """Decide on what is there (a stalled stream): the held inlet ticks, then the merge."""
        out: list[DiverterOutput] = []
        while self._held:
            out += self._push_inlet()
        return out + self._process(self.merger.release_all())

    def end_of_stream(self) -> list[DiverterOutput]:
        """Close everything: release what the merge holds and close open episodes."""
        if self.finished:
            return []
        self.finished = True
        out = self.release_all()
        for d in self.deciders.values():
            out += d.flush()
        return out


def to_message(o: DiverterOutput, seq: int) -> OosAlert | DivertCommand:
    """The wire message of a diverter output."""
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
    )


class OosService(LiveService):
    """See the module docstring."""

    idle_release_s = 2.0
    #: wall seconds every inlet tick waits for late tracer events (two publisher heartbeats)
    inlet_grace_s = 1.0

    def __init__(self, spec: LineSpec, **kwargs: Any) -> None:
        super().__init__("oos", spec, **kwargs)
        self.core = OosCore(spec)
        # fast replays: a tracer event the bus delivers late (recovered on the publisher's
        # 0.5 s miss-detection heartbeat) must still find its inlet tick unreleased
        self.core.inlet_grace_s = self.inlet_grace_s
        self.log_ids = OutputLog(self.state_path / "oos.published")
        self._idle = 0.0

    def setup(self) -> None:
        line = self.spec.name
        self.alert_pub = self.history_publisher(keys.oos_alert(line), OosAlert)
        self.divert_pub = self.history_publisher(keys.divert_command(line), DivertCommand)
        self.history_subscribe(f"twin/{line}/feeder/*/flow", FeederFlow)
        self.history_subscribe(
            keys.measured_concentration(line, self.spec.sensor.id), MeasuredConcentration
        )
        if self.core.use_predicted:
            self.history_subscribe(
                keys.predicted_concentration(line, "outlet"), PredictedConcentration
            )
        self.history_subscribe(f"twin/{line}/*/*/event", Event)

    def handle(self, key: str, msg: Any) -> None:
        self._idle = 0.0
        if isinstance(msg, FeederFlow):
            outs = self.core.flow(keys.parse_key(key).id, msg.t, msg.mass_flow_kg_h)
        elif isinstance(msg, MeasuredConcentration):
            if msg.quality == "bad":
                self.counters.inc("ignored_bad_quality")
                return
            outs = self.core.measured(msg.component, msg.t, msg.concentration_pct_w_w)
        elif isinstance(msg, PredictedConcentration):
            outs = self.core.predicted(msg.component, msg.t, msg.concentration_pct_w_w)
        elif isinstance(msg, Event) and msg.kind == "note" and msg.detail == END_OF_STREAM:
            outs = self.core.announce_end(msg.t)
        elif isinstance(msg, Event) and msg.kind == "tracer_pulse" and msg.mass_kg:
            comp = msg.component or msg.source
            if comp in self.spec.components.values():
                self.core.tracer_pulse(comp, msg.t, msg.mass_kg, msg.duration_s or 1.0)
                self.counters.inc("tracer_pulses")
            return
        else:
            return
        self.emit(outs + (self.core.release_inlet() if not self.core.finished else []))
        if self.core.end_t is not None:
            self.emit(self.core.finish_if_complete())
        core = self.core
        if not len(core.merger):
            return
        now = time.monotonic()
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
            self.emit(core.release_all())

    def emit(self, outs: list[DiverterOutput]) -> None:
        for o in outs:
            if o.id in self.log_ids:
                self.counters.inc("suppressed_republish")
                continue
            pub = self.alert_pub if o.kind == "alert" else self.divert_pub
            pub.publish(to_message(o, pub.seq))
            self.log_ids.add(o.id)
            self.counters.inc("alerts" if o.kind == "alert" else "divert_commands")

    def idle(self) -> None:
        # a stream that went quiet (e.g. no blender) must not hold decisions back forever
        self._idle += self.idle_s
        if self._idle >= self.idle_release_s:
            if self.core.end_t is not None:
                self.emit(self.core.end_of_stream())  # a stream never reached the end
            elif len(self.core.merger) or self.core._held:
                # everything went quiet: release the held inlet ticks too
                self.emit(self.core.release_all())

    def finish(self) -> None:
        self.log_ids.close()
