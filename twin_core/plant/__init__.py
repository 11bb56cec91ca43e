"""Declared line model and plant simulator: LIW feeders -> blender RTD -> NIR probe.

- ``config``: :class:`LineConfig` (feeders, blender RTD model, sensor and its noise, tracers);
- ``model``: :class:`LineModel`, the declared model predicting the probe reading from the
  feeders' reported flows (mass-flow-weighted RTD convolution);
- ``effects``: registry of candidate effects (structural additions to the model);
- ``nir``: the seed's NIR noise (white, pink, proportional, outliers, baseline offset);
- ``simulate``: :func:`simulate_line` producing a :class:`LineRun`.
"""

from twin_core.plant.config import (
    BlenderSpec,
    FeederSpec,
    FlowDisturbance,
    LineConfig,
    NIRNoise,
    SensorSpec,
    TracerPulse,
    line_config_from_dict,
    line_config_to_dict,
    seed_line,
)
from twin_core.plant.effects import EFFECTS, Effect, ParamSpec, make_effect, register
from twin_core.plant.model import (
    LineInputs,
    LineModel,
    inlet_component_flows,
    outlet_concentration,
    rtd_kernel,
    sensor_signal,
)
from twin_core.plant.nir import add_nir_noise, pink_noise
from twin_core.plant.simulate import Event, FeederRecord, LineRun, simulate_line

__all__ = [
    "EFFECTS",
    "BlenderSpec",
    "Effect",
    "Event",
    "FeederRecord",
    "FeederSpec",
    "FlowDisturbance",
    "LineConfig",
    "LineInputs",
    "LineModel",
    "LineRun",
    "NIRNoise",
    "ParamSpec",
    "SensorSpec",
    "TracerPulse",
    "add_nir_noise",
    "inlet_component_flows",
    "line_config_from_dict",
    "line_config_to_dict",
    "make_effect",
    "outlet_concentration",
    "pink_noise",
    "register",
    "rtd_kernel",
    "seed_line",
    "sensor_signal",
    "simulate_line",
]
