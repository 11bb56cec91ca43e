"""Stream logic of the OOS diverter (the oos service's core, no bus): feeder flows, tracer
events, measured and predicted outlet concentration in; alerts and divert commands out.

One :class:`~twin_core.online.diverter.OosDecider` per specified component gets three streams
merged by plant time (:class:`~twin_core.online.merge.WatermarkMerger`), so the decisions do not
depend on the order the streams arrive in:

- **inlet**: the linearised inlet composition of each component,
  ``x = c0 + 100 (m_i - c0/100 m_tot) / m_nom`` (c0 the target, m_nom the sum of the set
  points), from the aligned feeder flows plus the mass of announced tracer pulses
  (:class:`~twin_core.online.inlet.InletStream`): the first-order perturbation of the
  mass-flow-weighted outlet is exactly the convolution of ``x - c0`` with E(t), so the funnel
  (``twin_core.quality.funnel.funnel_gain``) applies to flow pulses (tracer) as well as to
  composition changes;
- **measured** (NIR) and **predicted** (blender) outlet concentrations.

E(t) is the blender's (:class:`~twin_core.online.blender.BlenderKernel`): the declared model,
or what the twin adopted (:meth:`OosCore.adopt_estimate`, :meth:`OosCore.adopt_effects`), so the
diverter follows the model the blender adopted; funnel gain and lot boundaries
(``twin_core.quality.lots.diversion_window`` with the configured quantiles) are rebuilt from it.

An outlet decision at t depends on the inlet only up to t - t(F = lot_lower), so an inlet tick
can wait that long (less one tick) before it enters the merge at no cost in decision latency: a
tracer event may arrive up to ``inlet_hold_s`` of plant time after the flows of its tick and
still count in its own tick. The hold comes from the declared E(t).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from schemas.line import LineSpec
from twin_core.online.blender import BlenderKernel
from twin_core.online.diverter import DiverterOutput, OosDecider
from twin_core.online.funnel import Excursion
from twin_core.online.inlet import FeederSample, InletStream, InletTick, tracer_pulse
from twin_core.online.merge import WatermarkMerger
from twin_core.plant.effects import Effect
from twin_core.quality.funnel import funnel_gain
from twin_core.quality.lots import diversion_window, excursion_window

__all__ = ["INLET_LEAD_TICKS", "OosCore"]

#: the inlet stream enters the event-time merge at least this many ticks ahead of its plant time
INLET_LEAD_TICKS = 2


def traceability(
    e: np.ndarray, dt: float, lower: float, upper: float
) -> Callable[[float, float], tuple[float, float]]:
    """RTD traceability of an inlet window to the outlet (lot boundaries, seed ch. 6):
    ``(t_in_start, t_in_end) -> (t_in_start + t(F = lower), t_in_end + t(F = upper))``."""
    tk = np.arange(e.size) * dt

    def window(a: float, b: float) -> tuple[float, float]:
        return diversion_window(a, b, tk, e, lower, upper)

    return window


def predicted_excursion(
    e: np.ndarray, dt: float, target: float, lower: float, upper: float, guard: float, pad: float
) -> Excursion:
    """The outlet window of an inlet episode from its predicted outlet
    (``twin_core.quality.lots.excursion_window`` with E(t) ``e``, the guard narrowing the
    limits), widened by ``pad`` s on each side: ``(t_in_start, deviations) -> window | None``."""

    def excursion(t0: float, dev: np.ndarray) -> tuple[float, float] | None:
        w = excursion_window(t0, dev, e, dt, target, lower, upper, guard)
        return None if w is None else (w[0] - pad, w[1] + pad)

    return excursion


class OosCore:
    """Stream logic of the diverter without the bus: feed messages, get outputs.

    Args:
        spec: the line (specification, OOS settings, tick, services).
        e: an E(t) on the tick grid to use instead of the declared blender model.
        clock: wall clock (s) for the inlet's ``inlet_grace_s``.
    """

    def __init__(
        self,
        spec: LineSpec,
        e: np.ndarray | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.spec = spec
        dt = spec.dt_s
        self.kernel = BlenderKernel(spec, e)
        o = spec.oos
        gain, window = self._funnel()
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
                excursion=self._excursion(s.component),
            )
            for s in spec.spec
        }
        self.use_predicted = "blender" in spec.services
        streams = ["inlet", "measured"] + (["predicted"] if self.use_predicted else [])
        #: producers of model updates whose progress holds the decisions back (plant-time
        #: adoption: ``schemas.messages.AdoptionProgress``)
        self.adoption_sources = spec.adoption_sources()
        streams += self.adoption_sources
        #: merge time of the last item decided on (None before any)
        self.t_done: float | None = None
        self.merger = WatermarkMerger(streams)
        self.m_nom = sum(f.setpoint_kg_h for f in spec.feeders)
        self.end_t: float | None = None
        self.finished = False
        #: wall time of the last release of the merge (None before anything was pending)
        self.last_release: float | None = None
        self.clock = clock
        e0 = self.kernel.e
        f = np.cumsum(e0) * dt
        t_lo = float(np.argmax(f >= o.lot_lower)) * dt if f[-1] >= o.lot_lower else 0.0
        lead_ticks = max(INLET_LEAD_TICKS, int(math.floor(t_lo / dt + 1e-9)) - 1)
        self.inlet_lead_s = lead_ticks * dt
        self.inlet = InletStream(
            spec.components,
            dt,
            max_lag=max(1, int(spec.inlet_max_lag_s / dt)),
            hold_s=(lead_ticks - 1) * dt,
            clock=clock,
        )
        self._last: dict[tuple[str, str], float] = {}
        self.duplicates = 0

    # -- the model ---------------------------------------------------------------------------
    def _funnel(self) -> tuple[np.ndarray | None, Callable[[float, float], tuple[float, float]]]:
        """Funnel gain (None when ``oos.use_funnel`` is off) and traceability of the E(t) in use."""
        o, dt, e = self.spec.oos, self.spec.dt_s, self.kernel.e
        gain = funnel_gain(e, dt) if o.use_funnel else None
        return gain, traceability(e, dt, o.lot_lower, o.lot_upper)

    def _excursion(self, component: str) -> Excursion | None:
        """The predicted-excursion window of ``component``'s inlet episodes under the E(t) in
        use (``oos.divert_window: excursion``), else None (the lot window)."""
        o = self.spec.oos
        if o.divert_window != "excursion":
            return None
        s = next(x for x in self.spec.spec if x.component == component)
        return predicted_excursion(
            self.kernel.e,
            self.spec.dt_s,
            s.target_pct_w_w,
            s.lower_pct_w_w,
            s.upper_pct_w_w,
            o.divert_guard_pct_w_w,
            o.divert_pad_s,
        )

    def _refresh_funnel(self) -> None:
        gain, window = self._funnel()
        for comp, d in self.deciders.items():
            d.set_funnel(gain, window, self._excursion(comp))

    def adopt_estimate(self, model: str, params: Mapping[str, float]) -> None:
        """The blender adopted an RTD estimate: follow it (funnel and lot boundaries)."""
        self.kernel.adopt_estimate(model, params)
        self._refresh_funnel()

    def schedule(self, t_from: float, kind: str, payload: Any) -> float:
        """A model update (``BlenderKernel.schedule``) followed from merge time ``t_from`` on,
        as the blender does; returns how late it came, s of plant time (0: in time; else the
        decisions already made at or after ``t_from``)."""
        self.kernel.schedule(t_from, kind, payload)
        if self.t_done is None or t_from > self.t_done:
            return 0.0
        return self.t_done - t_from

    def progress(self, source: str, complete_to_s: float) -> list[DiverterOutput]:
        """Every update of ``source`` applying up to ``complete_to_s`` is scheduled: the
        decisions up to there may be made."""
        return self._process(self.merger.advance(source, complete_to_s))

    def finding(self, finding: Mapping[str, Any]) -> list[DiverterOutput]:
        """A close-loop finding (``schemas.closeloop.ModelFinding`` in dict form) when the
        product is at risk: the product-side reading's outlet is checked against the
        specification of the measured component over the finding's window
        (``OosDecider.product_risk``). Its model's effects are followed through
        :meth:`schedule`."""
        out: list[DiverterOutput] = []
        reading = finding.get("product_reading")
        if not finding.get("product_at_risk") or not reading:
            return out
        comp = self.spec.sensor.component
        d = self.deciders.get(comp)
        if d is None:
            return out
        return d.product_risk(
            float(finding["t"]),
            str(finding["finding_id"]),
            float(reading["t_start_s"]),
            float(reading["t_end_s"]),
            float(reading["outlet_min_pct_w_w"]),
            float(reading["outlet_max_pct_w_w"]),
            reading.get("out_of_spec_s"),
        )

    def adopt_effects(self, effects: Sequence[Effect | Mapping]) -> list[Effect]:
        """The blender adopted a finding's effects: follow its E(t); returns the effects that
        could not be adopted."""
        left = self.kernel.adopt_effects(effects)
        self._refresh_funnel()
        return left

    # -- inputs ------------------------------------------------------------------------------
    @property
    def inlet_hold_s(self) -> float:
        """Plant time an inlet tick waits for late tracer events, s."""
        return self.inlet.hold_s

    @property
    def inlet_grace_s(self) -> float:
        """Wall time an inlet tick also waits after its flows arrived, s (0: plant time only):
        a sample the bus missed reaches a subscriber one publisher heartbeat later."""
        return self.inlet.grace_s

    @inlet_grace_s.setter
    def inlet_grace_s(self, value: float) -> None:
        self.inlet.grace_s = float(value)

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
            self.last_release = self.clock()
        for stream, t, item in released:
            if self.kernel.apply_due(t):
                self._refresh_funnel()
            self.t_done = t
            if stream == "inlet":
                t_in, xs, tracer_kg = item
                for comp, x in xs.items():
                    out += self.deciders[comp].inlet(t_in, x, tracer_kg.get(comp, 0.0))
            else:
                comp, c = item
                d = self.deciders.get(comp)
                if d is not None:
                    out += d.measured(t, c) if stream == "measured" else d.predicted(t, c)
        return out

    def flow(
        self, feeder: str, t: float, flow_kg_h: float, refilling: bool = False
    ) -> list[DiverterOutput]:
        """One feeder flow (kg/h)."""
        if not self._fresh("flow", feeder, t):
            return []
        out = self._merge_inlet(
            self.inlet.push(feeder, t, FeederSample(float(flow_kg_h), bool(refilling)))
        )
        return out + self._advance_inlet()

    def _advance_inlet(self) -> list[DiverterOutput]:
        """The inlet stream's watermark while its ticks are held: none released later enters
        the merge before the oldest held one, ``oldest + inlet_lead_s``. Without it the merge
        waited for the first released tick, ``inlet_hold_s`` of plant time after the start (or
        a restart), holding every measured decision of that stretch back (a blind start)."""
        oldest = self.inlet.oldest_held_t
        if oldest is None:
            return []
        # strictly before the oldest held tick's merge time: it, not yet merged, goes first there
        mark = math.nextafter(oldest + self.inlet_lead_s, -math.inf)
        return self._process(self.merger.advance("inlet", mark))

    def history_complete(self) -> list[DiverterOutput]:
        """The history of every input has been handled (the end of a start or restart's
        catch-up): the inlet ticks held now wait for plant time only, not for the wall-time
        grace meant for live samples (:meth:`InletStream.waive_grace`). Without it a restarted
        diverter held its first live decisions until the grace of the ticks it had just
        rebuilt from history ran out (0.15-0.45 s after it reported ``running``)."""
        self.inlet.waive_grace()
        return self.release_inlet() + self._advance_inlet()

    def release_inlet(self) -> list[DiverterOutput]:
        """Release the inlet ticks that have waited long enough (:class:`InletStream`)."""
        return self._merge_inlet(self.inlet.release())

    def _merge_inlet(self, ticks: list[InletTick]) -> list[DiverterOutput]:
        """Inlet ticks enter the merge ``inlet_lead_s`` ahead of their plant time."""
        out: list[DiverterOutput] = []
        for tick in ticks:
            mass = tick.mass_kg_h(self.spec.components)
            total = sum(mass.values())
            x = {
                c: d.target + 100.0 * (mass.get(c, 0.0) - d.target / 100.0 * total) / self.m_nom
                for c, d in self.deciders.items()
            }
            tracer_kg = {c: q * self.spec.dt_s / 3600.0 for c, q in tick.tracer_kg_h.items()}
            out += self._process(
                self.merger.push("inlet", tick.t + self.inlet_lead_s, (tick.t, x, tracer_kg))
            )
        return out

    def tracer_pulse(self, component: str, t: float, mass_kg: float, duration_s: float) -> bool:
        """An announced tracer pulse: its mass enters the inlet composition (funnel, tracing).
        Returns False for a pulse already announced (history after a restart)."""
        from schemas.line import TracerPulse

        pulse = TracerPulse(t_s=t, mass_kg=mass_kg, component=component, duration_s=duration_s)
        return self.inlet.add_pulse(pulse) is not None

    def add_event(self, event: Mapping) -> bool:
        """A plant event (dict form, ``twin_core.online.inlet.event_record``); returns whether
        it announced a new tracer pulse of a known component."""
        p = tracer_pulse(event)
        if p is None or p.component not in self.spec.components.values():
            return False
        return self.tracer_pulse(p.component, p.t_s, p.mass_kg, p.duration_s)

    def measured(self, component: str, t: float, c: float) -> list[DiverterOutput]:
        """One measured outlet concentration (% w/w)."""
        if not self._fresh("measured", component, t):
            return []
        return self._process(self.merger.push("measured", t, (component, c)))

    def predicted(self, component: str, t: float, c: float) -> list[DiverterOutput]:
        """One predicted outlet concentration (% w/w); ignored when the line has no blender."""
        if not self.use_predicted or not self._fresh("predicted", component, t):
            return []
        return self._process(self.merger.push("predicted", t, (component, c)))

    # -- end of stream, stalls ---------------------------------------------------------------
    def announce_end(self, t_end: float) -> list[DiverterOutput]:
        """The plant's last sample is at ``t_end``: finish once every stream has reached it
        (the streams through other services arrive later than the event)."""
        self.end_t = t_end
        return self.finish_if_complete()

    def finish_if_complete(self) -> list[DiverterOutput]:
        if self.end_t is None or self.finished:
            return []
        slack = max(self.spec.dt_s, self.spec.sensor.sample_period_s)
        last = dict(self.merger.last)
        held = self.inlet.newest_held_t
        if held is not None:
            last["inlet"] = held + self.inlet_lead_s
        if all(last.get(s, -math.inf) >= self.end_t - slack for s in self.merger.order):
            return self.end_of_stream()
        return []

    @property
    def pending(self) -> bool:
        """Whether anything waits in the merge or the inlet hold."""
        return bool(len(self.merger) or self.inlet.pending)

    def release_all(self, until: float = math.inf) -> list[DiverterOutput]:
        """Decide on what is there (a stalled stream): the held inlet ticks, then the merge up
        to merge time ``until`` (the model updates known up to there: default all)."""
        out = self._merge_inlet(self.inlet.release_all())
        return out + self._process(self.merger.release_all(until))

    def end_of_stream(self) -> list[DiverterOutput]:
        """Close everything: release what the merge holds and close open episodes."""
        if self.finished:
            return []
        self.finished = True
        out = self.release_all()
        for d in self.deciders.values():
            out += d.flush()
        return out
