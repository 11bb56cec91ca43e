"""Open-world effects: what a real line does that the close-loop's candidate library does not.

These effects are injected by the plant simulator only. They are *not* registered in
``twin_core.plant.effects.EFFECTS`` (the candidates the close-loop fits); they live in their own
registry, :data:`OPEN_WORLD`, so the close-loop can be tested on a plant richer than its model.
Each is one small class with its physical story, parameters (``ParamSpec``: default, bounds,
unit) and a reference where one exists; ``side`` says whether it changes the product
(``"product"``: what leaves the blender is not what the model says) or only the probe's view
of it (``"probe"``). ``aliases`` lists candidate names that would name the same mechanism (a
claim of one of them is the truth, not a confusion).

Stages and hooks (the simulator's chain, ``twin_core.plant.simulate``):

- ``feeder``: :meth:`OpenWorldEffect.apply_feeder` turns a feeder's reported flow into the
  flow delivered to the blender (it sees the feeder's whole record: screw speed, refills);
- ``blender``: :meth:`OpenWorldEffect.blender_terms` adds terms to the finite-volume vessel
  (``twin_core.plant.blender_fv``): a velocity factor, a wall film, a stagnant zone. They need
  the simulator's ``blender="fv"`` path, not the declared convolution;
- ``sensor``: :meth:`OpenWorldEffect.apply_sensor` turns the outlet concentration into the
  probe's noise-free reading (before the in-list sensor effects and the baseline offset).

The classes reuse :class:`twin_core.plant.effects.Effect` for parameter handling (bounds,
dict form) only; the close-loop never sees them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from scipy.optimize import brentq
from scipy.signal import lfilter

from schemas.line import LineConfig
from twin_core.plant.blender_fv import FiniteVolumeBlender, FVResult, WallFilm
from twin_core.plant.effects import Effect, ParamSpec
from twin_core.plant.model import (
    LineInputs,
    apply_unit_effects,
    outlet_concentration,
    pulse_bin_flow,
    sensor_signal,
)

__all__ = [
    "OPEN_WORLD",
    "BlenderContext",
    "BlenderTerms",
    "OpenWorldEffect",
    "OpenWorldLine",
    "delivered_flows",
    "make_open_world",
    "open_world_line",
    "register_open_world",
]

OPEN_WORLD: dict[str, type[OpenWorldEffect]] = {}


def register_open_world(cls: type[OpenWorldEffect]) -> type[OpenWorldEffect]:
    """Class decorator: add an open-world effect to :data:`OPEN_WORLD` (never to ``EFFECTS``)."""
    if cls.name in OPEN_WORLD:
        raise ValueError(f"open-world effect name must be unique, got duplicate {cls.name!r}")
    if cls.stage not in ("feeder", "blender", "sensor"):
        raise ValueError(f"open-world stage must be feeder/blender/sensor, got {cls.stage!r}")
    if cls.side not in ("product", "probe"):
        raise ValueError(f"open-world side must be product/probe, got {cls.side!r}")
    OPEN_WORLD[cls.name] = cls
    return cls


@dataclass(frozen=True)
class BlenderContext:
    """What a blender-stage effect may use: the declared vessel ``fv``, the grid ``t``, the
    feeders' delivered flows per component ``feed_kg_s`` (kg/s, tracers excluded) and the
    sensor's ``component``."""

    fv: FiniteVolumeBlender
    t: np.ndarray
    feed_kg_s: Mapping[str, np.ndarray]
    component: str


@dataclass
class BlenderTerms:
    """What blender-stage effects add to the finite-volume vessel: a velocity factor per tick
    (product of all), wall films, a stagnant zone (volume ratio, exchange time)."""

    velocity: np.ndarray | None = None
    films: list[WallFilm] = field(default_factory=list)
    dead_ratio: float = 0.0
    dead_tau_s: float = 60.0


class OpenWorldEffect(Effect):
    """Base class of the open-world effects (module docstring). ``target``: the feeder of a
    feeder-stage effect; for blender effects acting on one component, the component (default:
    the sensor's)."""

    side: ClassVar[str] = ""
    aliases: ClassVar[tuple[str, ...]] = ()

    def apply_feeder(self, t: np.ndarray, flow_kg_s: np.ndarray, record: Any) -> np.ndarray:
        """feeder stage: delivered flow (kg/s) from the reported one and the feeder's record
        (``twin_core.plant.simulate.FeederRecord``: screw speed, refill flags)."""
        return flow_kg_s

    def blender_terms(self, ctx: BlenderContext) -> BlenderTerms:
        """blender stage: terms for the vessel (:class:`BlenderContext`: the declared vessel,
        the grid, the feeders' delivered flows per component, the sensor's component)."""
        return BlenderTerms()

    def to_dict(self) -> dict[str, Any]:
        return {**super().to_dict(), "side": self.side, "stage": self.stage}


def make_open_world(spec: OpenWorldEffect | Mapping[str, Any]) -> OpenWorldEffect:
    """An open-world effect from an instance or ``{"name", "params": {...}, "target": ...}``."""
    if isinstance(spec, OpenWorldEffect):
        return spec
    if not isinstance(spec, Mapping) or "name" not in spec:
        raise ValueError(f"open-world effect must be a mapping with 'name', got {spec!r}")
    name = spec["name"]
    if name not in OPEN_WORLD:
        raise ValueError(
            f"open-world effect name must be one of {sorted(OPEN_WORLD)}, got {name!r}"
        )
    return OPEN_WORLD[name](target=spec.get("target"), **dict(spec.get("params", {})))


# ---------------------------------------------------------------------------------------------
# feeder stage (product side)
# ---------------------------------------------------------------------------------------------
@register_open_world
class LoadCellSpanError(OpenWorldEffect):
    """Delivered-vs-reported feed bias from a load-cell calibration (span) error.

    The load cell reads W / (1 + b); the controller regulates the flow it computes from that
    weight to the set point, so the screw delivers (1 + b) times what the feeder reports, at
    every operating point, in gravimetric and volumetric mode alike:

        delivered = (1 + b) reported

    (LIW control on the load-cell weight: Engisch & Muzzio, J. Pharm. Innov. 11 (2016) 28). The
    product is off target while the feeder display is right; only an assay or an independent
    mass check (catch-weigh) sees it. Tracer pulses, dosed by hand, are not biased.
    """

    name = "load_cell_span_error"
    stage = "feeder"
    side = "product"
    aliases = ("feed_bias", "feeder_bias", "flow_bias", "delivered_bias", "feed_rate_bias")
    doc = "delivered flow = (1 + b) x reported (load-cell span error)"
    params = (ParamSpec("bias", 0.0, -0.5, 0.5, "1", "relative excess of the delivered flow"),)

    def apply_feeder(self, t: np.ndarray, flow_kg_s: np.ndarray, record: Any) -> np.ndarray:
        return flow_kg_s * (1.0 + self.values["bias"])


@register_open_world
class ScrewPulsation(OpenWorldEffect):
    """Periodic feed pulsation coherent with the screw rotation.

    A twin-screw feeder discharges in pulses as the flights pass the outlet: at low fill and
    low speed the flow fluctuates at the screw frequency (form chosen here: one harmonic). With
    theta(t) the screw angle, the integral of 2 pi rpm/60 over the feeder's reported screw
    speed,

        delivered = reported (1 + a sin(n theta(t) + phi)),

    n pulses per revolution. The blender filters it (|G(i omega)| of the RTD), so what reaches
    the probe is a line in the spectrum at n rpm/60 Hz, coherent with the screw speed record.
    Each tick gets the exact mean of the sine over the tick (theta linear within it).
    """

    name = "screw_pulsation"
    stage = "feeder"
    side = "product"
    doc = "relative flow pulsation a at n x the screw frequency"
    params = (
        ParamSpec("amplitude", 0.0, 0.0, 0.9, "1", "relative amplitude of the pulsation"),
        ParamSpec("pulses_per_rev", 1.0, 1.0, 8.0, "1", "pulses per screw revolution"),
        ParamSpec("phase", 0.0, -math.pi, math.pi, "rad", "phase at t = 0"),
    )

    def apply_feeder(self, t: np.ndarray, flow_kg_s: np.ndarray, record: Any) -> np.ndarray:
        rpm = np.asarray(record.screw_speed_rpm, dtype=float)
        if rpm.shape != t.shape or not np.all(np.isfinite(rpm)):
            raise ValueError(
                f"screw_pulsation needs a LIW feeder's screw speed, feeder {record.id!r} has none"
            )
        return flow_kg_s * (1.0 + self.values["amplitude"] * self.tick_mean_sine(t, rpm))

    def tick_mean_sine(self, t: np.ndarray, rpm: np.ndarray) -> np.ndarray:
        """Mean of sin(n theta + phi) over each tick, theta from the screw speed at the tick's
        start: (cos x_j - cos x_{j+1}) / (x_{j+1} - x_j), x = n theta + phi."""
        dt = float(t[1] - t[0])
        n = self.values["pulses_per_rev"]
        step = n * 2.0 * math.pi * rpm / 60.0 * dt
        x0 = self.values["phase"] + np.concatenate([[0.0], np.cumsum(step[:-1])])
        x1 = x0 + step
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = (np.cos(x0) - np.cos(x1)) / step
        return np.where(step > 1e-9, mean, np.sin(x0))

    def frequency_hz(self, rpm: float) -> float:
        """Pulsation frequency at a screw speed: n rpm / 60."""
        return self.values["pulses_per_rev"] * rpm / 60.0


@register_open_world
class ChuteClogging(OpenWorldEffect):
    """Intermittent clogging of the feeder's discharge chute.

    Powder bridges in the chute between the feeder and the blender inlet: for a few seconds
    nothing reaches the blender while the feeder (whose load cell is upstream) reports its
    normal flow; then the plug breaks and the held mass arrives as a slug over ``slug_s``.
    Episodes start as a Poisson process (``rate_per_h``) with durations uniform in
    [``min_s``, ``max_s``] (whole ticks; drawn from ``seed``). Mass is conserved: every
    episode's held mass is delivered by the slug.
    """

    name = "chute_clogging"
    stage = "feeder"
    side = "product"
    doc = "feed chute blocked for min_s..max_s, then the held mass released as a slug"
    params = (
        ParamSpec("rate_per_h", 0.0, 0.0, 60.0, "1/h", "episodes per hour"),
        ParamSpec("min_s", 5.0, 1.0, 600.0, "s", "shortest blockage"),
        ParamSpec("max_s", 20.0, 1.0, 600.0, "s", "longest blockage"),
        ParamSpec("slug_s", 4.0, 1.0, 60.0, "s", "time the held mass takes to arrive"),
        ParamSpec("seed", 0.0, 0.0, 2.0**31, "1", "seed of the episode times"),
    )

    def episodes(self, t: np.ndarray) -> list[tuple[int, int]]:
        """(first tick, number of ticks) of the blockages inside the run (each followed by its
        slug, all inside the run)."""
        v = self.values
        if v["max_s"] < v["min_s"]:
            raise ValueError(f"chute_clogging.max_s must be >= min_s, got {v['max_s']!r}")
        dt = float(t[1] - t[0])
        rng = np.random.default_rng(int(v["seed"]))
        out: list[tuple[int, int]] = []
        slug = int(math.ceil(v["slug_s"] / dt))
        now = 0.0
        while v["rate_per_h"] > 0:
            now += rng.exponential(3600.0 / v["rate_per_h"])
            i = int(round(now / dt))
            k = max(1, int(round(rng.uniform(v["min_s"], v["max_s"]) / dt)))
            if i + k + slug >= t.size:
                break
            if not out or i > out[-1][0] + out[-1][1] + slug:
                out.append((i, k))
        return out

    def apply_feeder(self, t: np.ndarray, flow_kg_s: np.ndarray, record: Any) -> np.ndarray:
        dt = float(t[1] - t[0])
        slug = int(math.ceil(self.values["slug_s"] / dt))
        out = np.array(flow_kg_s, dtype=float)
        for i, k in self.episodes(t):
            held = float(out[i : i + k].sum())
            out[i : i + k] = 0.0
            out[i + k : i + k + slug] += held / slug
        return out


# ---------------------------------------------------------------------------------------------
# blender stage (product side)
# ---------------------------------------------------------------------------------------------
@register_open_world
class ApiWallLoss(OpenWorldEffect):
    """API lost in the blender: a steady first-order loss of the API to the walls and blades
    (adhering fines scraped to the dust extraction, or electrostatic build-up that never
    releases).

    In the vessel the API density decays at a rate k besides being transported; at steady
    state the fraction that reaches the outlet is G_AD(k), the transfer function of the
    open-open dispersion vessel at s = k, G_AD(s) = exp(Pe (1 - q) / 2) / q,
    q = sqrt(1 + 4 s tau / Pe) (Levenspiel, Chemical Reaction Engineering, 3rd ed., ch. 13-14:
    a first-order sink in a dispersed-flow vessel), so k solves 1 - G_AD(k) = lambda for the
    lost fraction lambda (the plug-flow delay loses nothing). The product is low in API by
    about lambda (1 - c) c; the probe reads it right.
    """

    name = "api_wall_loss"
    stage = "blender"
    side = "product"
    aliases = ("component_loss", "api_loss", "api_lost", "material_loss", "holdup_loss")
    doc = "a fraction lambda of the API is lost in the blender (first-order wall loss)"
    params = (
        ParamSpec("loss_fraction", 0.0, 0.0, 0.9, "1", "fraction of the API lost at steady state"),
    )

    def rate_per_s(self, tau: float, pe: float) -> float:
        """Loss rate k giving the fraction lambda lost in the open-open vessel (docstring)."""
        lam = self.values["loss_fraction"]
        if lam == 0.0:
            return 0.0

        def lost(k: float) -> float:
            q = math.sqrt(1.0 + 4.0 * k * tau / pe)
            return 1.0 - math.exp(0.5 * pe * (1.0 - q)) / q - lam

        hi = 1.0 / tau
        while lost(hi) < 0:
            hi *= 2.0
        return float(brentq(lost, 0.0, hi, xtol=1e-14, rtol=1e-12))

    def blender_terms(self, ctx: BlenderContext) -> BlenderTerms:
        k = self.rate_per_s(ctx.fv.tau, ctx.fv.pe)
        if k == 0.0:
            return BlenderTerms()
        return BlenderTerms(films=[WallFilm(self.target or ctx.component, k)])


@register_open_world
class ApiBuildupRelease(OpenWorldEffect):
    """API held up on the blender walls: build-up to a capacity, then release.

    After cleaning the walls are bare: API deposits at rate k (1 - m_f/m_cap) (a Langmuir-like
    film that saturates), so the product starts low in API and recovers as the film fills; at
    ``release_s`` the film sloughs off and its mass returns to the flow with time constant
    ``release_tau_s`` (a high-API slug), and then builds up again. Wall build-up and sudden
    release of cohesive API (form chosen here: a Langmuir-like capacity, an exponential
    release; blender hold-up itself: Vanarase & Muzzio, Powder Technol. 208 (2011) 26).
    ``release_s`` < 0: no release.
    """

    name = "api_buildup_release"
    stage = "blender"
    side = "product"
    aliases = ("api_holdup", "holdup", "api_loss", "material_holdup")
    doc = "API film building up to m_cap (rate k), released at release_s"
    params = (
        ParamSpec("deposition_per_s", 0.0, 0.0, 1.0, "1/s", "deposition rate on bare walls"),
        ParamSpec("capacity_g", 5.0, 0.01, 1000.0, "g", "film capacity"),
        ParamSpec("release_s", -1.0, -1.0, 1e6, "s", "plant time of the release (< 0: none)"),
        ParamSpec("release_tau_s", 20.0, 1.0, 600.0, "s", "release time constant"),
    )

    def blender_terms(self, ctx: BlenderContext) -> BlenderTerms:
        v = self.values
        if v["deposition_per_s"] == 0.0:
            return BlenderTerms()
        film = WallFilm(
            self.target or ctx.component,
            v["deposition_per_s"],
            capacity_kg=v["capacity_g"] / 1000.0,
            release_s=(v["release_s"],) if v["release_s"] >= 0 else (),
            release_tau_s=v["release_tau_s"],
        )
        return BlenderTerms(films=[film])


@register_open_world
class ThroughputHoldup(OpenWorldEffect):
    """Blender hold-up that changes with the throughput: RTD parameters depend on the operating
    point.

    In a continuous convective blender the hold-up grows less than the flow, so the mean
    residence time falls with the throughput Q (Vanarase & Muzzio, Powder Technol. 208 (2011)
    26; Gao, Muzzio & Ierapetritou, Chem. Eng. Sci. 66 (2011) 417). Modelled as

        tau(Q) = tau (Q / Q_ref)^(-alpha),  Pe unchanged,

    Q the feeders' total delivered flow as the vessel receives it (plug delay), smoothed over
    ``lag_s`` (the hold-up needs about a residence time to adjust), Q_ref the flow at which the
    declared tau holds (``reference_kg_h``; 0: the first tick's). The vessel's velocity factor
    is (Q/Q_ref)^alpha. The declared model has one tau for every operating point.
    """

    name = "throughput_holdup"
    stage = "blender"
    side = "product"
    doc = "tau scales as (Q/Q_ref)^-alpha with the throughput"
    params = (
        ParamSpec("alpha", 0.0, 0.0, 2.0, "1", "exponent of the throughput dependence"),
        ParamSpec("lag_s", 30.0, 0.0, 600.0, "s", "hold-up adjustment time"),
        ParamSpec("reference_kg_h", 0.0, 0.0, 1000.0, "kg/h", "throughput of the declared tau"),
    )

    def blender_terms(self, ctx: BlenderContext) -> BlenderTerms:
        total = sum(np.asarray(q, dtype=float) for q in ctx.feed_kg_s.values()) * 3600.0
        q = ctx.fv.delayed(total)
        lag = self.values["lag_s"]
        if lag > 0:
            a = math.exp(-ctx.fv.dt_s / lag)
            q, _ = lfilter([1.0 - a], [1.0, -a], q, zi=[a * q[0]])
        ref = self.values["reference_kg_h"] or float(total[0])
        return BlenderTerms(velocity=(np.maximum(q, 1e-9) / ref) ** self.values["alpha"])


@register_open_world
class TwoZoneExchange(OpenWorldEffect):
    """A stagnant zone exchanging with the flowing powder at a finite rate, all along the
    blender (mobile-immobile dispersion: Coats & Smith, SPE J. 4 (1964) 73; van Genuchten &
    Wierenga, Soil Sci. Soc. Am. J. 40 (1976) 473).

    d rho/dt = transport - (r / tau_x)(rho - s),  ds/dt = (rho - s) / tau_x

    r the stagnant-to-flowing volume ratio, tau_x the exchange time. Material enters and
    leaves the stagnant zone many times, so the response is second order (Laplace: s ->
    s (1 + r / (1 + s tau_x)) in G_AD): the mean grows by (1 + r) and a long tail appears that
    neither a Peclet change, a delay, nor the library's single-pass dead zone (one detour
    through a CSTR) reproduces. The hold-up is (1 + r) times the declared one.
    """

    name = "two_zone_exchange"
    stage = "blender"
    side = "product"
    aliases = ("dead_zone",)
    doc = "stagnant zone of volume ratio r exchanging with time constant tau_x"
    params = (
        ParamSpec("volume_ratio", 0.0, 0.0, 5.0, "1", "stagnant / flowing volume"),
        ParamSpec("exchange_tau_s", 60.0, 1.0, 3600.0, "s", "exchange time constant"),
    )

    def blender_terms(self, ctx: BlenderContext) -> BlenderTerms:
        return BlenderTerms(
            dead_ratio=self.values["volume_ratio"], dead_tau_s=self.values["exchange_tau_s"]
        )


# ---------------------------------------------------------------------------------------------
# sensor stage (probe side)
# ---------------------------------------------------------------------------------------------
def _rise(t: np.ndarray, t0: float, time_constant: float) -> np.ndarray:
    """0 before t0, then 1 - exp(-(t - t0)/T) (T = 0: a step)."""
    dt = np.clip(np.asarray(t, dtype=float) - t0, 0.0, None)
    if time_constant <= 0:
        return (np.asarray(t) >= t0).astype(float)
    return 1.0 - np.exp(-dt / time_constant)


@register_open_world
class ProbeFouling(OpenWorldEffect):
    """Powder film growing on the NIR probe window: a slow multiplicative loss of signal and a
    growing lag (the film is renewed ever more slowly by the flowing powder).

    s(t) = 1 - exp(-(t - t0)/T) after t0,  reading = (1 - phi_max s(t)) y(t),
    dy/dt = (c - y) / (tau_max s(t))

    (time-varying first-order lag with the sample convention of the library's sensor lag,
    y_i = a_i y_(i-1) + (1 - a_i) c_i, a_i = exp(-dt / tau_i)). Form chosen here: both the
    loss and the lag grow with the film's thickness, which saturates.
    """

    name = "probe_fouling"
    stage = "sensor"
    side = "probe"
    doc = "signal loss phi_max and lag tau_max growing with time constant T from t0"
    params = (
        ParamSpec("t_start_s", 0.0, 0.0, 1e6, "s", "fouling starts"),
        ParamSpec("growth_s", 1800.0, 1.0, 1e6, "s", "growth time constant T"),
        ParamSpec("loss_max", 0.0, 0.0, 0.9, "1", "final relative signal loss phi_max"),
        ParamSpec("lag_max_s", 0.0, 0.0, 600.0, "s", "final lag tau_max"),
    )

    def apply_sensor(self, t: np.ndarray, c: np.ndarray) -> np.ndarray:
        v = self.values
        s = _rise(t, v["t_start_s"], v["growth_s"])
        tau = v["lag_max_s"] * s
        dt = float(t[1] - t[0])
        with np.errstate(divide="ignore", over="ignore"):
            a = np.where(tau > 0, np.exp(-dt / np.where(tau > 0, tau, 1.0)), 0.0)
        c = np.asarray(c, dtype=float)
        y = np.empty_like(c)
        y[0] = c[0]
        for i in range(1, y.size):
            y[i] = a[i] * y[i - 1] + (1.0 - a[i]) * c[i]
        return (1.0 - v["loss_max"] * s) * y


@register_open_world
class NonlinearCalibration(OpenWorldEffect):
    """A calibration that is linear only near its centre: diffuse reflectance is not linear in
    concentration (Kubelka-Munk; the PLS model was built on a narrow range), so

        reading = c + kappa (c - c_ref)^2,

    right at the calibration centre c_ref, biased upwards (kappa > 0) at other set points and
    strongly at tracer peaks (Burns & Ciurczak, Handbook of Near-Infrared Analysis, 3rd ed.,
    on non-linearity of NIR calibrations).
    """

    name = "nonlinear_calibration"
    stage = "sensor"
    side = "probe"
    doc = "quadratic calibration curvature kappa about c_ref"
    params = (
        ParamSpec("curvature", 0.0, -0.5, 0.5, "1/(% w/w)", "kappa"),
        ParamSpec("centre", 10.0, 0.0, 100.0, "% w/w", "calibration centre c_ref"),
    )

    def apply_sensor(self, t: np.ndarray, c: np.ndarray) -> np.ndarray:
        c = np.asarray(c, dtype=float)
        return c + self.values["curvature"] * (c - self.values["centre"]) ** 2


@register_open_world
class HumidityStep(OpenWorldEffect):
    """A calibration step driven by the room humidity: at ``t_s`` the air handling changes the
    relative humidity, the powder's surface moisture follows with time constant ``tau_s`` and
    the water bands shift the NIR prediction (water absorbs strongly near 1450 and 1940 nm;
    Burns & Ciurczak, Handbook of Near-Infrared Analysis):

        reading = c + delta (1 - exp(-(t - t_s)/tau_s)) for t > t_s.

    Neither a constant offset nor a linear drift from the record start.
    """

    name = "humidity_step"
    stage = "sensor"
    side = "probe"
    doc = "offset delta appearing at t_s with time constant tau_s"
    params = (
        ParamSpec("t_s", 0.0, 0.0, 1e6, "s", "humidity change"),
        ParamSpec("offset", 0.0, -10.0, 10.0, "% w/w", "final offset delta"),
        ParamSpec("tau_s", 300.0, 0.0, 1e5, "s", "moisture equilibration time"),
    )

    def apply_sensor(self, t: np.ndarray, c: np.ndarray) -> np.ndarray:
        v = self.values
        return np.asarray(c, dtype=float) + v["offset"] * _rise(t, v["t_s"], v["tau_s"])


# ---------------------------------------------------------------------------------------------
# the line with open-world effects
# ---------------------------------------------------------------------------------------------
@dataclass
class OpenWorldLine:
    """Noise-free line under in-list and open-world effects: delivered flow per feeder (kg/h),
    outlet concentration per component (% w/w), the probe's noise-free reading, and the
    finite-volume run (``None`` on the convolution path)."""

    delivered_kg_h: dict[str, np.ndarray]
    outlet_pct_w_w: dict[str, np.ndarray]
    signal: np.ndarray
    fv: FVResult | None = None


def delivered_flows(
    t: np.ndarray,
    feeders: Mapping[str, Any],
    effects: Sequence[Effect] = (),
    open_world: Sequence[OpenWorldEffect] = (),
) -> dict[str, np.ndarray]:
    """Delivered flow of every feeder (kg/s): the reported flow, then the in-list feeder effects
    (``Effect.apply_flow``), then the open-world ones (:meth:`OpenWorldEffect.apply_feeder`), each
    on its target feeder (None: every feeder)."""
    out: dict[str, np.ndarray] = {}
    for name, rec in feeders.items():
        q = np.asarray(rec.flow_kg_h, dtype=float) / 3600.0
        for e in effects:
            if e.stage == "feeder" and e.target in (None, name):
                q = e.apply_flow(t, q, rec.refilling)
        for e in open_world:
            if e.stage == "feeder" and e.target in (None, name):
                q = e.apply_feeder(t, q, rec)
        out[name] = q
    return out


def _blender_terms(
    fv: FiniteVolumeBlender,
    t: np.ndarray,
    feed: Mapping[str, np.ndarray],
    component: str,
    open_world: Sequence[OpenWorldEffect],
) -> BlenderTerms:
    """The blender-stage effects' terms combined (velocity factors multiply)."""
    terms = BlenderTerms()
    ctx = BlenderContext(fv, t, feed, component)
    for e in open_world:
        if e.stage != "blender":
            continue
        part = e.blender_terms(ctx)
        if part.velocity is not None:
            terms.velocity = (
                part.velocity if terms.velocity is None else terms.velocity * part.velocity
            )
        terms.films.extend(part.films)
        if part.dead_ratio > 0:
            if terms.dead_ratio > 0:
                raise ValueError("open_world may hold one stagnant-zone effect, got two")
            terms.dead_ratio, terms.dead_tau_s = part.dead_ratio, part.dead_tau_s
    return terms


def open_world_line(
    config: LineConfig,
    t: np.ndarray,
    feeders: Mapping[str, Any],
    effects: Sequence[Effect] = (),
    open_world: Sequence[OpenWorldEffect] = (),
    blender: str = "fv",
) -> OpenWorldLine:
    """The noise-free line on the grid ``t`` from the feeders' records (reported flows, screw
    speeds, refill flags; ``twin_core.plant.simulate.FeederRecord``) under in-list ``effects``
    and ``open_world`` effects.

    ``blender="fv"``: the vessel is :class:`~twin_core.plant.blender_fv.FiniteVolumeBlender`
    (the independent code path; in-list rtd effects, defined on E(t), are not available there);
    ``"convolution"``: the declared model's convolution (``twin_core.plant.model``; open-world
    blender effects are not available there). Tracer pulses enter as in the declared model
    (``model.pulse_bin_flow``); in-list unit-stage effects change what enters the vessel
    (``model.apply_unit_effects``; the finite-volume vessel starts at steady state with the
    first of those flows); the probe sees the open-world sensor effects, then the in-list
    sensor effects and the baseline (``model.sensor_signal``).
    """
    if blender not in ("fv", "convolution"):
        raise ValueError(f"blender must be 'fv' or 'convolution', got {blender!r}")
    sensor = config.sensor
    components = {f.id: f.component for f in config.feeders}
    per_feeder = delivered_flows(t, feeders, effects, open_world)
    feed: dict[str, np.ndarray] = {}
    for name, q in per_feeder.items():
        feed[components[name]] = feed.get(components[name], 0.0) + q
    fv_run = None
    if blender == "convolution":
        bad = [e.name for e in open_world if e.stage == "blender"]
        if bad:
            raise ValueError(
                f"open_world blender effects {bad} need blender='fv', got 'convolution'"
            )
        delivered = LineInputs(
            t_s=t,
            flows_kg_h={n: q * 3600.0 for n, q in per_feeder.items()},
            components=components,
            tracers=list(config.tracers),
        )
        vessel = [e for e in effects if e.stage in ("rtd", "unit")]
        outlet = outlet_concentration(delivered, config.blender, vessel)
    else:
        bad = [e.name for e in effects if e.stage == "rtd"]
        if bad:
            raise ValueError(f"effects {bad} act on E(t): use blender='convolution', got 'fv'")
        dt = float(t[1] - t[0])
        probe = FiniteVolumeBlender.from_config(config.blender, dt)
        terms = _blender_terms(probe, t, feed, sensor.component, open_world)
        fv = FiniteVolumeBlender.from_config(
            config.blender, dt, dead_ratio=terms.dead_ratio, dead_tau_s=terms.dead_tau_s
        )
        inlet = {c: np.array(q, dtype=float) for c, q in feed.items()}
        for p in config.tracers:
            rate = p.mass_kg / p.duration_s
            pulse = pulse_bin_flow(t, dt, p.t_s, p.t_s + p.duration_s, rate)
            inlet[p.component] = inlet.get(p.component, np.zeros_like(t)) + pulse
        for c in inlet:
            inlet[c], _ = apply_unit_effects(t, c, inlet[c], float(inlet[c][0]), effects)
        fv_run = fv.simulate(inlet, velocity=terms.velocity, films=terms.films)
        outlet = fv_run.outlet_pct_w_w
    c = outlet.get(sensor.component, np.zeros_like(t))
    for e in open_world:
        if e.stage == "sensor":
            c = e.apply_sensor(t, c)
    signal = sensor_signal(t, c, effects, sensor.noise.baseline_offset)
    return OpenWorldLine(
        delivered_kg_h={n: q * 3600.0 for n, q in per_feeder.items()},
        outlet_pct_w_w=outlet,
        signal=signal,
        fv=fv_run,
    )
