"""What-if runs of an exported blender model (``twin compartment simulate``): an inlet signal of
a baseline with an optional step, tracer pulse and flow change, through the model.

The outlet is ``blender_model_predict`` (the whole blender's RTD convolution, Eq. 8-9 of seed
chapter 5, with the flows scaled after a change of throughput or blade speed: the rpm law of the
model when a blade speed is given).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin_core.compartment.blender_model import blender_model_flow_scale, blender_model_predict

__all__ = ["InletScenario", "simulate_blender"]


@dataclass
class InletScenario:
    """The inlet of a what-if run: ``inlet`` baseline; a step to ``step_to`` at ``step_at``; a
    pulse of ``pulse_height`` over ``pulse_width`` s at ``pulse_at``; flows scaled to
    ``scale_to`` (or to the model's scale for blade speed ``rpm_to``) from ``scale_at``."""

    duration_s: float = 3600.0
    dt_s: float = 0.1
    inlet: float = 3.0
    step_at: float | None = None
    step_to: float | None = None
    pulse_at: float | None = None
    pulse_width: float = 1.0
    pulse_height: float = 10.0
    scale_at: float | None = None
    scale_to: float = 1.0
    rpm_to: float | None = None


def simulate_blender(bm, s: InletScenario) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, inlet, outlet) of the scenario through the blender model ``bm``; a bad scenario
    raises ValueError naming the field."""
    if s.dt_s <= 0 or s.duration_s <= s.dt_s:
        raise ValueError(f"need 0 < dt < duration, got dt={s.dt_s}, duration={s.duration_s}")
    t = np.arange(0.0, s.duration_s, s.dt_s)
    u = np.full(t.size, s.inlet)
    if s.step_at is not None:
        if s.step_to is None:
            raise ValueError("step_at needs step_to, got step_to=None")
        u[t >= s.step_at] = s.step_to
    if s.pulse_at is not None:
        u[(t >= s.pulse_at) & (t < s.pulse_at + s.pulse_width)] += s.pulse_height
    scale = None
    if s.scale_at is not None:
        to = s.scale_to
        if s.rpm_to is not None:
            to = float(blender_model_flow_scale(bm, np.array([s.rpm_to]))[0])
        if to < 0:
            raise ValueError(f"scale_to must be >= 0, got {to}")
        scale = np.where(t >= s.scale_at, to, 1.0)
    return t, u, blender_model_predict(bm, t, u, flow_scale=scale)
