"""The online close-loop without the bus: windows, adoption, and the blender's adopted model.

References: the plant simulator's ground truth (the injected effect and its size), and the batch
line model (``twin_core.plant.model.outlet_concentration``, mass-flow-weighted convolution
c_i = 100 (E*m_i)/(E*sum m)) as the peer of the blender's streaming prediction.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas.line import LineSpec
from services.blender import BlenderPredictor
from twin_core.closeloop.online import OnlineCloseLoop, Window
from twin_core.plant import simulate_line
from twin_core.plant.config import FlowDisturbance
from twin_core.plant.model import LineModel

CONFIG = Path(__file__).resolve().parent.parent / "services" / "configs" / "line1.yaml"
DIST = [
    FlowDisturbance("api", 300.0, 0.6, 30.0),
    FlowDisturbance("api", 750.0, -0.6, 40.0),
    FlowDisturbance("api", 1200.0, -0.6, 40.0),
]


def _stream(ocl: OnlineCloseLoop, run) -> list:
    found = []
    for i, t in enumerate(run.t_s):
        for name, rec in run.feeders.items():
            ocl.add_flow(name, t, rec.flow_kg_h[i], bool(rec.refilling[i]))
        ocl.add_measured(t, run.measured_pct_w_w[i])
        for w in ocl.due():
            found.append((w, ocl.check(w)))
    return found


def test_windows_find_the_hidden_dead_zone_once_and_then_hold():
    """Ground truth: a dead zone (30 % of the flow through a 40 s stagnant CSTR) injected by the
    plant simulator, absent from the declared model."""
    cfg = LineSpec.from_file(CONFIG).plant_config()
    truth = {"name": "dead_zone", "params": {"fraction": 0.3, "tau_s": 40.0}}
    run = simulate_line(cfg, 1500.0, seed=4, effects=[truth], disturbances=DIST)
    ocl = OnlineCloseLoop(cfg, 1.0, interval_s=300.0, window_s=1200.0, min_window_s=600.0)
    found = _stream(ocl, run)
    assert [w for w, _ in found] == [
        Window(0.0, 600.0),
        Window(0.0, 900.0),
        Window(0.0, 1200.0),
        Window(300.0, 1500.0),
    ]
    first = found[0][1]
    assert first.status == "explained"
    (eff,) = first.effects
    vals = {p["name"]: p["value"] for p in eff["params"]}
    assert eff["name"] == "dead_zone"
    assert vals["fraction"] == pytest.approx(0.3, abs=0.06)
    assert vals["tau_s"] == pytest.approx(40.0, rel=0.3)
    assert first.errors["after"]["heldout"]["rmse"] < first.errors["before"]["heldout"]["rmse"]
    assert [e.name for e in ocl.model_.effects] == ["dead_zone"]
    assert all(f.status == "consistent" for _, f in found[1:]), [f.status for _, f in found]


def test_no_effect_no_claim_and_bad_input_is_named():
    cfg = LineSpec.from_file(CONFIG).plant_config()
    run = simulate_line(cfg, 1200.0, seed=8, disturbances=DIST)
    ocl = OnlineCloseLoop(cfg, 1.0)
    found = _stream(ocl, run)
    assert len(found) == 3 and all(f.status == "consistent" for _, f in found)
    assert ocl.model_.effects == []
    with pytest.raises(ValueError, match="feeder must be one of"):
        ocl.add_flow("nope", 0.0, 1.0)
    with pytest.raises(ValueError, match="flow_kg_h"):
        ocl.add_flow("api", 0.0, float("nan"))
    with pytest.raises(ValueError, match="c_pct_w_w"):
        ocl.add_measured(0.0, float("inf"))
    with pytest.raises(ValueError, match="skip_s < min_window_s"):
        OnlineCloseLoop(cfg, 1.0, skip_s=700.0, min_window_s=600.0)


@pytest.mark.parametrize(
    "effects",
    [
        [{"name": "dead_zone", "params": {"fraction": 0.3, "tau_s": 40.0}}],
        [
            {"name": "extra_delay", "params": {"delay_s": 7.5}},
            {"name": "back_mixing", "params": {"pe_factor": 0.5}},
        ],
        [{"name": "refill_surge", "target": "api", "params": {"amplitude": 0.4, "tau_s": 30.0}}],
    ],
    ids=["dead_zone", "delay+backmixing", "refill_surge"],
)
def test_blender_streaming_prediction_with_adopted_effects_equals_the_batch_model(effects):
    """Peer: the batch line model with the same effects on the same reported flows (refills
    included), after the streaming kernel's start-up (the batch model starts from steady state
    analytically)."""
    data = LineSpec.from_file(CONFIG).model_dump()
    data["feeders"][0]["liw"] = dict(initial_mass_kg=0.6, refill_low_kg=0.45, refill_high_kg=0.65)
    spec = LineSpec.model_validate(data)
    cfg = spec.plant_config()
    run = simulate_line(cfg, 900.0, seed=2, disturbances=DIST[:2])
    assert any(r.refilling.any() for r in run.feeders.values())
    bp = BlenderPredictor(spec)
    assert bp.set_effects(effects) == []
    out: dict[float, float] = {}
    for i, t in enumerate(run.t_s):
        for name, rec in run.feeders.items():
            for tt, c in bp.push(name, float(t), rec.flow_kg_h[i], bool(rec.refilling[i])):
                out[tt] = c["api"]
    batch = LineModel(cfg, effects).outlet(run.inputs())["api"]
    stream = np.array([out[float(t)] for t in run.t_s])
    late = run.t_s >= spec.blender.kernel_s
    np.testing.assert_allclose(stream[late], batch[late], atol=1e-6)


def test_blender_refuses_drifts_and_sensor_effects():
    spec = LineSpec.from_file(CONFIG)
    bp = BlenderPredictor(spec)
    left = bp.set_effects(
        [
            {"name": "feed_factor_drift", "target": "api", "params": {"rate_per_h": 0.2}},
            {"name": "sensor_offset", "params": {"offset": 0.3}},
            {"name": "bypass", "params": {"fraction": 0.1}},
        ]
    )
    assert sorted(e.name for e in left) == ["feed_factor_drift", "sensor_offset"]
    assert [e.name for e in bp.effects] == ["bypass"]


def test_blender_flow_memory_keeps_the_last_samples_in_order_across_wraps():
    """The feeder-effect memory (doubled buffer) against a plain list of the same samples."""
    from services.blender import _FlowMemory

    mem = _FlowMemory(7)
    ref = []
    for i in range(40):
        mem.append(float(i), 10.0 + i, i % 5 == 0)
        ref.append((float(i), 10.0 + i, i % 5 == 0))
        t, q, r = mem.window()
        last = ref[-7:]
        assert t.tolist() == [x[0] for x in last]
        assert q.tolist() == [x[1] for x in last]
        assert r.tolist() == [x[2] for x in last]
