"""The seed's line (chapter 6.1.2) as a declared :class:`schemas.line.LineConfig`."""

from __future__ import annotations

from typing import Any

from schemas.line import FeederLine, LineConfig, SensorLine, TracerPulse

__all__ = ["seed_line"]


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
    Blender: axial dispersion with delay of Table 6.2 (the default ``BlenderModelConfig``).
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
            FeederLine(
                id="api",
                component="api",
                setpoint_kg_h=api_fraction * total_kg_h,
                liw=dict(api_liw or {}),
            ),
            FeederLine(
                id="excipient",
                component="excipient",
                setpoint_kg_h=(1 - api_fraction) * total_kg_h,
                liw=dict(excipient_liw or {}),
            ),
        ],
        sensor=SensorLine(component="api"),
        tracers=[
            TracerPulse(t_s=float(t), mass_kg=g / 1000.0, component="api")
            for g, t in zip(tracer_g, tracer_times_s)
        ],
    )
