"""Declared line model and plant simulator: LIW feeders -> blender RTD -> NIR probe.

The line is configured by ``schemas.line.LineConfig`` (feeders, blender RTD model, sensor and its
noise, tracers: the one line / feeder / blender / sensor configuration model, a
``schemas.line.LineSpec`` included); this package computes with it:

- ``seed``: :func:`seed_line`, the seed's line;
- ``model``: :class:`LineModel`, the declared model predicting the probe reading from the
  feeders' reported flows (mass-flow-weighted RTD convolution);
- ``effects``: registry of candidate effects (structural additions to the model);
- ``nir``: the seed's NIR noise (white, pink, proportional, outliers, baseline offset; the pink
  part is ``twin_core.rtd.noise.pink_noise``);
- ``simulate``: :func:`simulate_line` producing a :class:`LineRun` (its events are the wire
  contract's ``schemas.messages.Event``, the one event type).
"""

from twin_core.plant.effects import EFFECTS, Effect, ParamSpec, make_effect, register
from twin_core.plant.model import (
    LineInputs,
    LineModel,
    inlet_component_flows,
    outlet_concentration,
    rtd_kernel,
    sensor_signal,
)
from twin_core.plant.nir import add_nir_noise
from twin_core.plant.seed import seed_line
from twin_core.plant.simulate import FeederRecord, FlowDisturbance, LineRun, simulate_line

__all__ = [
    "EFFECTS",
    "Effect",
    "FeederRecord",
    "FlowDisturbance",
    "LineInputs",
    "LineModel",
    "LineRun",
    "ParamSpec",
    "add_nir_noise",
    "inlet_component_flows",
    "make_effect",
    "outlet_concentration",
    "register",
    "rtd_kernel",
    "seed_line",
    "sensor_signal",
    "simulate_line",
]
