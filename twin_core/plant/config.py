"""Configuration of the declared line model: feeders -> blender RTD -> NIR sensor.

Plain dataclasses (no pydantic) so that the library stays dependency-light; the wire/config
schemas of the services map onto these. Every class validates itself on construction and
raises ``ValueError`` naming the field and the value. ``line_config_from_dict`` /
``line_config_to_dict`` convert to and from plain dicts (the YAML/JSON form).

Units: flows in kg/h, masses in kg, times in s, concentrations in % w/w (declared units at the
edge, as in the rest of the project).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

#: RTD model names accepted by :class:`BlenderSpec` (functions of ``twin_core.rtd.models``)
RTD_MODELS: dict[str, tuple[str, ...]] = {
    "axial_dispersion_open": ("tau_d", "tau", "pe"),
    "axial_dispersion_closed": ("tau_d", "tau", "pe"),
    "tanks_in_series": ("tau_d", "tau", "n"),
    "cstr_pfr": ("tau_pfr", "tau_cstr"),
}


def _check_finite(name: str, value: float) -> None:
    if not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise ValueError(f"{name} must be a finite number, got {value!r}")


def _check_nonneg(name: str, value: float) -> None:
    _check_finite(name, value)
    if value < 0:
        raise ValueError(f"{name} must be >= 0, got {value!r}")


@dataclass
class FeederSpec:
    """One loss-in-weight feeder feeding one component.

    name: unique feeder id (``"api"``); component: the component it feeds; setpoint_kg_h: mass
    flow setpoint; liw: keyword arguments for ``twin_core.feeder.LossInWeightFeeder`` (hopper
    size, refill levels, PID gains, feed-factor curve...). ``setpoint_kg_h`` is passed to it as
    ``setpoint_kg_h`` unless ``liw`` already sets it. ``ideal=True`` replaces the LIW simulator
    by a constant flow at the setpoint (no refills): the declared "perfect feeder".
    """

    name: str
    component: str
    setpoint_kg_h: float
    liw: dict[str, Any] = field(default_factory=dict)
    ideal: bool = False

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("feeder name must be a non-empty string, got ''")
        if not self.component:
            raise ValueError(f"feeder {self.name!r}: component must be non-empty, got ''")
        _check_nonneg(f"feeders[{self.name}].setpoint_kg_h", self.setpoint_kg_h)


@dataclass
class BlenderSpec:
    """The blender as a linear system with impulse response E(t) from ``twin_core.rtd.models``.

    Default: axial dispersion (open-open) with delay, seed Table 6.2 (untruncated 10 g pulse):
    tau_d = 11.92 s, tau = 16.37 s, Pe = 7.67 (mean residence time ~32.5 s).
    """

    model: str = "axial_dispersion_open"
    params: dict[str, float] = field(
        default_factory=lambda: {"tau_d": 11.92, "tau": 16.37, "pe": 7.67}
    )

    def __post_init__(self) -> None:
        if self.model not in RTD_MODELS:
            raise ValueError(
                f"blender.model must be one of {sorted(RTD_MODELS)}, got {self.model!r}"
            )
        needed = RTD_MODELS[self.model]
        missing = [k for k in needed if k not in self.params]
        if missing:
            raise ValueError(f"blender.params missing {missing} for model {self.model!r}")
        extra = [k for k in self.params if k not in needed]
        if extra:
            raise ValueError(f"blender.params has unknown keys {extra} for model {self.model!r}")
        for k, v in self.params.items():
            _check_nonneg(f"blender.params.{k}", v)
        for k in ("tau", "pe", "n", "tau_cstr"):
            if k in self.params and self.params[k] <= 0:
                raise ValueError(f"blender.params.{k} must be > 0, got {self.params[k]!r}")

    @property
    def delay_s(self) -> float:
        """Plug-flow (transport) delay of the model, s."""
        return float(self.params.get("tau_d", self.params.get("tau_pfr", 0.0)))


@dataclass
class NIRNoise:
    """NIR noise of the seed (chapter 6.1.3.2, SEED_NOTES): all in % w/w.

    white_sd: white noise everywhere; pink_sd: 1/f noise (standard deviation over the run);
    proportional_rel: noise standard deviation proportional to the signal (largest near a
    peak); outlier_prob / outlier_sd: probability per sample and size of isolated outliers;
    baseline_offset: constant offset of the calibration. Defaults put the baseline at mean
    -0.05 and standard deviation ~0.122 (seed: -0.03 to -0.074 and 0.125 to 0.132).
    """

    white_sd: float = 0.10
    pink_sd: float = 0.07
    proportional_rel: float = 0.02
    outlier_prob: float = 0.003
    outlier_sd: float = 1.5
    baseline_offset: float = -0.05

    def __post_init__(self) -> None:
        for k in ("white_sd", "pink_sd", "proportional_rel", "outlier_sd"):
            _check_nonneg(f"sensor.noise.{k}", getattr(self, k))
        _check_finite("sensor.noise.baseline_offset", self.baseline_offset)
        if not 0.0 <= self.outlier_prob <= 1.0:
            raise ValueError(
                f"sensor.noise.outlier_prob must be in [0, 1], got {self.outlier_prob!r}"
            )


@dataclass
class SensorSpec:
    """The NIR probe at the blender outlet: measures one component in % w/w every period."""

    component: str
    sample_period_s: float = 1.0
    noise: NIRNoise = field(default_factory=NIRNoise)

    def __post_init__(self) -> None:
        if not self.component:
            raise ValueError("sensor.component must be non-empty, got ''")
        _check_finite("sensor.sample_period_s", self.sample_period_s)
        if self.sample_period_s <= 0:
            raise ValueError(f"sensor.sample_period_s must be > 0, got {self.sample_period_s!r}")
        if isinstance(self.noise, dict):
            self.noise = NIRNoise(**self.noise)


@dataclass
class TracerPulse:
    """A known mass of a component injected at the blender inlet at ``t_s`` over ``duration_s``."""

    t_s: float
    mass_kg: float
    component: str
    duration_s: float = 1.0

    def __post_init__(self) -> None:
        _check_nonneg("tracer.t_s", self.t_s)
        _check_nonneg("tracer.mass_kg", self.mass_kg)
        _check_finite("tracer.duration_s", self.duration_s)
        if self.duration_s <= 0:
            raise ValueError(f"tracer.duration_s must be > 0, got {self.duration_s!r}")


@dataclass
class FlowDisturbance:
    """A known change of one feeder's flow: ``delta_kg_h`` added during [t_s, t_s + duration_s).

    ``duration_s = inf`` is a step. It is an input the twin sees (the feeder reports it).
    """

    feeder: str
    t_s: float
    delta_kg_h: float
    duration_s: float = math.inf

    def __post_init__(self) -> None:
        _check_nonneg("disturbance.t_s", self.t_s)
        _check_finite("disturbance.delta_kg_h", self.delta_kg_h)
        if not self.duration_s > 0:
            raise ValueError(f"disturbance.duration_s must be > 0, got {self.duration_s!r}")


@dataclass
class LineConfig:
    """The declared line: feeders -> blender -> NIR sensor, plus planned tracer pulses."""

    feeders: list[FeederSpec]
    blender: BlenderSpec = field(default_factory=BlenderSpec)
    sensor: SensorSpec | None = None
    tracers: list[TracerPulse] = field(default_factory=list)
    name: str = "line1"

    def __post_init__(self) -> None:
        if not self.feeders:
            raise ValueError("feeders must list at least one feeder, got []")
        names = [f.name for f in self.feeders]
        if len(set(names)) != len(names):
            raise ValueError(f"feeder names must be unique, got {names}")
        if self.sensor is None:
            self.sensor = SensorSpec(component=self.feeders[0].component)
        comps = set(self.components)
        if self.sensor.component not in comps:
            raise ValueError(
                f"sensor.component must be one of {sorted(comps)}, got {self.sensor.component!r}"
            )
        for p in self.tracers:
            if p.component not in comps:
                raise ValueError(
                    f"tracer.component must be one of {sorted(comps)}, got {p.component!r}"
                )

    @property
    def components(self) -> list[str]:
        """Component names in feeder order (unique, first occurrence)."""
        out: list[str] = []
        for f in self.feeders:
            if f.component not in out:
                out.append(f.component)
        return out

    @property
    def total_flow_kg_h(self) -> float:
        return float(sum(f.setpoint_kg_h for f in self.feeders))

    def feeder(self, name: str) -> FeederSpec:
        for f in self.feeders:
            if f.name == name:
                return f
        raise ValueError(f"feeder must be one of {[f.name for f in self.feeders]}, got {name!r}")


def line_config_from_dict(d: dict[str, Any]) -> LineConfig:
    """Build a :class:`LineConfig` from its plain-dict (YAML/JSON) form.

    Keys: ``name``, ``feeders`` (list of FeederSpec fields), ``blender`` ({model, params}),
    ``sensor`` ({component, sample_period_s, noise: {...}}), ``tracers`` (list of
    TracerPulse fields).
    """
    if not isinstance(d, dict):
        raise ValueError(f"line config must be a mapping, got {type(d).__name__}")
    known = {"name", "feeders", "blender", "sensor", "tracers"}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ValueError(f"line config has unknown keys {unknown}")
    feeders = [FeederSpec(**f) for f in d.get("feeders", [])]
    blender = BlenderSpec(**d["blender"]) if d.get("blender") else BlenderSpec()
    sensor = None
    if d.get("sensor"):
        s = dict(d["sensor"])
        s["noise"] = NIRNoise(**s.get("noise", {}))
        sensor = SensorSpec(**s)
    tracers = [TracerPulse(**p) for p in d.get("tracers", [])]
    return LineConfig(
        feeders=feeders,
        blender=blender,
        sensor=sensor,
        tracers=tracers,
        name=d.get("name", "line1"),
    )


def line_config_to_dict(cfg: LineConfig) -> dict[str, Any]:
    """Inverse of :func:`line_config_from_dict` (plain JSON-able dict)."""
    return asdict(cfg)


def seed_line(
    api_fraction: float = 0.10,
    total_kg_h: float = 12.0,
    tracer_g: tuple[float, ...] = (10.0,),
    tracer_times_s: tuple[float, ...] = (120.0,),
    api_liw: dict[str, Any] | None = None,
    excipient_liw: dict[str, Any] | None = None,
) -> LineConfig:
    """The seed's line (chapter 6.1.2): 12 kg/h through a GCM 250 at 100 rpm, NIR at the outlet.

    Two feeders (API and excipient, Avicel PH301) at ``api_fraction`` of ``total_kg_h``; the NIR
    measures the API; tracer pulses of API (seed: 10 / 7.5 / 6 / 5 g) at the given times.
    Blender: axial dispersion with delay of Table 6.2.
    """
    if not 0.0 <= api_fraction <= 1.0:
        raise ValueError(f"api_fraction must be in [0, 1], got {api_fraction!r}")
    if len(tracer_g) != len(tracer_times_s):
        raise ValueError(
            f"tracer_g and tracer_times_s must have equal length, got {len(tracer_g)} "
            f"and {len(tracer_times_s)}"
        )
    return LineConfig(
        feeders=[
            FeederSpec("api", "api", api_fraction * total_kg_h, liw=dict(api_liw or {})),
            FeederSpec(
                "excipient",
                "excipient",
                (1 - api_fraction) * total_kg_h,
                liw=dict(excipient_liw or {}),
            ),
        ],
        blender=BlenderSpec(),
        sensor=SensorSpec(component="api"),
        tracers=[
            TracerPulse(t_s=float(t), mass_kg=g / 1000.0, component="api")
            for g, t in zip(tracer_g, tracer_times_s)
        ],
    )
