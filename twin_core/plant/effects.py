"""Candidate effects: structural additions to the declared line model, each with parameters.

An effect acts at one stage of the line model (see ``twin_core.plant.model``):

- ``"feeder"``: delivered flow differs from the flow the feeder reports (the twin's input);
- ``"rtd"``: the blender impulse response E(t) differs from the declared one;
- ``"unit"``: the unit does not pass on all of a component's mass (lost, held up);
- ``"sensor"``: the NIR reading differs from the outlet concentration.

Feeder, rtd and unit effects change the product (the real outlet composition: ``side`` is
``"product"``); sensor effects change only the probe's reading of it (``side`` ``"probe"``). A
product-side and a probe-side explanation of the same residual are not equivalent for the
product: the close-loop reports both and acts on the product-side one.

Each effect is one small class registered in :data:`EFFECTS` under its ``name``, with its
parameters declared as :class:`ParamSpec` (default, bounds, unit, meaning). The default of
every parameter is its "null" value at which the effect does nothing, except time constants,
which have a typical value. To add an effect: subclass :class:`Effect`, set ``name``, ``stage``,
``params``, ``doc`` and implement the stage method; decorate with :func:`register`.

The plant simulator injects effects as ground truth; the close-loop identification fits them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from scipy.signal import lfilter

from schemas.line import BlenderModelConfig


@dataclass(frozen=True)
class ParamSpec:
    """A parameter of an effect: name, default, bounds [lower, upper], unit, meaning, and the
    starting values the identification tries (``starts``)."""

    name: str
    default: float
    lower: float
    upper: float
    unit: str
    doc: str
    starts: tuple[float, ...] = ()


EFFECTS: dict[str, type[Effect]] = {}

#: the stages of the line model an effect can act at (see the module docstring)
STAGES = ("feeder", "rtd", "unit", "sensor")


def register(cls: type[Effect]) -> type[Effect]:
    """Class decorator: add an effect class to :data:`EFFECTS` under ``cls.name``."""
    if cls.name in EFFECTS:
        raise ValueError(f"effect name must be unique, got duplicate {cls.name!r}")
    if cls.stage not in STAGES:
        raise ValueError(f"effect stage must be one of {STAGES}, got {cls.stage!r}")
    EFFECTS[cls.name] = cls
    return cls


class Effect:
    """Base class. Parameters are given as keyword arguments and checked against bounds.

    Feeder-stage effects also take ``target``: the feeder they act on (None: every feeder);
    unit-stage effects the component they act on (None: every component).
    """

    name: ClassVar[str] = ""
    stage: ClassVar[str] = ""
    params: ClassVar[tuple[ParamSpec, ...]] = ()
    doc: ClassVar[str] = ""
    #: order of application inside a stage (lower first)
    order: ClassVar[int] = 0
    #: False for effects that change with time from the start of their record (drifts): a
    #: streaming model cannot adopt them as a fixed structural change
    time_invariant: ClassVar[bool] = True

    def __init__(self, target: str | None = None, **values: float) -> None:
        names = [p.name for p in self.params]
        unknown = sorted(set(values) - set(names))
        if unknown:
            raise ValueError(f"effect {self.name!r}: unknown parameters {unknown}; has {names}")
        self.target = target
        self.values: dict[str, float] = {}
        for p in self.params:
            v = float(values.get(p.name, p.default))
            if not math.isfinite(v) or v < p.lower or v > p.upper:
                raise ValueError(
                    f"{self.name}.{p.name} must be in [{p.lower}, {p.upper}], got {v!r}"
                )
            self.values[p.name] = v

    # -- helpers -------------------------------------------------------------------------
    @property
    def side(self) -> str:
        """``"probe"`` for sensor-stage effects, ``"product"`` for the others (module docstring)."""
        return "probe" if self.stage == "sensor" else "product"

    @classmethod
    def bounds(cls) -> tuple[np.ndarray, np.ndarray]:
        return (
            np.array([p.lower for p in cls.params], dtype=float),
            np.array([p.upper for p in cls.params], dtype=float),
        )

    @classmethod
    def defaults(cls) -> np.ndarray:
        return np.array([p.default for p in cls.params], dtype=float)

    def vector(self) -> np.ndarray:
        return np.array([self.values[p.name] for p in self.params], dtype=float)

    def with_vector(self, x: np.ndarray) -> Effect:
        lo, hi = self.bounds()
        x = np.clip(np.asarray(x, dtype=float), lo, hi)
        return type(self)(target=self.target, **{p.name: float(v) for p, v in zip(self.params, x)})

    def label(self) -> str:
        return f"{self.name}[{self.target}]" if self.target else self.name

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "target": self.target, "params": dict(self.values)}

    def __repr__(self) -> str:
        vals = ", ".join(f"{k}={v:.4g}" for k, v in self.values.items())
        tgt = f"target={self.target!r}, " if self.target else ""
        return f"{type(self).__name__}({tgt}{vals})"

    # -- stage hooks (defaults: identity) -------------------------------------------------
    def blender_params(self, model: str, params: dict[str, float]) -> dict[str, float]:
        """rtd stage: change the blender model parameters before E(t) is evaluated."""
        return params

    def apply_rtd(self, tk: np.ndarray, e: np.ndarray, blender: BlenderModelConfig) -> np.ndarray:
        """rtd stage: transform E(t) sampled on ``tk`` (uniform, from 0)."""
        return e

    def apply_flow(
        self, t: np.ndarray, flow: np.ndarray, refilling: np.ndarray | None
    ) -> np.ndarray:
        """feeder stage: delivered flow from the reported flow of the target feeder."""
        return flow

    def apply_component(self, t: np.ndarray, q: np.ndarray) -> np.ndarray:
        """unit stage: the mass flow (kg/s) of the target component the unit passes on, from
        the one that enters it (feeders and tracer pulses)."""
        return q

    def apply_sensor(self, t: np.ndarray, c: np.ndarray) -> np.ndarray:
        """sensor stage: sensor signal (before noise) from the outlet concentration."""
        return c


def make_effect(spec: Effect | Mapping[str, Any]) -> Effect:
    """An effect from an instance or a dict ``{"name", "params": {...}, "target": ...}``."""
    if isinstance(spec, Effect):
        return spec
    if not isinstance(spec, Mapping) or "name" not in spec:
        raise ValueError(f"effect must be an Effect or a mapping with 'name', got {spec!r}")
    name = spec["name"]
    if name not in EFFECTS:
        raise ValueError(f"effect name must be one of {sorted(EFFECTS)}, got {name!r}")
    return EFFECTS[name](target=spec.get("target"), **dict(spec.get("params", {})))


def _exp_kernel_conv(tk: np.ndarray, e: np.ndarray, tau: float) -> np.ndarray:
    """(e * k)(t) with k(t) = exp(-t/tau)/tau, exact for piecewise-linear-in-bin e (ZOH form)."""
    dt = float(tk[1] - tk[0]) if tk.size > 1 else 1.0
    a = math.exp(-dt / tau)
    return lfilter([1.0 - a], [1.0, -a], e)


def _shift(tk: np.ndarray, e: np.ndarray, delay: float) -> np.ndarray:
    """e(t - delay) on the grid tk (linear interpolation, zero outside)."""
    return np.interp(tk - delay, tk, e, left=0.0, right=0.0)


# ---------------------------------------------------------------------------------------
# blender (RTD) effects
# ---------------------------------------------------------------------------------------
@register
class DeadZone(Effect):
    """Stagnant volume exchanging with the active one.

    E'(t) = (1 - f) E(t) + f (E * k)(t),  k(t) = exp(-t / tau_s) / tau_s

    a fraction f of the material is caught once in a well-mixed stagnant zone of mean
    residence time tau_s (the Cholette-Cloutier dead-zone picture, Levenspiel, Chemical
    Reaction Engineering, 3rd ed., ch. 12: active plug/dispersion region in series-parallel
    with a slowly exchanging CSTR). Shows as a long exponential tail after tracer pulses.
    """

    name = "dead_zone"
    stage = "rtd"
    order = 2
    doc = "fraction f of the flow detours through a stagnant CSTR of mean time tau_s"
    params = (
        ParamSpec(
            "fraction", 0.0, 0.0, 0.8, "1", "fraction of material through the zone", (0.1, 0.3)
        ),
        ParamSpec(
            "tau_s", 60.0, 2.0, 600.0, "s", "mean residence time in the zone", (20.0, 80.0, 200.0)
        ),
    )

    def apply_rtd(self, tk: np.ndarray, e: np.ndarray, blender: BlenderModelConfig) -> np.ndarray:
        f = self.values["fraction"]
        if f == 0.0:
            return e
        return (1.0 - f) * e + f * _exp_kernel_conv(tk, e, self.values["tau_s"])


@register
class Bypass(Effect):
    """A fraction of the flow short-circuits the blender: transport delay and a small mixed
    volume only.

    E'(t) = (1 - b) E(t) + b k_b(t - tau_d),  k_b(t) = exp(-t / tau_b) / tau_b, t > 0

    (Levenspiel ch. 12, "bypass" in parallel with the active volume; the bypass stream keeps
    the plug-flow delay tau_d of the declared model and the short mixing time
    ``BYPASS_TAU_S`` = 3 s of the outlet chute). Shows as an early peak in tracer responses.
    """

    name = "bypass"
    stage = "rtd"
    order = 3
    doc = "fraction b of the flow passes the blender after only the plug-flow delay (+3 s mixing)"
    params = (
        ParamSpec("fraction", 0.0, 0.0, 0.8, "1", "bypassing fraction of the flow", (0.05, 0.2)),
    )
    BYPASS_TAU_S: ClassVar[float] = 3.0

    def apply_rtd(self, tk: np.ndarray, e: np.ndarray, blender: BlenderModelConfig) -> np.ndarray:
        b = self.values["fraction"]
        if b == 0.0:
            return e
        dt = float(tk[1] - tk[0])
        spike = np.zeros_like(e)
        pos = blender.delay_s / dt
        i = int(math.floor(pos))
        w = pos - i
        if i < spike.size:
            spike[i] += (1.0 - w) / dt
        if i + 1 < spike.size:
            spike[i + 1] += w / dt
        return (1.0 - b) * e + b * _exp_kernel_conv(tk, spike, self.BYPASS_TAU_S)


@register
class ExtraDelay(Effect):
    """Extra transport delay (e.g. a longer chute/conveyor to the probe): E'(t) = E(t - d)."""

    name = "extra_delay"
    stage = "rtd"
    order = 9
    doc = "additional plug-flow delay d between inlet and probe"
    params = (
        ParamSpec(
            "delay_s", 0.0, -10.0, 60.0, "s", "extra delay (negative: shorter)", (-3.0, 3.0, 10.0)
        ),
    )

    def apply_rtd(self, tk: np.ndarray, e: np.ndarray, blender: BlenderModelConfig) -> np.ndarray:
        d = self.values["delay_s"]
        return e if d == 0.0 else _shift(tk, e, d)


@register
class BackMixing(Effect):
    """Changed axial back-mixing: the model's Peclet number (or tank number) times a factor.

    Pe' = pe_factor * Pe for the axial dispersion models, n' = pe_factor * n for tanks in
    series (Pe ~ 2 (n - 1) for large Pe, Levenspiel ch. 13-14), E' recomputed.
    """

    name = "back_mixing"
    stage = "rtd"
    order = 0
    doc = "axial dispersion changed: Pe (or n) multiplied by pe_factor"
    params = (ParamSpec("pe_factor", 1.0, 0.1, 10.0, "1", "multiplier of Pe (or n)", (0.6, 1.6)),)

    def blender_params(self, model: str, params: dict[str, float]) -> dict[str, float]:
        p = dict(params)
        key = "pe" if "pe" in p else "n" if "n" in p else None
        if key is None:
            raise ValueError(f"back_mixing needs a model with pe or n, got {model!r}")
        p[key] = p[key] * self.values["pe_factor"]
        return p


# ---------------------------------------------------------------------------------------
# feeder effects
# ---------------------------------------------------------------------------------------
@register
class RefillSurge(Effect):
    """Refill surge: the delivered flow overshoots while a hopper is refilled and after.

    delivered = reported * (1 + a * s(t)),  s = 1 while refilling,
    s = exp(-(t - t_end) / tau) after the refill ends (densified powder in the screw; the
    controller in volumetric mode does not see it: Engisch & Muzzio, J. Pharm. Innov. 2014).
    tau is bounded to 180 s: a refill disturbance fades within minutes; a slower one would
    be a drift, not a surge (and would mimic the drift effects).
    """

    name = "refill_surge"
    stage = "feeder"
    doc = "relative overfeed a during a refill, decaying with tau after it"
    params = (
        ParamSpec(
            "amplitude", 0.0, -0.5, 1.5, "1", "relative flow excess while refilling", (0.1, 0.3)
        ),
        ParamSpec("tau_s", 30.0, 1.0, 180.0, "s", "decay time after the refill", (10.0, 60.0)),
    )

    def apply_flow(
        self, t: np.ndarray, flow: np.ndarray, refilling: np.ndarray | None
    ) -> np.ndarray:
        a = self.values["amplitude"]
        if a == 0.0 or refilling is None or not np.any(refilling):
            return flow
        dt = float(t[1] - t[0]) if t.size > 1 else 1.0
        # s[n] = 1 while refilling, else s[n-1] * exp(-dt/tau)
        decay = math.exp(-dt / self.values["tau_s"])
        s = _refill_shape(refilling.astype(bool), decay)
        return flow * (1.0 + a * s)


def _refill_shape(refilling: np.ndarray, decay: float) -> np.ndarray:
    """s[n] = 1 while refilling, decay^(n - last refill sample) after, 0 before any refill."""
    idx = np.arange(refilling.size)
    last = np.maximum.accumulate(np.where(refilling, idx, -1))
    with np.errstate(over="ignore", under="ignore"):
        return np.where(last >= 0, decay ** (idx - np.maximum(last, 0)), 0.0)


@register
class FeedFactorDrift(Effect):
    """Feed-factor drift: delivered flow drifts away from the reported one linearly in time.

    delivered = reported * (1 + r (t - t0) / 3600), t0 = start of the record (a slowly
    changing bulk density in the screw; the feed factor of seed Eq. 2 drifting).
    """

    name = "feed_factor_drift"
    stage = "feeder"
    time_invariant = False
    doc = "relative drift rate r of delivered vs reported flow, per hour"
    params = (
        ParamSpec("rate_per_h", 0.0, -2.0, 2.0, "1/h", "relative flow drift per hour", (0.1, -0.1)),
    )

    def apply_flow(
        self, t: np.ndarray, flow: np.ndarray, refilling: np.ndarray | None
    ) -> np.ndarray:
        r = self.values["rate_per_h"]
        if r == 0.0:
            return flow
        return flow * np.maximum(1.0 + r * (t - t[0]) / 3600.0, 0.0)


@register
class FeedBias(Effect):
    """Delivered-vs-reported feed bias: delivered = reported (1 + b), constant.

    The feeder reports its gravimetric flow estimate (the slope of its load-cell weight); a
    load cell off calibration, a weight signal disturbed by vibration or a hopper touched by a
    hose biases that estimate, and the controller then holds the *reported* flow at its set
    point while the powder delivered differs by a fixed fraction (Engisch & Muzzio, J. Pharm.
    Innov. 11:1, 2016: LIW flow estimation). Product-side: the outlet composition is off.
    """

    name = "feed_bias"
    stage = "feeder"
    doc = "relative bias b of the delivered vs the reported flow"
    params = (ParamSpec("bias", 0.0, -0.5, 0.5, "1", "delivered / reported - 1", (0.05, -0.05)),)

    def apply_flow(
        self, t: np.ndarray, flow: np.ndarray, refilling: np.ndarray | None
    ) -> np.ndarray:
        b = self.values["bias"]
        return flow if b == 0.0 else flow * (1.0 + b)


# ---------------------------------------------------------------------------------------
# unit (mass balance) effects
# ---------------------------------------------------------------------------------------
@register
class ComponentLoss(Effect):
    """A fraction of one component's mass does not reach the outlet (lost in the unit):

        m_out,i = (1 - l) m_in,i   (the sink of an open mass balance)

    API sticking to the blade and wall (a coating that is scraped off to waste), drawn off by
    the dust extraction, or segregated into a region that is emptied at cleaning; tracer pulses
    of the component lose the same fraction. Nearly the same reading as a probe gain
    g = (1 - l) / (1 - l c / 100): only an assay of the product tells them apart.
    """

    name = "component_loss"
    stage = "unit"
    doc = "fraction l of the component's mass lost in the unit"
    params = (
        ParamSpec("fraction", 0.0, 0.0, 0.6, "1", "fraction of the component lost", (0.03, 0.1)),
    )

    def apply_component(self, t: np.ndarray, q: np.ndarray) -> np.ndarray:
        return q * (1.0 - self.values["fraction"])


@register
class Holdup(Effect):
    """The unit holds up part of one component while the record runs: a store of M kg fills
    from empty at the start of the record with time constant tau,

        m_out,i(t) = max(m_in,i(t) - (M / tau) exp(-(t - t0) / tau), 0)

    (API building a layer on the blender's blade and wall after start-up or cleaning until the
    layer saturates; the component's outlet content is low at first and recovers with tau).
    Grows from the start of its record, like a drift: reported, not adopted online.
    """

    name = "holdup"
    stage = "unit"
    time_invariant = False
    doc = "component mass M held up by the unit, filling with time constant tau from the start"
    params = (
        ParamSpec("mass_g", 0.0, 0.0, 500.0, "g", "mass held up at saturation", (10.0, 50.0)),
        ParamSpec("tau_s", 300.0, 30.0, 7200.0, "s", "filling time constant", (150.0, 900.0)),
    )

    def apply_component(self, t: np.ndarray, q: np.ndarray) -> np.ndarray:
        m = self.values["mass_g"] / 1000.0
        if m == 0.0:
            return q
        tau = self.values["tau_s"]
        return np.maximum(q - (m / tau) * np.exp(-(t - t[0]) / tau), 0.0)


# ---------------------------------------------------------------------------------------
# sensor effects
# ---------------------------------------------------------------------------------------
@register
class SensorLag(Effect):
    """First-order sensor lag: tau dy/dt = c - y (exact zero-order-hold discretisation)."""

    name = "sensor_lag"
    stage = "sensor"
    order = 0
    doc = "first-order lag of the probe with time constant tau"
    params = (ParamSpec("tau_s", 0.0, 0.0, 60.0, "s", "time constant", (2.0, 8.0)),)

    def apply_sensor(self, t: np.ndarray, c: np.ndarray) -> np.ndarray:
        tau = self.values["tau_s"]
        if tau <= 0.0:
            return c
        dt = float(t[1] - t[0]) if t.size > 1 else 1.0
        a = math.exp(-dt / tau)
        y, _ = lfilter([1.0 - a], [1.0, -a], c, zi=[a * c[0]])
        return y


@register
class SensorGain(Effect):
    """Calibration slope error: y = g c (the seed's day-to-day shift in peak intensity)."""

    name = "sensor_gain"
    stage = "sensor"
    order = 1
    doc = "multiplicative calibration error g"
    params = (ParamSpec("gain", 1.0, 0.2, 3.0, "1", "slope of reading vs truth", (0.9, 1.1)),)

    def apply_sensor(self, t: np.ndarray, c: np.ndarray) -> np.ndarray:
        return self.values["gain"] * c


@register
class SensorOffset(Effect):
    """Calibration offset: y = c + o (% w/w)."""

    name = "sensor_offset"
    stage = "sensor"
    order = 2
    doc = "additive calibration offset o"
    params = (ParamSpec("offset", 0.0, -10.0, 10.0, "% w/w", "additive offset", (0.2, -0.2)),)

    def apply_sensor(self, t: np.ndarray, c: np.ndarray) -> np.ndarray:
        return c + self.values["offset"]


@register
class SensorDrift(Effect):
    """Sensor drift: y = c + d (t - t0) / 3600, t0 the start of the record."""

    name = "sensor_drift"
    stage = "sensor"
    time_invariant = False
    order = 3
    doc = "linear drift d of the reading, % w/w per hour"
    params = (ParamSpec("rate_per_h", 0.0, -20.0, 20.0, "% w/w / h", "drift rate", (0.5, -0.5)),)

    def apply_sensor(self, t: np.ndarray, c: np.ndarray) -> np.ndarray:
        return c + self.values["rate_per_h"] * (t - t[0]) / 3600.0
