"""The line configuration: one pydantic model for the line, its feeders, blender and sensor.

- :class:`LineConfig` is the declared line: feeders (:class:`FeederLine`, each with the
  overrides of its loss-in-weight simulator, ``schemas.feeder.FeederConfig``), the blender model
  (:class:`BlenderModelConfig`: an RTD model of ``twin_core.rtd.models`` or a compartment
  export), the NIR sensor and its noise (:class:`SensorLine`, :class:`NIRNoise`) and planned
  tracer pulses (:class:`TracerPulse`). The plant simulator, the declared line model and the
  close-loop (``twin_core.plant``, ``twin_core.closeloop``) take it as it is.
- :class:`LineSpec` is the live twin's configuration file: a :class:`LineConfig` (it *is* one)
  plus the specification (target and limits per component), the OOS, RTD and close-loop
  settings, the bus (``schemas.bus_config.BusConfig``: endpoints and security) and which
  services ``twin up`` starts. Example: ``services/configs/line1.yaml``. It is the one file
  format of a line (``twin up``, ``twin close-loop --config``).

Every field is validated; a bad value raises ``pydantic.ValidationError`` naming the field
(:func:`schemas.base.validation_summary` puts it on one line).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal, get_args

from pydantic import Field, model_validator

from schemas.base import Finite, Fraction, Ident, NonNegative, Positive, StrictModel
from schemas.bus_config import BusConfig
from schemas.feeder import FeederConfig

__all__ = [
    "RTD_MODELS",
    "BlenderModelConfig",
    "CloseLoopSettings",
    "FeederLine",
    "LineConfig",
    "LineSpec",
    "NIRNoise",
    "OosSettings",
    "RtdSettings",
    "SensorLine",
    "SpecLimits",
    "TracerPulse",
    "TrackingSettings",
    "BatchSettings",
    "SERVICE_NAMES",
]

#: a service ``twin up`` knows how to start
ServiceName = Literal[
    "plant",
    "feeder",
    "blender",
    "rtd",
    "oos",
    "recorder",
    "dem",
    "closeloop",
    "bridge",
    "trace",
]
SERVICE_NAMES: tuple[str, ...] = get_args(ServiceName)

#: RTD models a declared blender may use (functions of ``twin_core.rtd.models``) and the names of
#: their parameters, in call order
RTD_MODELS: dict[str, tuple[str, ...]] = {
    "axial_dispersion_open": ("tau_d", "tau", "pe"),
    "axial_dispersion_closed": ("tau_d", "tau", "pe"),
    "tanks_in_series": ("tau_d", "tau", "n"),
    "cstr_pfr": ("tau_pfr", "tau_cstr"),
}

#: parameters of :data:`RTD_MODELS` that must be > 0 (the others >= 0)
_POSITIVE_RTD_PARAMS = ("tau", "pe", "n", "tau_cstr")


class FeederLine(StrictModel):
    """One loss-in-weight feeder of the line, feeding one component.

    ``id``: unique feeder id (key segment); ``setpoint_kg_h``: mass-flow set point; ``liw``:
    field overrides of its loss-in-weight simulator (``schemas.feeder.FeederConfig``: hopper,
    refill levels, PID gains, feed-factor curve...), whose set point is the feeder's unless
    ``liw`` sets it (:meth:`liw_config`); ``ideal``: a constant flow at the set point instead
    (no LIW dynamics, no refills), the declared "perfect feeder".
    """

    id: Ident
    component: Ident
    setpoint_kg_h: NonNegative
    liw: dict[str, Any] = Field(
        default_factory=dict, description="field overrides of schemas.feeder.FeederConfig"
    )
    ideal: bool = Field(False, description="constant flow at the set point (no LIW dynamics)")
    initial_lot: Ident | None = Field(
        None,
        description="raw-material lot in the hopper at the start (None: '<id>-L0000'); each "
        "refill event's lot_id names the next (twin_core.tracking)",
    )

    @model_validator(mode="after")
    def _liw_fields_known(self) -> FeederLine:
        unknown = sorted(set(self.liw) - set(FeederConfig.model_fields))
        if unknown:
            raise ValueError(
                f"liw must name fields of schemas.feeder.FeederConfig, got unknown {unknown}"
            )
        return self

    def liw_config(self) -> FeederConfig:
        """The configuration of this feeder's loss-in-weight simulator (validated here: a bad
        value raises naming the field)."""
        return FeederConfig(**{"name": self.id, "setpoint_kg_h": self.setpoint_kg_h, **self.liw})


class HoldupConfig(StrictModel):
    """The compartment blender's holdup at a basis point and how it follows the operating point
    (``twin_core.compartment.operating_point``): M(r, Q) = kg x (kappa(rpm) / kappa(r)) x
    (Q / throughput_kg_h)^beta, kappa the blades' conveying frequency from the DEM runs."""

    kg: Positive = Field(description="flowing holdup of the whole blender at the basis, kg")
    rpm: Positive = Field(description="blade speed of the basis, rev/min")
    throughput_kg_h: Positive = Field(description="throughput of the basis, kg/h")
    beta: Finite = Field(1.0, description="1: holdup proportional to throughput; 0: fixed")


class BlenderModelConfig(StrictModel):
    """The blender as a linear system with impulse response E(t).

    ``kind: rtd``: the RTD model ``model`` of ``twin_core.rtd.models`` (one of
    :data:`RTD_MODELS`) with its parameters (SI); default: axial dispersion (open-open) with
    delay, seed Table 6.2 (untruncated 10 g pulse): tau_d = 11.92 s, tau = 16.37 s, Pe = 7.67
    (mean residence time ~32.5 s). ``kind: compartment``: compartment models of the blender's
    periodic section (``schemas.blender_model.BlenderModel`` JSON: ``export_path`` a file or a
    directory of them, one per blade speed; None: the shipped models built from the seed-size
    DEM runs, ``twin_core/compartment/data``) at the operating point: ``blade_speed_rpm`` until
    the plant reports one (``BlenderDrive``), the feeders' set points as throughput, ``holdup``
    (None: the DEM runs' own time scale); the rule is
    ``twin_core.compartment.operating_point``. A blade speed outside the table's range (by more
    than 5 %) makes the blender request a DEM run of the section there from the dem service
    (when it runs), with the packaged scene ``dem_preset`` (``twin_core/scenes/configs``; None:
    no request); the model built from it joins the table when it is published. The declared line model (close-loop, plant
    simulator) uses its axial-dispersion equivalent (fitted to its E(t)). ``kernel_s``: length of E(t) kept for the streaming convolution;
    ``adopt_rtd_estimates``: replace E(t) by the rtd service's fits; ``adopt_findings``: add the
    effects the closeloop service finds (``twin/<line>/closeloop/finding``) to the prediction
    model (the time-invariant blender and feeder effects). ``adoption_delay_s``: plant seconds
    after the end of its data from which an RTD estimate or a finding is applied (its
    ``applies_from_s``): the blender and the diverter wait, if need be, until the rtd and closeloop
    services have got that far (``AdoptionProgress``), so that the model at each plant time does
    not depend on machine load or restarts; larger: less waiting, later adoption.
    ``adoption_wait_s``: wall seconds a producer that reports no progress (down) may hold the
    predictions and decisions back; then they go on without it (counted in
    ``adoption_bypassed``; an update that comes after its plant time is counted in
    ``adopted_late``).
    """

    kind: Literal["rtd", "compartment"] = "rtd"
    model: Ident = "axial_dispersion_open"
    params: dict[Ident, Finite] = Field(
        default_factory=lambda: {"tau_d": 11.92, "tau": 16.37, "pe": 7.67}
    )
    export_path: str | None = None
    blade_speed_rpm: Positive = 100.0
    holdup: HoldupConfig | None = None
    dem_preset: Ident | None = "blender_small"
    kernel_s: Positive = 300.0
    adopt_rtd_estimates: bool = False
    adopt_findings: bool = True
    adoption_delay_s: NonNegative = 60.0
    adoption_wait_s: Positive = 60.0

    @model_validator(mode="after")
    def _model_complete(self) -> BlenderModelConfig:
        if self.kind == "compartment":
            return self
        if self.model not in RTD_MODELS:
            raise ValueError(f"model must be one of {sorted(RTD_MODELS)}, got {self.model!r}")
        needed = RTD_MODELS[self.model]
        missing = [k for k in needed if k not in self.params]
        if missing:
            raise ValueError(f"params missing {missing} for model {self.model!r}")
        extra = [k for k in self.params if k not in needed]
        if extra:
            raise ValueError(f"params has unknown keys {extra} for model {self.model!r}")
        for k, v in self.params.items():
            if v < 0 or (k in _POSITIVE_RTD_PARAMS and v == 0):
                bound = "> 0" if k in _POSITIVE_RTD_PARAMS else ">= 0"
                raise ValueError(f"params.{k} must be {bound}, got {v!r}")
        return self

    @property
    def delay_s(self) -> float:
        """Plug-flow (transport) delay of the RTD model, s."""
        return float(self.params.get("tau_d", self.params.get("tau_pfr", 0.0)))


class NIRNoise(StrictModel):
    """NIR noise of the seed (chapter 6.1.3.2, docs/seed.md): all in % w/w.

    white_sd: white noise everywhere; pink_sd: 1/f noise (standard deviation over the run);
    proportional_rel: noise standard deviation proportional to the signal (largest near a
    peak); outlier_prob / outlier_sd: probability per sample and size of isolated outliers;
    baseline_offset: constant offset of the calibration. Defaults put the baseline at mean
    -0.05 and standard deviation ~0.122 (seed: -0.03 to -0.074 and 0.125 to 0.132).
    """

    white_sd: NonNegative = 0.10
    pink_sd: NonNegative = 0.07
    proportional_rel: NonNegative = 0.02
    outlier_prob: Fraction = 0.003
    outlier_sd: NonNegative = 1.5
    baseline_offset: Finite = -0.05


class SensorLine(StrictModel):
    """The NIR probe at the blender outlet: measures one component in % w/w every period."""

    id: Ident = "nir1"
    component: Ident
    sample_period_s: Positive = 1.0
    noise: NIRNoise = Field(default_factory=NIRNoise)


class TracerPulse(StrictModel):
    """A known mass of a component injected at the blender inlet at ``t_s`` over
    ``duration_s``."""

    t_s: NonNegative
    mass_kg: NonNegative
    component: Ident
    duration_s: Positive = 1.0


class LineConfig(StrictModel):
    """The declared line: feeders -> blender -> NIR sensor, plus planned tracer pulses.

    ``tracers`` are injected by the plant simulator; the live services take the pulses from the
    ``tracer_pulse`` events instead.
    """

    name: Ident = "line1"
    feeders: list[FeederLine] = Field(min_length=1)
    blender: BlenderModelConfig = Field(default_factory=BlenderModelConfig)
    sensor: SensorLine
    tracers: list[TracerPulse] = Field(default_factory=list)

    @model_validator(mode="after")
    def _line_consistent(self) -> LineConfig:
        ids = [f.id for f in self.feeders]
        if len(set(ids)) != len(ids):
            raise ValueError(f"feeders ids must be unique, got {ids}")
        comps = {f.component for f in self.feeders}
        if self.sensor.component not in comps:
            raise ValueError(
                f"sensor.component must be one of {sorted(comps)}, got {self.sensor.component!r}"
            )
        for p in self.tracers:
            if p.component not in comps:
                raise ValueError(
                    f"tracers component must be one of {sorted(comps)}, got {p.component!r}"
                )
        return self

    @property
    def components(self) -> dict[str, str]:
        """feeder id -> component."""
        return {f.id: f.component for f in self.feeders}

    def line_dict(self) -> dict[str, Any]:
        """JSON-able dict of the declared line: the :class:`LineConfig` fields only (also for a
        :class:`LineSpec`), e.g. for a report or a recording's provenance."""
        return self.model_dump(mode="json", include=set(LineConfig.model_fields))


class SpecLimits(StrictModel):
    """Specification of one component at the outlet, % w/w: lower < target < upper."""

    component: Ident
    target_pct_w_w: Finite
    lower_pct_w_w: Finite
    upper_pct_w_w: Finite

    @model_validator(mode="after")
    def _ordered(self) -> SpecLimits:
        if not self.lower_pct_w_w < self.target_pct_w_w < self.upper_pct_w_w:
            raise ValueError(
                "limits must satisfy lower < target < upper, got "
                f"{self.lower_pct_w_w} / {self.target_pct_w_w} / {self.upper_pct_w_w}"
            )
        return self


class OosSettings(StrictModel):
    """How the OOS diverter decides.

    n_on / n_off: consecutive samples out / back in that open / close an episode;
    hysteresis_pct_w_w: deadband inside the limits; inlet_detect_pct_w_w: inlet composition
    deviation that starts a feeder-disturbance episode (the funnel decides if it matters);
    inlet_n_on / inlet_n_off: debounce of that detector; lot_lower / lot_upper: F(t) quantiles of
    the lot boundaries (seed ch. 6: 0.5 % / 99.5 %); use_funnel: flag feeder disturbances early;
    stall_release_s: how long a stalled input stream (e.g. the blender down) may hold the
    diverter's decisions back before it decides on the streams present. divert_window: the
    outlet window of a flagged feeder disturbance, ``excursion`` (where its predicted outlet
    leaves the specification narrowed by ``divert_guard_pct_w_w`` on each side, widened by
    ``divert_pad_s``; ``twin_core.quality.lots.excursion_window``) or ``lot`` (the lot
    boundaries: every sample holding >= lot_lower of the disturbed material).
    """

    n_on: int = Field(3, ge=1)
    n_off: int = Field(3, ge=1)
    hysteresis_pct_w_w: NonNegative = 0.05
    inlet_detect_pct_w_w: Positive = 0.3
    inlet_n_on: int = Field(1, ge=1)
    inlet_n_off: int = Field(3, ge=1)
    lot_lower: float = Field(0.005, gt=0.0, lt=0.5)
    lot_upper: float = Field(0.995, gt=0.5, lt=1.0)
    use_funnel: bool = True
    stall_release_s: Positive = Field(
        10.0, description="wall seconds a stalled input stream may hold decisions back"
    )
    divert_window: Literal["excursion", "lot"] = "excursion"
    divert_guard_pct_w_w: NonNegative = 0.2
    divert_pad_s: NonNegative = 3.0


class RtdSettings(StrictModel):
    """How the rtd service turns tracer pulses into RTD estimates.

    detect: ``events`` (only announced ``tracer_pulse`` events) or ``auto`` (also pulses found in
    the NIR signal); model: a ``twin_core.rtd.fitting`` model name (``ad_open``, ``tis``, ...);
    denoise: a ``twin_core.rtd.denoise.denoise`` method (``none`` to skip); truncation_k: samples
    below ``k`` baseline standard deviations are zeroed (seed: mu + 3 sigma); hampel_n_sigma:
    outlier threshold of the Hampel identifier.
    """

    detect: Literal["events", "auto"] = "auto"
    model: Ident = "ad_open"
    denoise: Literal["none", "sa", "sa_centred", "sg", "fft", "wavelet", "auto"] = "wavelet"
    truncation_k: NonNegative = 3.0
    hampel_n_sigma: Positive = 4.0
    max_duration_s: Positive = 300.0


class CloseLoopSettings(StrictModel):
    """How the closeloop service checks the model against the measurements while the line runs.

    Every ``interval_s`` of plant time, once ``min_window_s`` of data is in, the declared model
    (plus the effects adopted so far) is checked on the last ``window_s`` (``twin_core.closeloop``:
    residual -> candidate effects -> held-out test); ``skip_s``: start of a window (after the
    start of the run) left out of the fit while the model's steady-state start wears off;
    ``candidates``: effect names tried (empty: all); ``max_effects``: effects added per window.

    Error control over time: ``false_claims_per_day`` is the probability, on a line with no
    missing effect, that the check claims one at least once in a day of operation. Each window
    spends the same share of it: its claim test runs at level
    ``false_claims_per_day * interval_s / 86400`` (a constant-rate alpha-spending rule, Lan &
    DeMets 1983, Biometrika 70:659; by Bonferroni's inequality the daily bound holds whatever
    the dependence of overlapping windows), capped at 0.05
    (``twin_core.closeloop.online.claim_alpha``). ``noise_span_s``: the plant time over which
    the probe's 1/f noise has its declared standard deviation; a window is a segment of that
    process, so its slow wander is noise, not a sensor offset or gain (4 h by default: taken
    as the window itself, a 600 s window of a 1 h record claimed a sensor gain at z 5.3;
    taken as a day, the innovation tests of 30 min records reject their own noise).
    """

    interval_s: Positive = 300.0
    window_s: Positive = 1200.0
    min_window_s: Positive = 600.0
    skip_s: NonNegative = 150.0
    candidates: list[Ident] = Field(default_factory=list)
    max_effects: int = Field(1, ge=1, le=2)
    false_claims_per_day: float = Field(0.05, gt=0.0, lt=1.0)
    noise_span_s: Positive = 14400.0

    @model_validator(mode="after")
    def _windows(self) -> CloseLoopSettings:
        if self.min_window_s > self.window_s:
            raise ValueError(
                f"min_window_s must be <= window_s, got {self.min_window_s} > {self.window_s}"
            )
        if self.skip_s >= self.min_window_s:
            raise ValueError(
                f"skip_s must be < min_window_s, got {self.skip_s} >= {self.min_window_s}"
            )
        return self


class TrackingSettings(StrictModel):
    """How the twin tracks raw-material lots to the blender outlet (``twin_core.tracking``).

    ``hopper``: the loss-in-weight hopper's mixing of a refill with its heel: ``fifo`` (plug
    flow, first in first out), ``mixed`` (stirred heel: the refill mixes at once with what is
    left), ``mixture`` (a share ``mixed_fraction`` of each discharge drawn from the whole
    hopper, the rest oldest first; calibrated on a refill with a tagged lot, see
    docs/traceability.md). ``threshold``: the mass fraction of a lot in the product above which
    a recall lists a product interval (``twin trace --lot``; default 1e-3 = 0.1 % w/w).
    """

    hopper: Literal["fifo", "mixed", "mixture"] = "fifo"
    mixed_fraction: Fraction = 0.5
    threshold: float = Field(1e-3, gt=0.0, lt=1.0)


class BatchSettings(StrictModel):
    """How the line's output is cut into batches (ICH Q13 section 3.1: a batch of a continuous
    process is defined by a quantity of output, a quantity of input or a run time).

    ``by``: ``product_mass`` (kg of product leaving the blender, diverted product included),
    ``api_mass`` (kg of the ``api_component`` fed) or ``run_time`` (s of plant time); ``size``:
    that quantity per batch (kg or s); the last batch of a record may be partial. ``start_s``:
    plant time the first batch starts.
    """

    by: Literal["product_mass", "api_mass", "run_time"] = "product_mass"
    size: Positive
    api_component: Ident = "api"
    start_s: NonNegative = 0.0


class LineSpec(LineConfig):
    """The live twin's configuration: the declared line and how the services run it (see the
    module docstring)."""

    dt_s: Positive = Field(1.0, description="tick of the inlet and prediction streams, s")
    spec: list[SpecLimits] = Field(min_length=1)
    oos: OosSettings = Field(default_factory=OosSettings)
    rtd: RtdSettings = Field(default_factory=RtdSettings)
    closeloop: CloseLoopSettings = Field(default_factory=CloseLoopSettings)
    tracking: TrackingSettings = Field(default_factory=TrackingSettings)
    batch: BatchSettings | None = Field(None, description="batch definition (None: one batch)")
    bus: BusConfig = Field(
        default_factory=lambda: BusConfig(mode="router", listen=["tcp/127.0.0.1:7447"], connect=[])
    )
    services: list[ServiceName] = Field(default_factory=lambda: ["feeder", "blender", "rtd", "oos"])
    feeder_mode: Literal["replay", "simulate"] = Field(
        "replay",
        description="replay: pass recorded load-cell flows through; simulate: run the LIW model",
    )
    inlet_max_lag_s: Positive = Field(
        600.0,
        description="plant time one feeder's flows may run ahead of another's before the missing "
        "value is held (a lost message); large, so that arrival order never changes a result",
    )
    history_samples: int = Field(
        20000, ge=1, description="samples per key cached by publishers for late/restarted peers"
    )
    express: bool = Field(
        False, description="zenoh express (no batching): lower latency, lower throughput"
    )
    state_dir: str = Field(".twin-state", description="where services keep restart state")
    record_path: str | None = Field(None, description="MCAP file written by the recorder")
    opcua_bridge: str | None = Field(
        None,
        description="BRIDGE.yaml of the bridge service (services: bridge; schemas.opcua), "
        "absolute or relative to the working directory of twin up",
    )

    @model_validator(mode="after")
    def _live_consistent(self) -> LineSpec:
        if "bridge" in self.services and not self.opcua_bridge:
            raise ValueError("opcua_bridge must name the BRIDGE.yaml when services has 'bridge'")
        comps = {f.component for f in self.feeders}
        for s in self.spec:
            if s.component not in comps:
                raise ValueError(
                    f"spec component must be one of {sorted(comps)}, got {s.component!r}"
                )
        if self.bus.mode != "router":
            raise ValueError(
                f"bus.mode must be 'router' (twin up hosts the router), got {self.bus.mode!r}"
            )
        if not self.bus.listen:
            raise ValueError("bus.listen must name the router endpoint, got []")
        return self

    # ------------------------------------------------------------------ helpers
    def adoption_sources(self) -> list[str]:
        """The services whose model updates the blender and the diverter adopt and wait for
        (``blender.adoption_delay_s``): ``rtd`` with ``adopt_rtd_estimates``, ``closeloop``
        with ``adopt_findings``, each when it runs."""
        b = self.blender
        wanted = {"rtd": b.adopt_rtd_estimates, "closeloop": b.adopt_findings}
        return [s for s in ("rtd", "closeloop") if wanted[s] and s in self.services]

    def limits(self, component: str) -> SpecLimits | None:
        for s in self.spec:
            if s.component == component:
                return s
        return None

    def client_bus(self) -> BusConfig:
        """The bus configuration of a service: a client of the router (same security).

        Timestamping is on: the publishers' caches (history for restarted peers) need it."""
        data = self.bus.model_dump()
        data.update(
            mode="client",
            listen=[],
            connect=list(self.bus.listen),
            line=self.name,
            timestamping=True,
        )
        return BusConfig.model_validate(data)

    def router_bus(self) -> BusConfig:
        """The router session hosted by ``twin up``."""
        return self.bus.model_copy(update={"line": self.name, "timestamping": True})

    def to_file(self, path: str | Path) -> None:
        """Write as JSON (``.json``) or YAML (any other suffix)."""
        data = self.model_dump(mode="json")
        if str(path).endswith(".json"):
            Path(path).write_text(json.dumps(data, indent=2))
        else:
            import yaml

            Path(path).write_text(yaml.safe_dump(data, sort_keys=False))
