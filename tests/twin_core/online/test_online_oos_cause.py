"""The diverter's alert names what went in at the inlet: a tracer pulse is a tracer pulse (its
mass and injection time), a feeder disturbance an inlet disturbance of the feeder flows."""

from __future__ import annotations

from pathlib import Path

from schemas import keys
from schemas.line import LineSpec, TracerPulse
from schemas.messages import Event, FeederFlow
from twin_core.online.oos import OosCore
from twin_core.plant import simulate_line
from twin_core.plant.messages import run_messages, simulate_messages

CONFIG = Path(__file__).resolve().parents[3] / "services" / "configs" / "line1.yaml"


def _spec() -> LineSpec:
    data = LineSpec.from_file(CONFIG).model_dump()
    data["services"] = ["oos"]
    return LineSpec.model_validate(data)


def _alerts(spec: LineSpec, msgs) -> list:
    core = OosCore(spec)
    outs = []
    for k, m in msgs:
        if isinstance(m, FeederFlow):
            outs += core.flow(keys.parse_key(k).id, m.t, m.mass_flow_kg_h)
        elif isinstance(m, Event) and m.kind == "tracer_pulse":
            core.tracer_pulse(m.component, m.t, m.mass_kg, m.duration_s)
    outs += core.end_of_stream()
    return [o for o in outs if o.kind == "alert"]


def test_a_tracer_pulse_alert_is_named_a_tracer_pulse():
    spec = _spec()
    cfg = spec.model_copy(deep=True)
    cfg.tracers.append(TracerPulse(t_s=300.0, mass_kg=0.010, component="api"))
    [alert] = _alerts(spec, run_messages(simulate_line(cfg, 500.0, dt_s=1.0, seed=9), spec))
    assert alert.cause.startswith("tracer pulse of api (10 g injected at 300.0 s"), alert.cause
    assert "inlet disturbance" not in alert.cause


def test_a_feeder_disturbance_alert_is_named_an_inlet_disturbance():
    spec = _spec()
    _, msgs = simulate_messages(
        spec,
        400.0,
        seed=21,
        disturbances=[{"feeder": "api", "t_s": 200.0, "delta_kg_h": 0.6, "duration_s": 30.0}],
    )
    [alert] = _alerts(spec, msgs)
    assert alert.cause.startswith("inlet disturbance of api (feeder flows) from 200.0 s")
    assert "tracer" not in alert.cause
