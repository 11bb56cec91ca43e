"""Standard excitation scenario and effect magnitudes for validating the close-loop.

An effect must be excited to be identifiable: dead zone / bypass / back-mixing / delay / lag
show in tracer pulse responses, a refill surge needs a refill, a feed-factor drift is told from
a sensor drift only when the feeder's flow level changes. The scenario therefore has, in both
the training and the held-out window of the default 60/40 time split: tracer pulses of API
(seed sizes 10 / 7.5 / 6 / 5 g), an API hopper refill, and a known API flow dip.
"""

from __future__ import annotations

from typing import Any

from schemas.line import LineConfig
from twin_core.plant.seed import seed_line
from twin_core.plant.simulate import FlowDisturbance

#: magnitudes per effect used by the tests and the confusion benchmark ("small" .. "large")
EFFECT_MAGNITUDES: dict[str, list[dict[str, float]]] = {
    "dead_zone": [{"fraction": 0.15, "tau_s": 60.0}, {"fraction": 0.3, "tau_s": 40.0}],
    "bypass": [{"fraction": 0.08}, {"fraction": 0.15}],
    "extra_delay": [{"delay_s": 4.0}, {"delay_s": 10.0}],
    "back_mixing": [{"pe_factor": 0.5}, {"pe_factor": 2.5}],
    "sensor_offset": [{"offset": 0.25}, {"offset": -0.6}],
    "sensor_drift": [{"rate_per_h": 1.0}, {"rate_per_h": -2.5}],
    "sensor_gain": [{"gain": 1.06}, {"gain": 0.85}],
    "sensor_lag": [{"tau_s": 4.0}, {"tau_s": 10.0}],
    "refill_surge": [{"amplitude": 0.3, "tau_s": 30.0}, {"amplitude": 0.6, "tau_s": 60.0}],
    "feed_factor_drift": [{"rate_per_h": 0.15}, {"rate_per_h": -0.3}],
    "feed_bias": [{"bias": 0.06}, {"bias": -0.12}],
    "component_loss": [{"fraction": 0.06}, {"fraction": 0.15}],
    "holdup": [{"mass_g": 40.0, "tau_s": 300.0}, {"mass_g": 50.0, "tau_s": 600.0}],
}

#: feeder (feeder-stage effects) or component (unit-stage effects) an effect acts on
EFFECT_TARGETS: dict[str, str] = {
    "refill_surge": "api",
    "feed_factor_drift": "api",
    "feed_bias": "api",
    "component_loss": "api",
    "holdup": "api",
}


def standard_scenario(duration_s: float = 1500.0) -> tuple[LineConfig, list[FlowDisturbance]]:
    """The seed line (12 kg/h, 10 % API, Table 6.2 blender, seed NIR noise) with API tracer
    pulses every 300 s, API hopper refills at ~450 s and ~1050 s and an API flow dip of
    -0.4 kg/h for 120 s at 20 % and 80 % of the run."""
    sizes = (10.0, 7.5, 6.0, 5.0)
    times = [100.0 + 300.0 * i for i in range(int((duration_s - 150.0) // 300.0) + 1)]
    cfg = seed_line(
        tracer_g=tuple(sizes[i % len(sizes)] for i in range(len(times))),
        tracer_times_s=tuple(times),
        api_liw=dict(initial_mass_kg=0.6, refill_low_kg=0.45, refill_high_kg=0.65),
        excipient_liw=dict(initial_mass_kg=8.0, refill_low_kg=1.5, refill_high_kg=8.0),
    )
    dist = [
        FlowDisturbance("api", round(0.2 * duration_s), -0.4, 120.0),
        FlowDisturbance("api", round(0.8 * duration_s), -0.4, 120.0),
    ]
    return cfg, dist


def effect_spec(name: str, level: int) -> dict[str, Any]:
    """Dict form of the scenario's effect ``name`` at magnitude index ``level``."""
    if name not in EFFECT_MAGNITUDES:
        raise ValueError(f"effect name must be one of {sorted(EFFECT_MAGNITUDES)}, got {name!r}")
    mags = EFFECT_MAGNITUDES[name]
    if not 0 <= level < len(mags):
        raise ValueError(f"level must be in [0, {len(mags) - 1}], got {level}")
    return {"name": name, "target": EFFECT_TARGETS.get(name), "params": dict(mags[level])}


__all__ = ["EFFECT_MAGNITUDES", "EFFECT_TARGETS", "effect_spec", "standard_scenario"]
