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
delivered flows, rtd effects change E(t), unit effects the mass of a component the unit passes
on, sensor effects change the signal. :class:`OutletModel` evaluates the outlet of one set of
inputs for many effect sets (the close-loop's fits) with the convolutions' spectra kept.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sp_fft

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

    params = rtd_params(blender, effects)
    return apply_rtd_effects(blender, tk, model_e(blender.model, params, tk), effects)


def rtd_params(blender: BlenderModelConfig, effects: Sequence[Effect] = ()) -> dict[str, float]:
    """The blender model's parameters changed by the rtd-stage effects' ``blender_params``."""
    params = dict(blender.params)
    for e in sorted((e for e in effects if e.stage == "rtd"), key=lambda e: e.order):
        params = e.blender_params(blender.model, params)
    return params


def apply_rtd_effects(
    blender: BlenderModelConfig, tk: np.ndarray, e_t: np.ndarray, effects: Sequence[Effect] = ()
) -> np.ndarray:
    """Each rtd-stage effect's ``apply_rtd``, in order, on the model's E(t) sampled on ``tk``."""
    for e in sorted((e for e in effects if e.stage == "rtd"), key=lambda e: e.order):
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


def rtd_blender_config(config: LineConfig) -> LineConfig:
    """The line with an RTD-model blender, as the declared line model convolves with one: the
    config itself for ``blender.kind: rtd``; for a compartment blender, its axial-dispersion
    equivalent at the declared operating point
    (``twin_core.compartment.operating_point.rtd_equivalent``)."""
    if config.blender.kind == "rtd":
        return config
    from twin_core.compartment.operating_point import configured_point, rtd_equivalent

    blender = rtd_equivalent(config.blender, configured_point(config))
    return config.model_copy(update={"blender": blender})


def _apply_feeder_effects(inputs: LineInputs, feeder: str, effects: Sequence[Effect]) -> np.ndarray:
    """Delivered mass flow (kg/s) of one feeder: its reported flow through the feeder-stage
    effects that target it (or every feeder), in their order."""
    q = inputs.flows_kg_h[feeder] / 3600.0
    for e in sorted(effects, key=lambda e: e.order):
        if e.stage == "feeder" and (e.target is None or e.target == feeder):
            q = e.apply_flow(inputs.t_s, q, inputs.refilling.get(feeder))
    return q


def apply_unit_effects(
    t: np.ndarray, component: str, q: np.ndarray, q0: float, effects: Sequence[Effect]
) -> tuple[np.ndarray, float]:
    """The component's mass flow through the unit-stage effects acting on it (``target``: the
    component, or None for every component): the inflow ``q`` and the steady history ``q0``
    (time-invariant effects only: a time-variant one starts with the record)."""
    for e in sorted(effects, key=lambda e: e.order):
        if e.stage == "unit" and (e.target is None or e.target == component):
            q = e.apply_component(t, q)
            if e.time_invariant:
                q0 = float(e.apply_component(t[:1], np.array([q0]))[0])
    return q, q0


def _tracer_flows(inputs: LineInputs) -> dict[str, np.ndarray]:
    """Tracer pulses as mass flows per component (kg/s, :func:`pulse_bin_flow`)."""
    tracer: dict[str, np.ndarray] = {}
    for p in inputs.tracers:
        q = pulse_bin_flow(
            inputs.t_s, inputs.dt_s, p.t_s, p.t_s + p.duration_s, p.mass_kg / p.duration_s
        )
        tracer[p.component] = tracer.get(p.component, 0.0) + q
    return tracer


def inlet_component_flows(
    inputs: LineInputs, effects: Sequence[Effect] = ()
) -> dict[str, np.ndarray]:
    """Inlet mass flow per component (kg/s) on inputs.t_s: delivered feeder flows (feeder-stage
    effects applied to their target feeder) plus tracer pulses (:func:`pulse_bin_flow`: mass /
    duration over the pulse, spread over the grid bins it overlaps, so the mass is exact), then
    the unit-stage effects of the component (what the unit passes on)."""
    return {c: q for c, (q, _) in OutletModel(inputs).inflows(effects).items()}


#: E(t) beyond the sample where less than this mass is left is not convolved (its contribution
#: to an outlet mass flow is below this fraction of the inflow)
KERNEL_TAIL_MASS = 1e-12


class OutletModel:
    """The declared line model's outlet on one set of inputs, evaluated for many effect sets.

    c_i = 100 (E * m_i) / (E * sum m) (module docstring) by FFT convolution: the spectra of the
    component inflows and of E(t) are kept (keyed by the effects that change them), so an effect
    set that changes only E(t) costs one forward and two inverse real FFTs, one that changes
    one feeder's flow one forward and two inverse. E(t) is convolved up to the sample where less
    than ``KERNEL_TAIL_MASS`` of it is left (shorter transforms). The line's history before
    t_s[0] (steady state at the first flows) adds q0 S(t), S = 1 - F.
    """

    def __init__(self, inputs: LineInputs, blender: BlenderModelConfig | None = None) -> None:
        self.inputs = inputs
        self.blender = blender
        self.t = inputs.t_s
        self.n = self.t.size
        self.dt = inputs.dt_s
        self.tg = self.t - self.t[0]
        self.tracer = _tracer_flows(inputs)
        self.components = sorted(set(inputs.components.values()) | set(self.tracer))
        self._spectra: dict[tuple, np.ndarray] = {}
        self._kernels: dict[tuple, tuple[np.ndarray, np.ndarray, int]] = {}
        self._base: dict[tuple, np.ndarray] = {}
        self._inflows: dict[tuple, dict[str, tuple[np.ndarray, float]]] = {}

    # -- inflows -------------------------------------------------------------------------
    def inflows(self, effects: Sequence[Effect] = ()) -> dict[str, tuple[np.ndarray, float]]:
        """Component -> (inflow of the unit, kg/s, steady history value q0) under the feeder-
        and unit-stage effects."""
        key = _effects_key(effects, ("feeder", "unit"))
        hit = self._inflows.get(key)
        if hit is not None:
            return hit
        inp = self.inputs
        feed: dict[str, np.ndarray] = {}
        for name in inp.flows_kg_h:
            c = inp.components[name]
            feed[c] = feed.get(c, 0.0) + _apply_feeder_effects(inp, name, effects)
        out = {}
        for c in self.components:
            f = np.asarray(feed.get(c, np.zeros(self.n)), dtype=float)
            q = f + self.tracer[c] if c in self.tracer else f
            out[c] = apply_unit_effects(self.t, c, q, float(f[0]), effects)
        if len(self._inflows) > 64:
            self._inflows.clear()
        self._inflows[key] = out
        return out

    # -- kernel --------------------------------------------------------------------------
    def kernel(self, effects: Sequence[Effect] = ()) -> tuple[np.ndarray, np.ndarray, int]:
        """(E(t) on the record's grid with the rtd-stage effects, survival S = 1 - F, the
        number of samples of E convolved)."""
        if self.blender is None:
            raise ValueError("blender must be given to evaluate the outlet")
        key = _effects_key(effects, ("rtd",))
        hit = self._kernels.get(key)
        if hit is None:
            from twin_core.rtd.models import model_e

            params = rtd_params(self.blender, effects)
            pkey = tuple(sorted(params.items()))
            base = self._base.get(pkey)
            if base is None:
                base = self._base[pkey] = model_e(self.blender.model, params, self.tg)
            e_t = apply_rtd_effects(self.blender, self.tg, base, effects)
            mass = self.dt * np.cumsum(e_t)
            survival = np.clip(1.0 - mass, 0.0, None)
            tail = mass[-1] - mass
            n_k = (
                int(np.argmax(tail < KERNEL_TAIL_MASS)) + 1
                if tail[-1] < KERNEL_TAIL_MASS
                else self.n
            )
            hit = (e_t, survival, max(n_k, 1))
            if len(self._kernels) > 64:
                self._kernels.clear()
            self._kernels[key] = hit
        return hit

    def _spectrum(self, key: tuple, x: np.ndarray, nfft: int) -> np.ndarray:
        k = (key, nfft)
        hit = self._spectra.get(k)
        if hit is None:
            hit = sp_fft.rfft(x, nfft)
            if len(self._spectra) > 256:
                self._spectra.clear()
            self._spectra[k] = hit
        return hit

    # -- outlet --------------------------------------------------------------------------
    def outlet_mass_flows(
        self, effects: Sequence[Effect] = (), components: Sequence[str] | None = None
    ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Outlet mass flows (kg/s) of ``components`` (default all) and the total, (E * m_i)
        plus the history term."""
        e_t, survival, n_k = self.kernel(effects)
        flows = self.inflows(effects)
        nfft = sp_fft.next_fast_len(self.n + n_k - 1, real=True)
        rtd_key = ("E", _effects_key(effects, ("rtd",)))
        ek = self._spectrum(rtd_key, e_t[:n_k], nfft)
        in_key = _effects_key(effects, ("feeder", "unit"))
        total_spec = 0.0
        total_q0 = 0.0
        specs = {}
        for c, (q, q0) in flows.items():
            specs[c] = self._spectrum(("q", c, in_key), q, nfft)
            total_spec = total_spec + specs[c]
            total_q0 += q0
        want = self.components if components is None else list(components)
        out = {}
        for c in want:
            if c not in flows:
                continue
            y = sp_fft.irfft(specs[c] * ek, nfft)[: self.n] * self.dt
            out[c] = y + flows[c][1] * survival
        total = sp_fft.irfft(total_spec * ek, nfft)[: self.n] * self.dt + total_q0 * survival
        return out, total

    def concentrations(
        self, effects: Sequence[Effect] = (), components: Sequence[str] | None = None
    ) -> dict[str, np.ndarray]:
        """Outlet mass fraction (% w/w) of ``components`` (default all)."""
        outs, total = self.outlet_mass_flows(effects, components)
        with np.errstate(invalid="ignore", divide="ignore"):
            return {c: np.where(total > 0, 100.0 * y / total, np.nan) for c, y in outs.items()}


def _effects_key(effects: Sequence[Effect], stages: tuple[str, ...]) -> tuple:
    """Hashable identity of the effects of ``stages`` (name, target, parameter values)."""
    return tuple((e.name, e.target, tuple(e.vector())) for e in effects if e.stage in stages)


def outlet_concentration(
    inputs: LineInputs,
    blender: BlenderModelConfig,
    effects: Sequence[Effect] = (),
) -> dict[str, np.ndarray]:
    """Outlet mass fraction of every component, % w/w, c_i = 100 (E*m_i)/(E*sum m).

    The convolution runs on ``inputs.t_s`` (rectangle rule, y[n] = dt sum_j u[j] E[n-j], by FFT:
    :class:`OutletModel`). Before t_s[0] the line is at steady state with the first feeder flows
    m_i0 (no tracer): that history adds exactly m_i0 S(t), S[n] = 1 - dt sum_{j<=n} E[j] (the
    fraction of the older material still inside, 1 - F(t)), so the line starts full and no
    warm-up padding is needed.
    """
    return OutletModel(inputs, blender).concentrations(effects)


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
        self.config = rtd_blender_config(self.config)
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
