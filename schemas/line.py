"""Line configuration of the live twin: one YAML/JSON file for ``twin up`` and the services.

It declares the line (feeders, blender model, NIR sensor: the same fields as
``twin_core.plant.LineConfig``, which :meth:`LineSpec.plant_config` builds), the specification
(target and limits per component), the OOS settings (debounce, deadband, inlet detection,
lot-boundary quantiles), the bus (``schemas.bus_config.BusConfig``: endpoints and security) and
which services ``twin up`` starts. Example: ``services/configs/line1.yaml``.

Every field is validated; a bad value raises ``pydantic.ValidationError`` naming the field.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, model_validator

from schemas.base import Finite, Ident, NonNegative, Positive, StrictModel
from schemas.bus_config import BusConfig

__all__ = [
    "BlenderModelConfig",
    "CloseLoopSettings",
    "FeederLine",
    "LineSpec",
    "OosSettings",
    "RtdSettings",
    "SensorLine",
    "SpecLimits",
    "SERVICE_NAMES",
]

#: the services ``twin up`` knows how to start
SERVICE_NAMES = ("plant", "feeder", "blender", "rtd", "oos", "recorder", "dem", "closeloop")


class FeederLine(StrictModel):
    """One loss-in-weight feeder: id (key segment), component fed, set point, LIW options."""

    id: Ident
    component: Ident
    setpoint_kg_h: Positive
    liw: dict[str, Any] = Field(
        default_factory=dict, description="keyword arguments of twin_core.feeder.LossInWeightFeeder"
    )
    ideal: bool = Field(False, description="constant flow at the set point (no LIW dynamics)")


class BlenderModelConfig(StrictModel):
    """Blender model used for prediction.

    ``kind: rtd``: an RTD model of ``twin_core.rtd.models`` with its parameters (SI);
    ``kind: compartment``: a compartment-network export (``schemas.blender_model.BlenderModel``
    JSON file) whose impulse response is used. ``kernel_s``: length of E(t) kept for the
    streaming convolution; ``adopt_rtd_estimates``: replace E(t) by the rtd service's fits;
    ``adopt_findings``: add the effects the closeloop service finds (``twin/<line>/closeloop/finding``)
    to the prediction model (the time-invariant blender and feeder effects).
    """

    kind: Literal["rtd", "compartment"] = "rtd"
    model: Ident = "axial_dispersion_open"
    params: dict[Ident, Finite] = Field(
        default_factory=lambda: {"tau_d": 11.92, "tau": 16.37, "pe": 7.67}
    )
    export_path: str | None = None
    kernel_s: Positive = 300.0
    adopt_rtd_estimates: bool = False
    adopt_findings: bool = True

    @model_validator(mode="after")
    def _export_for_compartment(self) -> BlenderModelConfig:
        if self.kind == "compartment" and not self.export_path:
            raise ValueError(f"export_path must be given for kind 'compartment', got {None!r}")
        return self


class SensorLine(StrictModel):
    """The NIR probe at the blender outlet (noise fields as ``twin_core.plant.NIRNoise``)."""

    id: Ident = "nir1"
    component: Ident
    sample_period_s: Positive = 1.0
    noise: dict[str, Finite] = Field(default_factory=dict)


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
    diverter's decisions back before it decides on the streams present.
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
    """

    interval_s: Positive = 300.0
    window_s: Positive = 1200.0
    min_window_s: Positive = 600.0
    skip_s: NonNegative = 150.0
    candidates: list[Ident] = Field(default_factory=list)
    max_effects: int = Field(1, ge=1, le=2)

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


class LineSpec(StrictModel):
    """The whole live-twin configuration (see the module docstring)."""

    name: Ident = "line1"
    dt_s: Positive = Field(1.0, description="tick of the inlet and prediction streams, s")
    feeders: list[FeederLine] = Field(min_length=1)
    blender: BlenderModelConfig = Field(default_factory=BlenderModelConfig)
    sensor: SensorLine
    spec: list[SpecLimits] = Field(min_length=1)
    oos: OosSettings = Field(default_factory=OosSettings)
    rtd: RtdSettings = Field(default_factory=RtdSettings)
    closeloop: CloseLoopSettings = Field(default_factory=CloseLoopSettings)
    bus: BusConfig = Field(
        default_factory=lambda: BusConfig(mode="router", listen=["tcp/127.0.0.1:7447"], connect=[])
    )
    services: list[
        Literal["plant", "feeder", "blender", "rtd", "oos", "recorder", "dem", "closeloop"]
    ] = Field(default_factory=lambda: ["feeder", "blender", "rtd", "oos"])
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

    @model_validator(mode="after")
    def _consistent(self) -> LineSpec:
        ids = [f.id for f in self.feeders]
        if len(set(ids)) != len(ids):
            raise ValueError(f"feeders ids must be unique, got {ids}")
        comps = {f.component for f in self.feeders}
        if self.sensor.component not in comps:
            raise ValueError(
                f"sensor.component must be one of {sorted(comps)}, got {self.sensor.component!r}"
            )
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
    @property
    def components(self) -> dict[str, str]:
        """feeder id -> component."""
        return {f.id: f.component for f in self.feeders}

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

    def plant_config(self) -> Any:
        """The equivalent ``twin_core.plant.LineConfig`` (declared line model)."""
        from twin_core.plant import line_config_from_dict

        if self.blender.kind != "rtd":
            raise ValueError(f"plant_config needs blender.kind 'rtd', got {self.blender.kind!r}")
        return line_config_from_dict(
            {
                "name": self.name,
                "feeders": [
                    {
                        "name": f.id,
                        "component": f.component,
                        "setpoint_kg_h": f.setpoint_kg_h,
                        "liw": dict(f.liw),
                        "ideal": f.ideal,
                    }
                    for f in self.feeders
                ],
                "blender": {"model": self.blender.model, "params": dict(self.blender.params)},
                "sensor": {
                    "component": self.sensor.component,
                    "sample_period_s": self.sensor.sample_period_s,
                    "noise": dict(self.sensor.noise),
                },
            }
        )

    def to_file(self, path: str | Path) -> None:
        """Write as JSON (``.json``) or YAML (any other suffix)."""
        data = self.model_dump(mode="json")
        if str(path).endswith(".json"):
            Path(path).write_text(json.dumps(data, indent=2))
        else:
            import yaml

            Path(path).write_text(yaml.safe_dump(data, sort_keys=False))
