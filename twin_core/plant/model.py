"""The declared line model: feeder flows -> blender RTD -> outlet concentration -> NIR signal.

For components i with inlet mass flows m_i(t) (kg/s, tracer pulses included), the blender is a
linear time-invariant system with impulse response E(t) (RTD) acting on each component's mass
flow, so the outlet mass flows are (E * m_i)(t) and the outlet mass fraction is

    c_i(t) = 100 (E * m_i)(t) / (E * sum_j m_j)(t)      [% w/w]

(mass-flow-weighted convolution; Gao, Ierapetritou & Muzzio, Int. J. Pharm. 2012, "Periodic
section modeling of convective continuous powder mixing processes" / Engisch & Muzzio 2012 for
RTD-based composition prediction; the seed's Eq. (6) of 6.2 for the convolution). The line
starts full at the composition of the first sample (the history before t_s[0] is the first
sample extended to the past, added analytically). The NIR signal is the measured component's c_i plus the
declared baseline offset of the sensor; the sensor noise (``twin_core.plant.nir``) is not part
of the prediction.

Candidate effects (``twin_core.plant.effects``) enter at their stage: feeder effects change the
delivered flows, rtd effects change E(t), sensor effects change the signal.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from schemas.line import BlenderModelConfig, LineConfig, TracerPulse
from twin_core.plant.effects import Effect, make_effect


@dataclass
class LineInputs:
    """What the twin sees of the line: reported feeder flows, refill flags, tracer pulses.

    t_s: uniform grid (s); flows_kg_h: feeder id -> reported flow (kg/h) on t_s;
    components: feeder id -> component; refilling: feeder id -> bool array (may be empty);
    tracers: tracer pulses (their mass enters the inlet); screw_speed_rpm: feeder id ->
    screw speed on t_s (diagnostics only; may be empty).
    """

    t_s: np.ndarray
    flows_kg_h: dict[str, np.ndarray]
    components: dict[str, str]
    refilling: dict[str, np.ndarray] = field(default_factory=dict)
    tracers: list[TracerPulse] = field(default_factory=list)
    screw_speed_rpm: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.t_s = np.asarray(self.t_s, dtype=float)
        if self.t_s.ndim != 1 or self.t_s.size < 2:
            raise ValueError(f"t_s must be a 1-D array of >= 2 samples, got shape {self.t_s.shape}")
        d = np.diff(self.t_s)
        if not np.allclose(d, d[0], rtol=1e-6, atol=1e-9) or d[0] <= 0:
            raise ValueError("t_s must be uniform and increasing")
        for k, v in list(self.flows_kg_h.items()):
            v = np.asarray(v, dtype=float)
            if v.shape != self.t_s.shape:
                raise ValueError(f"flows_kg_h[{k}] must have shape {self.t_s.shape}, got {v.shape}")
            if not np.all(np.isfinite(v)) or np.any(v < 0):
                raise ValueError(f"flows_kg_h[{k}] must be finite and >= 0")
            self.flows_kg_h[k] = v
            if k not in self.components:
                raise ValueError(f"components must name the component of feeder {k!r}")
        for k, v in list(self.refilling.items()):
            self.refilling[k] = np.asarray(v, dtype=bool)
        for k, v in list(self.screw_speed_rpm.items()):
            v = np.asarray(v, dtype=float)
            if v.shape != self.t_s.shape:
                raise ValueError(
                    f"screw_speed_rpm[{k}] must have shape {self.t_s.shape}, got {v.shape}"
                )
            self.screw_speed_rpm[k] = v

    @property
    def dt_s(self) -> float:
        return float(self.t_s[1] - self.t_s[0])


def rtd_kernel(
    blender: BlenderModelConfig, tk: np.ndarray, effects: Sequence[Effect] = ()
) -> np.ndarray:
    """E(t) of the blender on ``tk`` (uniform from 0) with the rtd-stage effects applied.

    The base E is ``twin_core.rtd.models.model_e(blender.model, params, tk)`` (the one E(t)
    builder), its parameters first changed by the effects' ``blender_params``, then each
    effect's ``apply_rtd`` in order.
    """
    from twin_core.rtd.models import model_e

    rtd_eff = sorted((e for e in effects if e.stage == "rtd"), key=lambda e: e.order)
    params = dict(blender.params)
    for e in rtd_eff:
        params = e.blender_params(blender.model, params)
    e_t = model_e(blender.model, params, tk)
    for e in rtd_eff:
        e_t = e.apply_rtd(tk, e_t, blender)
    return e_t


def pulse_bin_flow(
    t: np.ndarray | float, dt: float, t0: float, t1: float, rate: float
) -> np.ndarray:
    """Mean over each tick bin [t - dt/2, t + dt/2) of a flow ``rate`` lasting over [t0, t1):

        q(t) = rate * max(0, min(t + dt/2, t1) - max(t - dt/2, t0)) / dt,

    so that sum q dt = rate (t1 - t0) exactly (a tracer pulse's mass). The one spreading of a
    tracer pulse onto the inlet grid: the declared model (:func:`inlet_component_flows`) and the
    live inlet (``twin_core.online.inlet.TracerInjector``) both use it.
    """
    t = np.asarray(t, dtype=float)
    overlap = np.clip(np.minimum(t + 0.5 * dt, t1) - np.maximum(t - 0.5 * dt, t0), 0.0, None)
    return rate * overlap / dt


def require_rtd_blender(config: LineConfig) -> None:
    """The declared line model convolves with an RTD model: ``blender.kind`` must be ``rtd``
    (a compartment export is the live blender service's alternative, not a declared model)."""
    if config.blender.kind != "rtd":
        raise ValueError(
            f"blender.kind must be 'rtd' for the declared line model, got {config.blender.kind!r}"
        )


def _inlet_parts(
    inputs: LineInputs, effects: Sequence[Effect] = ()
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    t = inputs.t_s
    dt = inputs.dt_s
    feed_eff = [e for e in effects if e.stage == "feeder"]
    feed: dict[str, np.ndarray] = {}
    for name, f in inputs.flows_kg_h.items():
        q = f / 3600.0
        for e in feed_eff:
            if e.target is None or e.target == name:
                q = e.apply_flow(t, q, inputs.refilling.get(name))
        c = inputs.components[name]
        feed[c] = feed.get(c, 0.0) + q
    tracer: dict[str, np.ndarray] = {}
    for p in inputs.tracers:
        q = pulse_bin_flow(t, dt, p.t_s, p.t_s + p.duration_s, p.mass_kg / p.duration_s)
        tracer[p.component] = tracer.get(p.component, 0.0) + q
    return feed, tracer


def inlet_component_flows(
    inputs: LineInputs, effects: Sequence[Effect] = ()
) -> dict[str, np.ndarray]:
    """Inlet mass flow per component (kg/s) on inputs.t_s: delivered feeder flows (feeder-stage
    effects applied to their target feeder) plus tracer pulses (:func:`pulse_bin_flow`: mass /
    duration over the pulse, spread over the grid bins it overlaps, so the mass is exact)."""
    feed, tracer = _inlet_parts(inputs, effects)
    out = {c: np.asarray(q, dtype=float) for c, q in feed.items()}
    for c, q in tracer.items():
        out[c] = out.get(c, np.zeros_like(inputs.t_s)) + q
    return out


def outlet_concentration(
    inputs: LineInputs,
    blender: BlenderModelConfig,
    effects: Sequence[Effect] = (),
) -> dict[str, np.ndarray]:
    """Outlet mass fraction of every component, % w/w, c_i = 100 (E*m_i)/(E*sum m).

    The convolution runs on ``inputs.t_s`` with ``twin_core.rtd.convolution.convolve``
    (rectangle rule, y[n] = dt sum_j u[j] E[n-j]). Before t_s[0] the line is at steady state
    with the first feeder flows m_i0 (no tracer): that history adds exactly
    m_i0 S(t), S[n] = 1 - dt sum_{j<=n} E[j] (the fraction of the older material still inside,
    1 - F(t)), so the line starts full and no warm-up padding is needed.
    """
    from twin_core.rtd.convolution import convolve

    t = inputs.t_s
    dt = inputs.dt_s
    feed, tracer = _inlet_parts(inputs, effects)
    comp = {c: np.asarray(q, dtype=float) for c, q in feed.items()}
    for c, q in tracer.items():
        comp[c] = comp.get(c, np.zeros_like(t)) + q
    tg = t - t[0]
    e_t = rtd_kernel(blender, tg, effects)
    survival = np.clip(1.0 - dt * np.cumsum(e_t), 0.0, None)
    outs: dict[str, np.ndarray] = {}
    total = np.zeros(t.size)
    for c, q in comp.items():
        q0 = float(np.atleast_1d(feed.get(c, 0.0))[0])  # steady history: feeders, no tracer
        y = np.asarray(convolve(tg, q, e_t), dtype=float) + q0 * survival
        outs[c] = y
        total = total + y
    with np.errstate(invalid="ignore", divide="ignore"):
        return {c: np.where(total > 0, 100.0 * y / total, np.nan) for c, y in outs.items()}


def sensor_signal(
    t: np.ndarray, c: np.ndarray, effects: Sequence[Effect] = (), baseline_offset: float = 0.0
) -> np.ndarray:
    """Noise-free NIR signal: sensor-stage effects (in their order) on c, plus baseline."""
    y = np.asarray(c, dtype=float)
    for e in sorted((e for e in effects if e.stage == "sensor"), key=lambda e: e.order):
        y = e.apply_sensor(t, y)
    return y + baseline_offset


@dataclass
class LineModel:
    """The declared model of a line (a ``schemas.line.LineConfig``), optionally augmented.

    ``predict(inputs)`` returns the expected NIR reading of ``config.sensor.component`` on
    inputs.t_s; ``outlet(inputs)`` all outlet concentrations. ``effects`` are structural
    additions (instances of ``twin_core.plant.effects.Effect`` or their dict form).
    """

    config: LineConfig
    effects: list[Effect] = field(default_factory=list)

    def __post_init__(self) -> None:
        require_rtd_blender(self.config)
        self.effects = [make_effect(e) for e in self.effects]

    def augmented(self, effects: Sequence[Effect | Mapping]) -> LineModel:
        """A copy with more effects added."""
        return LineModel(self.config, [*self.effects, *[make_effect(e) for e in effects]])

    def outlet(self, inputs: LineInputs) -> dict[str, np.ndarray]:
        return outlet_concentration(inputs, self.config.blender, self.effects)

    def predict(self, inputs: LineInputs) -> np.ndarray:
        sensor = self.config.sensor
        c = self.outlet(inputs).get(sensor.component)
        if c is None:
            c = np.zeros_like(inputs.t_s)
        return sensor_signal(inputs.t_s, c, self.effects, sensor.noise.baseline_offset)
