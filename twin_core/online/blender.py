"""Live prediction of the blender outlet from the feeder flows (the blender service's core).

The mass-flow-weighted RTD model of the declared line (``twin_core.plant.model``):

    c_i(t) = 100 (E * m_i)(t) / (E * sum_j m_j)(t)   [% w/w]

one streaming convolution (:class:`~twin_core.online.convolution.StreamingConvolver`) per
component mass flow m_i (reported feeder flows plus announced tracer pulses), the stream starting
at steady state (the first flows). :class:`BlenderKernel` is the blender's E(t) on the tick grid
as the twin adopts it: the declared model (``twin_core.rtd.models.model_e``, or a compartment
export's impulse response), replaced by an adopted RTD estimate, transformed by adopted rtd-stage
effects (dead zone, bypass, extra delay, back-mixing: ``twin_core.plant.model.rtd_kernel``). The
diverter uses the same object, so it follows the model the blender adopted.

:class:`BlenderPredictor` adds the adopted feeder-stage effects (e.g. a refill surge turns each
feeder's reported flow into the delivered one, causally, from the feeder's recent flows) and the
unit-stage ones (a component's mass partly lost in the blender).
Effects that grow with time from the start of their window (drifts) and sensor effects (the
probe, not the outlet) are not adopted.

Adoption is keyed to plant time: an RTD estimate or a model's effects are scheduled from the
plant time they apply from (:meth:`BlenderKernel.schedule`, the message's ``applies_from_s``) and
applied before the first tick at or after it (:meth:`BlenderKernel.apply_due`), whenever they
arrived; one that arrives after that tick was predicted is applied from the next tick, and the
caller is told by how much it was late.

A tracer event may arrive after the flows of its tick (another route, another publisher): the
tick's convolution input is then corrected in place. E(t) of a blender with a plug-flow delay is
exactly zero for its first samples, so the outlet values already given did not depend on that
input: the predictions equal those of an in-order arrival whenever the event is less than the
delay late.
"""

from __future__ import annotations

import hashlib
import heapq
import json
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from schemas.line import LineSpec, TracerPulse
from twin_core.online.convolution import StreamingConvolver
from twin_core.online.inlet import FeederSample, InletStream, InletTick, tracer_pulse
from twin_core.plant.effects import Effect, make_effect
from twin_core.rtd.models import model_e

__all__ = [
    "BlenderKernel",
    "BlenderPredictor",
    "FlowMemory",
    "declared_kernel",
    "model_version",
    "tick_grid",
]


def tick_grid(dt_s: float, length_s: float) -> np.ndarray:
    """Times k dt, 0 <= t < length_s, of an E(t) on the line's tick grid."""
    return np.arange(int(np.ceil(length_s / dt_s))) * dt_s


def model_version(e: np.ndarray, dt_s: float, effects: Sequence[Mapping[str, Any]] = ()) -> str:
    """The version of a blender model: the first 16 hex digits of the SHA-256 of what its
    predictions are computed from, the E(t) on the tick grid (float64, little-endian, with
    the tick) and the adopted effects (their dict form as sorted JSON). Equal models give equal
    versions in every process (the blender and the diverter compute it from the same kernel);
    any change of E(t) or of an effect gives another."""
    h = hashlib.sha256()
    h.update(np.float64(dt_s).tobytes())
    h.update(np.ascontiguousarray(np.asarray(e, dtype="<f8")).tobytes())
    h.update(json.dumps(list(effects), sort_keys=True, separators=(",", ":")).encode())
    return h.hexdigest()[:16]


def declared_kernel(spec: LineSpec) -> np.ndarray:
    """E(t) of the configured blender model on the line's tick grid (``spec.dt_s``, over
    ``blender.kernel_s``): a ``twin_core.rtd.models`` model, or a compartment export's impulse
    response."""
    b = spec.blender
    t = tick_grid(spec.dt_s, b.kernel_s)
    if b.kind == "rtd":
        return model_e(b.model, dict(b.params), t)
    from twin_core.compartment.operating_point import configured_point, table_from_config

    return table_from_config(b).rtd(configured_point(spec), t)


class BlenderKernel:
    """The blender's E(t) on the tick grid as the twin adopts it (see the module docstring).

    Args:
        spec: the line (declared blender model, tick, kernel length).
        e: an E(t) to start from instead of the declared one (no named RTD model then: rtd-stage
            effects cannot be adopted).
    """

    #: longest E(t) an adopted effect may stretch the kernel to, s
    MAX_KERNEL_S = 7200.0
    #: the kinds of update :meth:`schedule` takes
    UPDATE_KINDS = ("estimate", "effects", "operating_point", "model")

    def __init__(self, spec: LineSpec, e: np.ndarray | None = None) -> None:
        b = spec.blender
        self.dt = spec.dt_s
        self.length_s = b.kernel_s
        #: the RTD model E(t) is built from (declared, or the latest estimate); None: compartment
        self.rtd_model: tuple[str, dict[str, float]] | None = (
            (b.model, dict(b.params)) if b.kind == "rtd" and e is None else None
        )
        #: name of the model in use (``PredictedConcentration.model``)
        self.model_name = b.model if b.kind == "rtd" else "compartment"
        #: adopted effects (rtd and feeder stage)
        self.effects: list[Effect] = []
        #: compartment models by blade speed and the operating point in use (compartment only)
        self.table: Any = None
        self.point: Any = None
        #: E(t) comes from the table (not from an adopted RTD estimate)
        self._table_based = False
        if b.kind == "compartment" and e is None:
            from twin_core.compartment.operating_point import (
                configured_point,
                table_from_config,
            )

            self.table, self.point = table_from_config(b), configured_point(spec)
            self._from_table()
        else:
            self.e = declared_kernel(spec) if e is None else np.asarray(e, float)
        #: model switches applied and not yet taken by :meth:`take_switches`: (plant time, reason)
        self._switches: list[tuple[float, str]] = [(0.0, "start")]
        #: scheduled updates not yet applied: (applies from, order, kind, payload)
        self._pending: list[tuple[float, int, str, Any]] = []
        self._n_scheduled = 0
        #: the effects (dict form) of the latest update scheduled
        self.latest_effects: list[dict] = []

    def schedule(self, t_from: float, kind: str, payload: Any) -> None:
        """An update to apply from plant time ``t_from`` on: ``kind`` ``estimate`` (payload
        ``(model, params)``, :meth:`adopt_estimate`), ``effects`` (a list of effects,
        :meth:`adopt_effects`), ``operating_point`` (an ``OperatingPoint`` and the reason,
        :meth:`adopt_operating_point`) or ``model`` (a ``BlenderModel``, :meth:`adopt_model`);
        equal times apply in scheduling order."""
        if kind not in self.UPDATE_KINDS:
            raise ValueError(f"kind must be one of {list(self.UPDATE_KINDS)}, got {kind!r}")
        if kind == "effects":
            self.latest_effects = [dict(e) for e in payload]
        heapq.heappush(self._pending, (float(t_from), self._n_scheduled, kind, payload))
        self._n_scheduled += 1

    def apply_due(self, t: float) -> bool:
        """Apply the scheduled updates due at plant time ``t`` (``t_from <= t``), in order;
        returns whether E(t) or the effects changed."""
        changed = False
        while self._pending and self._pending[0][0] <= t:
            _, _, kind, payload = heapq.heappop(self._pending)
            if kind == "estimate":
                self.adopt_estimate(*payload)
                self._note_switch(t, "rtd_estimate")
            elif kind == "effects":
                self.adopt_effects(payload)
            elif kind == "operating_point":
                if not self.adopt_operating_point(payload[0]):
                    continue
                self._note_switch(t, payload[1])
            else:
                self.adopt_model(payload)
                self._note_switch(t, "new_model")
            changed = True
        return changed

    def _note_switch(self, t: float, reason: str) -> None:
        """Keep a switch for :meth:`take_switches`; several at one tick are one (the last)."""
        if self._switches and self._switches[-1][0] == t and self._switches[-1][1] != "start":
            self._switches[-1] = (t, reason)
        else:
            self._switches.append((t, reason))

    def adopt_operating_point(self, point: Any) -> bool:
        """The blender's E(t) at a new operating point (blade speed, throughput) from the
        table of compartment models (``twin_core.compartment.operating_point``); returns False
        (nothing changes) for an RTD-model blender, which has no law for it."""
        if self.table is None:
            return False
        self.point = point
        self.model_name = "compartment"
        self._from_table()
        return True

    def _from_table(self) -> None:
        """E(t) from the table at the operating point; with adopted rtd-stage effects, on its
        axial-dispersion equivalent (the model the close-loop found them against: the declared
        line model of a compartment blender, ``twin_core.plant.model.rtd_blender_config``)."""
        self._table_based = True
        if any(e.stage == "rtd" for e in self.effects):
            self.rtd_model = self.table.rtd_equivalent(self.point)
            self.e = self._with_effects()
        else:
            self.rtd_model = None
            self.e = self.table.rtd(self.point, tick_grid(self.dt, self.length_s))

    def adopt_model(self, model: Any) -> bool:
        """A new section model (``BlenderModel`` at its blade speed) joins the table; E(t) is
        rebuilt at the operating point in use. False (ignored) for an RTD-model blender."""
        if self.table is None:
            return False
        self.table.add(model)
        return self.adopt_operating_point(self.point)

    def take_switches(self) -> list[tuple[float, str]]:
        """The model switches applied since the last call: (plant time, reason), reason one of
        ``start``, ``blade_speed``, ``throughput``, ``new_model``, ``rtd_estimate``."""
        out, self._switches = self._switches, []
        return out

    def describe(self) -> str:
        """The model in use in words: the compartment models mixed at the operating point, or
        the RTD model's name."""
        if self.table is not None and self.model_name == "compartment":
            return f"compartment: {self.table.describe(self.point)}"
        return self.model_name

    def rule_text(self) -> str:
        """How the model was obtained for the operating point (``BlenderModelInUse.rule``)."""
        if self.table is None or self.model_name != "compartment":
            return ""
        rule = self.table.rule
        if rule.holdup_kg is None:
            return "DEM time scale; shapes mixed linearly in rpm"
        b = rule.basis
        return (
            f"holdup {rule.holdup_kg:g} kg at {b.rpm:g} rpm, {b.throughput_kg_h:g} kg/h; "
            f"x kappa ratio x (Q/Q_b)^{rule.beta:g}; shapes mixed linearly in rpm"
        )

    def __setattr__(self, name: str, value: Any) -> None:
        # E(t) or the adopted effects replaced: the version is computed again when asked
        if name in ("e", "effects"):
            object.__setattr__(self, "_version", None)
        object.__setattr__(self, name, value)

    @property
    def version(self) -> str:
        """The version of the model in use (:func:`model_version` of E(t) and the adopted
        effects), computed once per E(t) and effects assigned."""
        if self._version is None:
            self._version = model_version(self.e, self.dt, [x.to_dict() for x in self.effects])
        return self._version

    def mean_residence_time_s(self) -> float:
        """Mean of the E(t) in use (its tick grid)."""
        t = tick_grid(self.dt, self.e.size * self.dt)[: self.e.size]
        mass = float(np.sum(self.e))
        return float(np.sum(t * self.e) / mass) if mass > 0 else 0.0

    def adoptable(self, effect: Effect) -> bool:
        """Can this effect change the prediction of the outlet (see the module docstring)?"""
        if not effect.time_invariant or effect.stage == "sensor":
            return False
        rtd_based = self.rtd_model is not None or self.table is not None
        return effect.stage in ("feeder", "unit") or rtd_based

    def adopt_estimate(self, model: str, params: Mapping[str, float]) -> np.ndarray:
        """An adopted RTD estimate: the new base E(t) (the adopted rtd effects stay on top of it
        when the blender is an RTD model); returns the new E(t)."""
        if self.rtd_model is not None or self.table is not None:
            self.rtd_model = (model, dict(params))
            self._table_based = False
            self.e = self._with_effects()
        else:
            self.e = model_e(model, dict(params), tick_grid(self.dt, self.length_s))
        self.model_name = model
        return self.e

    def adopt_effects(self, effects: Sequence[Effect | Mapping]) -> list[Effect]:
        """Adopt a model's effects; returns the ones that could not be adopted."""
        effs = [make_effect(e) for e in effects]
        self.effects = [e for e in effs if self.adoptable(e)]
        if self.table is not None and self._table_based:
            self._from_table()
        elif self.rtd_model is not None:
            self.e = self._with_effects()
        return [e for e in effs if not self.adoptable(e)]

    def same_effects(self, effects: Sequence[Mapping]) -> bool:
        """Whether ``effects`` (dict form) are the adopted ones."""
        return list(effects) == [e.to_dict() for e in self.effects]

    def _with_effects(self) -> np.ndarray:
        """E(t) of the RTD model with the adopted rtd-stage effects, on the tick grid. An
        adopted effect may lengthen the tail (a dead zone of tau_s up to 600 s): E(t) is kept
        until less than 1e-7 of its mass is left out (at most ``MAX_KERNEL_S``)."""
        from schemas.line import BlenderModelConfig
        from twin_core.plant.model import rtd_kernel

        assert self.rtd_model is not None
        model, params = self.rtd_model
        n = int(np.ceil(self.length_s / self.dt))
        n_max = max(n, int(np.ceil(self.MAX_KERNEL_S / self.dt)))
        blender = BlenderModelConfig(model=model, params=dict(params))
        e = rtd_kernel(blender, np.arange(n_max) * self.dt, self.effects)
        tail = self.dt * (e.sum() - np.cumsum(e))
        n_need = int(np.argmax(tail < 1e-7)) + 1 if np.any(tail < 1e-7) else n_max
        return e[: max(n, n_need)]


class FlowMemory:
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
    """The prediction core (no bus): feed feeder samples, get outlet concentrations per tick.

    Args:
        spec: the line.
        e: an E(t) on the tick grid to use instead of the declared blender model.
    """

    #: reported flow kept per feeder for the feeder-stage effects (ticks; a refill surge decays
    #: within its tau <= 180 s, so 1800 ticks leave < exp(-10) of it out)
    FLOW_MEMORY = 1800

    def __init__(self, spec: LineSpec, e: np.ndarray | None = None) -> None:
        self.spec = spec
        self.components = spec.components
        self.comp_names = sorted(set(self.components.values()))
        self.kernel = BlenderKernel(spec, e)
        self.inlet = InletStream(
            self.components, spec.dt_s, max_lag=max(1, int(spec.inlet_max_lag_s / spec.dt_s))
        )
        self.conv: dict[str, StreamingConvolver] | None = None
        self._last_tick: float | None = None
        self._hist: dict[str, FlowMemory] = {}

    @property
    def e(self) -> np.ndarray:
        """E(t) in use, on the tick grid."""
        return self.kernel.e

    @property
    def effects(self) -> list[Effect]:
        """The adopted effects."""
        return self.kernel.effects

    def set_kernel(self, e: np.ndarray) -> None:
        """Replace E(t) (e.g. an adopted RTD estimate), keeping the flow history."""
        self.kernel.e = np.asarray(e, float)
        self._update_convolvers()

    def _update_convolvers(self) -> None:
        if self.conv is not None:
            for c in self.conv.values():
                c.set_kernel(self.kernel.e)

    def adopt_estimate(self, model: str, params: Mapping[str, float]) -> None:
        """An RTD estimate (``twin/<line>/rtd/estimate``) becomes the blender's RTD."""
        self.kernel.adopt_estimate(model, params)
        self._update_convolvers()

    def set_effects(self, effects: Sequence[Effect | Mapping]) -> list[Effect]:
        """Adopt a model's effects; returns the ones that could not be adopted."""
        left = self.kernel.adopt_effects(effects)
        self._update_convolvers()
        return left

    def schedule(self, t_from: float, kind: str, payload: Any) -> float:
        """An update (:meth:`BlenderKernel.schedule`) applied from the first tick at or after
        plant time ``t_from``; returns how late it came, s of plant time (0: in time; else the
        tick it is applied from minus ``t_from``: that tick is the one after the last
        predicted)."""
        self.kernel.schedule(t_from, kind, payload)
        if self._last_tick is None or t_from > self._last_tick:
            return 0.0
        return self._last_tick + self.spec.dt_s - t_from

    def _delivered(self, feeder: str, t: float, s: FeederSample) -> float:
        """The delivered flow under the adopted feeder-stage effects (causal: the effect's
        ``apply_flow`` on the feeder's recent reported flows, last value)."""
        effs = [e for e in self.effects if e.stage == "feeder" and e.target in (None, feeder)]
        h = self._hist.get(feeder)
        if h is None:
            h = self._hist[feeder] = FlowMemory(self.FLOW_MEMORY)
        h.append(t, s.flow_kg_h, s.refilling)
        if not effs:
            return s.flow_kg_h
        tt, qq, rr = h.window()
        qq = qq.copy()  # an effect may work in place: the memory keeps the reported flows
        for e in sorted(effs, key=lambda e: e.order):
            qq = e.apply_flow(tt, qq, rr)
        return float(qq[-1])

    def _through_unit(
        self, component: str, t: float, mass: float, steady: float
    ) -> tuple[float, float]:
        """A component's inflow (and its steady value) through the adopted unit-stage effects
        (e.g. a fraction lost in the blender); time-invariant ones only are adopted."""
        for e in sorted(self.effects, key=lambda e: e.order):
            if e.stage == "unit" and e.target in (None, component):
                tt = np.array([t])
                mass = float(e.apply_component(tt, np.array([mass]))[0])
                steady = float(e.apply_component(tt, np.array([steady]))[0])
        return mass, steady

    def add_pulse(self, component: str, t_s: float, mass_kg: float, duration_s: float) -> bool:
        """A tracer pulse entering the inlet; its flow in ticks already predicted corrects
        their convolution input (see the module docstring). Returns False for a pulse already
        announced (history after a restart)."""
        if component not in self.comp_names:
            raise ValueError(f"component must be one of {self.comp_names}, got {component!r}")
        pulse = TracerPulse(t_s=t_s, mass_kg=mass_kg, component=component, duration_s=duration_s)
        late = self.inlet.add_pulse(pulse, carry=False)
        if late is None:
            return False
        if late and self.conv is not None and self._last_tick is not None:
            conv = self.conv[component]
            for t, q in late.items():
                lag = int(round((self._last_tick - t) / self.spec.dt_s))
                if lag < conv.size:  # older inputs no longer reach any future outlet value
                    conv.amend(lag, q)
        return True

    def add_event(self, event: Mapping) -> bool:
        """A plant event (dict form, ``twin_core.online.inlet.event_record``); returns whether
        it announced a new tracer pulse of a known component (then added to the inlet)."""
        p = tracer_pulse(event)
        if p is None or p.component not in self.comp_names:
            return False
        return self.add_pulse(p.component, p.t_s, p.mass_kg, p.duration_s)

    def push(
        self, feeder: str, t: float, flow_kg_h: float, refilling: bool = False
    ) -> list[tuple[float, dict[str, float]]]:
        """One feeder sample -> the (t, {component: % w/w}) of every tick it completed."""
        out = []
        for tick in self.inlet.push(feeder, t, FeederSample(float(flow_kg_h), bool(refilling))):
            conc = self._predict(tick)
            if conc is not None:
                out.append((tick.t, conc))
        return out

    def _predict(self, tick: InletTick) -> dict[str, float] | None:
        if self.kernel.apply_due(tick.t):
            self._update_convolvers()
        mass = {c: 0.0 for c in self.comp_names}
        for f, s in tick.feeders.items():
            mass[self.components[f]] += self._delivered(f, tick.t, s)
        steady = dict(mass)
        for c, q in tick.tracer_kg_h.items():
            mass[c] += q
        for c in self.comp_names:
            mass[c], steady[c] = self._through_unit(c, tick.t, mass[c], steady[c])
        if self.conv is None:
            self.conv = {
                c: StreamingConvolver(self.kernel.e, self.spec.dt_s, initial=steady[c])
                for c in self.comp_names
            }
        self._last_tick = tick.t
        y = {c: self.conv[c].push(mass[c]) for c in self.comp_names}
        total = sum(y.values())
        if total > 0:
            return {c: 100.0 * v / total for c, v in y.items()}
        return None
