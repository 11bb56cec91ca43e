"""Blender service: predicts the outlet concentration of every component from the feeder flows.

Thin shell over :class:`twin_core.online.StreamingConvolver` with the mass-flow-weighted RTD
model of the declared line (``twin_core.plant.model``):

    c_i(t) = 100 (E * m_i)(t) / (E * sum_j m_j)(t)   [% w/w]

one streaming convolution per component mass flow, the stream starting at steady state (the
first flows). Subscribes ``twin/<line>/feeder/*/flow``; publishes one
:class:`~schemas.messages.PredictedConcentration` per component per tick on
``twin/<line>/blender/outlet/predicted``. Announced tracer pulses (``tracer_pulse`` events with
their mass) enter the inlet of their component as in the declared model. With ``blender.adopt_rtd_estimates`` it replaces E(t)
by each RTD estimate the rtd service publishes (``twin/<line>/rtd/estimate``). With
``blender.adopt_findings`` it adopts the model of each closeloop finding
(``twin/<line>/closeloop/finding``): its blender (rtd-stage) effects transform E(t)
(``twin_core.plant.model.rtd_kernel``: dead zone, bypass, extra delay, back-mixing, on the
declared or latest estimated RTD) and its feeder-stage effects turn each feeder's reported flow
into the delivered one (e.g. a refill surge) before the convolution. Effects that grow with time
from the start of their window (drifts) and sensor effects (the probe, not the outlet) are not
adopted: they are reported by the finding (``not_adopted`` counter).

A restarted blender recomputes from the flow history and does not publish a tick again: the last
published tick is kept in the run's state directory.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from schemas import keys
from schemas.closeloop import ModelFinding
from schemas.line import LineSpec
from schemas.messages import Event, FeederFlow, PredictedConcentration, RtdEstimate
from services.common import LiveService
from twin_core.online import InletAligner, StreamingConvolver, TracerInjector
from twin_core.plant.effects import Effect, make_effect

log = logging.getLogger(__name__)


def rtd_kernel(model: str, params: dict[str, float], dt_s: float, length_s: float) -> np.ndarray:
    """E(t) of ``twin_core.rtd.models.<model>(t, **params)`` on t = k dt, 0 <= t < length_s."""
    from twin_core.rtd import models

    fn = getattr(models, model, None)
    if fn is None or not callable(fn):
        raise ValueError(
            f"blender.model must name a function of twin_core.rtd.models, got {model!r}"
        )
    t = np.arange(int(np.ceil(length_s / dt_s))) * dt_s
    return np.asarray(fn(t, **params), dtype=float)


def blender_kernel(spec: LineSpec) -> np.ndarray:
    """E(t) of the configured blender model on the line's tick grid (``spec.dt_s``)."""
    b = spec.blender
    if b.kind == "rtd":
        return rtd_kernel(b.model, dict(b.params), spec.dt_s, b.kernel_s)
    try:
        from schemas.blender_model import BlenderModel
    except ImportError as exc:  # pragma: no cover - depends on the compartment area
        raise ValueError(
            f"blender.kind 'compartment' needs schemas.blender_model, unavailable: {exc}"
        ) from exc
    model = BlenderModel.model_validate_json(Path(b.export_path).read_text())
    t = np.arange(int(np.ceil(b.kernel_s / spec.dt_s))) * spec.dt_s
    return np.asarray(model.impulse_response(t), dtype=float)


class _FlowMemory:
    """The last ``size`` (t, flow, refilling) samples of one feeder as contiguous arrays, oldest
    first (a doubled buffer: O(1) append amortised, no copy to read)."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.t = np.empty(2 * size)
        self.q = np.empty(2 * size)
        self.r = np.zeros(2 * size, dtype=bool)
        self.end = 0

    def append(self, t: float, q: float, refilling: bool) -> None:
        if self.end == 2 * self.size:  # keep the newest size - 1, then append
            keep = self.size - 1
            for a in (self.t, self.q, self.r):
                a[:keep] = a[self.end - keep : self.end]
            self.end = keep
        self.t[self.end], self.q[self.end], self.r[self.end] = t, q, refilling
        self.end += 1

    def window(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a = max(0, self.end - self.size)
        return self.t[a : self.end], self.q[a : self.end], self.r[a : self.end]


class BlenderPredictor:
    """The prediction core (no bus): feed ticks of feeder flows, get outlet concentrations."""

    def __init__(self, spec: LineSpec, e: np.ndarray | None = None) -> None:
        self.spec = spec
        self.components = spec.components
        self.comp_names = sorted(set(self.components.values()))
        self.e = blender_kernel(spec) if e is None else np.asarray(e, float)
        self.aligner = InletAligner(
            list(self.components), spec.dt_s, max_lag=max(1, int(spec.inlet_max_lag_s / spec.dt_s))
        )
        self.conv: dict[str, StreamingConvolver] | None = None
        self.tracer = TracerInjector(spec.dt_s)
        b = spec.blender
        #: the RTD model E(t) is built from (declared, or the latest estimate); None: compartment
        self.rtd_model: tuple[str, dict[str, float]] | None = (
            (b.model, dict(b.params)) if b.kind == "rtd" and e is None else None
        )
        #: adopted effects (rtd and feeder stage)
        self.effects: list[Effect] = []
        self._refill: dict[str, dict[int, bool]] = {f: {} for f in self.components}
        self._hist: dict[str, _FlowMemory] = {}

    def set_kernel(self, e: np.ndarray) -> None:
        """Replace E(t) (an adopted RTD estimate), keeping the flow history."""
        self.e = np.asarray(e, float)
        if self.conv is not None:
            for c in self.conv.values():
                c.set_kernel(self.e)

    def _kernel(self) -> np.ndarray:
        """E(t) of the RTD model with the adopted rtd-stage effects, on the tick grid."""
        from twin_core.plant.config import BlenderSpec
        from twin_core.plant.model import rtd_kernel as model_kernel

        assert self.rtd_model is not None
        model, params = self.rtd_model
        dt = self.spec.dt_s
        n = int(np.ceil(self.spec.blender.kernel_s / dt))
        # an adopted effect may lengthen the tail (a dead zone of tau_s up to 600 s): keep E(t)
        # until less than 1e-7 of its mass is left out (at most MAX_KERNEL_S)
        n_max = max(n, int(np.ceil(self.MAX_KERNEL_S / dt)))
        e = model_kernel(BlenderSpec(model, dict(params)), np.arange(n_max) * dt, self.effects)
        tail = dt * (e.sum() - np.cumsum(e))
        n_need = int(np.argmax(tail < 1e-7)) + 1 if np.any(tail < 1e-7) else n_max
        return e[: max(n, n_need)]

    def set_rtd_model(self, model: str, params: Mapping[str, float]) -> None:
        """A new base RTD (an adopted estimate); the adopted rtd effects stay on top of it."""
        self.rtd_model = (model, dict(params))
        self.set_kernel(self._kernel())

    def adoptable(self, effect: Effect) -> bool:
        """Can this effect change the prediction of the outlet (see the module docstring)?"""
        if not effect.time_invariant or effect.stage == "sensor":
            return False
        return effect.stage == "feeder" or self.rtd_model is not None

    def set_effects(self, effects: Sequence[Effect | Mapping]) -> list[Effect]:
        """Adopt a model's effects; returns the ones that could not be adopted."""
        effs = [make_effect(e) for e in effects]
        self.effects = [e for e in effs if self.adoptable(e)]
        if self.rtd_model is not None:
            self.set_kernel(self._kernel())
        return [e for e in effs if not self.adoptable(e)]

    #: longest E(t) an adopted effect may stretch the kernel to, s
    MAX_KERNEL_S = 7200.0

    #: reported flow kept per feeder for the feeder-stage effects (ticks; a refill surge decays
    #: within its tau <= 180 s, so 1800 ticks leave < exp(-10) of it out)
    FLOW_MEMORY = 1800

    def _delivered(self, feeder: str, t: float, q: float, refilling: bool) -> float:
        """The delivered flow under the adopted feeder-stage effects (causal: the effect's
        ``apply_flow`` on the feeder's recent reported flows, last value)."""
        effs = [e for e in self.effects if e.stage == "feeder" and e.target in (None, feeder)]
        h = self._hist.get(feeder)
        if h is None:
            h = self._hist[feeder] = _FlowMemory(self.FLOW_MEMORY)
        h.append(t, q, refilling)
        if not effs:
            return q
        tt, qq, rr = h.window()
        qq = qq.copy()  # an effect may work in place: the memory keeps the reported flows
        for e in sorted(effs, key=lambda e: e.order):
            qq = e.apply_flow(tt, qq, rr)
        return float(qq[-1])

    def add_pulse(self, component: str, t_s: float, mass_kg: float, duration_s: float) -> None:
        """A tracer pulse entering the inlet (``twin_core.online.TracerInjector``)."""
        if component not in self.comp_names:
            raise ValueError(f"component must be one of {self.comp_names}, got {component!r}")
        self.tracer.add_pulse(component, t_s, mass_kg, duration_s)

    def push(
        self, feeder: str, t: float, flow_kg_h: float, refilling: bool = False
    ) -> list[tuple[float, dict[str, float]]]:
        """One feeder sample -> the (t, {component: % w/w}) of every tick it completed."""
        out = []
        dt = self.spec.dt_s
        if refilling:
            self._refill[feeder][int(round(t / dt))] = True
        for tt, flows in self.aligner.push(feeder, t, flow_kg_h):
            mass = {c: 0.0 for c in self.comp_names}
            k = int(round(tt / dt))
            for f, q in flows.items():
                r = self._refill[f].pop(k, False)
                mass[self.components[f]] += self._delivered(f, tt, q, r)
            steady = dict(mass)
            self.tracer.apply(tt, mass)
            if self.conv is None:
                self.conv = {
                    c: StreamingConvolver(self.e, self.spec.dt_s, initial=steady[c])
                    for c in self.comp_names
                }
            y = {c: self.conv[c].push(mass[c]) for c in self.comp_names}
            total = sum(y.values())
            if total > 0:
                out.append((tt, {c: 100.0 * v / total for c, v in y.items()}))
        return out


class BlenderService(LiveService):
    """See the module docstring."""

    def __init__(self, spec: LineSpec, **kwargs: Any) -> None:
        super().__init__("blender", spec, **kwargs)
        self.core = BlenderPredictor(spec)
        self.model_name = spec.blender.model if spec.blender.kind == "rtd" else "compartment"
        self._mark = self.state_path / "blender.last_t"
        self.last_published_t = -1.0
        if self._mark.exists():
            try:
                self.last_published_t = float(self._mark.read_text() or -1.0)
            except ValueError:
                self.last_published_t = -1.0
        self._n = 0
        self._last_event_t = -1.0

    def setup(self) -> None:
        line = self.spec.name
        self.pub = self.history_publisher(
            keys.predicted_concentration(line, "outlet"), PredictedConcentration
        )
        self.history_subscribe(f"twin/{line}/feeder/*/flow", FeederFlow)
        self.history_subscribe(f"twin/{line}/*/*/event", Event)
        if self.spec.blender.adopt_rtd_estimates:
            self.history_subscribe(keys.rtd_estimate(line), RtdEstimate)
        if self.spec.blender.adopt_findings:
            self.history_subscribe(keys.model_finding(line), ModelFinding)

    def handle(self, key: str, msg: Any) -> None:
        if isinstance(msg, Event):
            if msg.kind == "tracer_pulse" and msg.mass_kg and msg.t > self._last_event_t:
                self._last_event_t = msg.t
                comp = msg.component or msg.source
                if comp in self.core.comp_names:
                    self.core.add_pulse(comp, msg.t, msg.mass_kg, msg.duration_s or 1.0)
                    self.counters.inc("tracer_pulses")
            return
        if isinstance(msg, RtdEstimate):
            if self.core.rtd_model is not None:
                self.core.set_rtd_model(msg.model, msg.params)
            else:
                e = rtd_kernel(
                    msg.model, dict(msg.params), self.spec.dt_s, self.spec.blender.kernel_s
                )
                self.core.set_kernel(e)
            self.model_name = msg.model
            self.counters.inc("rtd_adopted")
            return
        if isinstance(msg, ModelFinding):
            new = [e.model_dump() for e in msg.model_effects]
            if new != [e.to_dict() for e in self.core.effects]:
                left = self.core.set_effects(new)
                self.counters.inc("findings_adopted")
                if left:
                    self.counters.inc("not_adopted", len(left))
                    log.info(
                        "blender: finding %s: not adopted: %s",
                        msg.finding_id,
                        ", ".join(e.label() for e in left),
                    )
            return
        feeder = keys.parse_key(key).id
        if feeder not in self.core.components:
            self.counters.inc("rejected_unknown")
            return
        for t, conc in self.core.push(feeder, msg.t, msg.mass_flow_kg_h, msg.refilling):
            if t <= self.last_published_t:
                continue  # already published before a restart
            for i, c in enumerate(self.core.comp_names):
                self.pub.publish(
                    PredictedConcentration(
                        t=t,
                        seq=int(round(t / self.spec.dt_s)) * len(self.core.comp_names) + i,
                        model=self.model_name,
                        component=c,
                        concentration_pct_w_w=conc[c],
                    )
                )
            self.last_published_t = t
            self._n += 1
            if self._n % 200 == 0:
                self._save_mark()

    def _save_mark(self) -> None:
        self._mark.parent.mkdir(parents=True, exist_ok=True)
        self._mark.write_text(repr(self.last_published_t))

    def idle(self) -> None:
        if self._n:
            self._save_mark()

    def finish(self) -> None:
        if self._n:
            self._save_mark()
