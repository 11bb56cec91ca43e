"""The blender's prediction core, ``twin_core.online.blender`` (no bus, single process)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas.line import BlenderModelConfig, LineSpec, TracerPulse
from twin_core.online.blender import BlenderPredictor, FlowMemory, tick_grid
from twin_core.plant import FlowDisturbance, LineModel, simulate_line
from twin_core.plant.messages import simulate_messages
from twin_core.rtd.models import model_e

CONFIG = Path(__file__).resolve().parents[3] / "services" / "configs" / "line1.yaml"
DIST = [FlowDisturbance("api", 300.0, 0.6, 30.0), FlowDisturbance("api", 750.0, -0.6, 40.0)]


def spec_with(**kw) -> LineSpec:
    """line1 with the seed's Table 6.2 axial-dispersion blender (the declared line model's own
    kernel: the streaming and batch convolutions are compared on the same E(t))."""
    data = LineSpec.from_file(CONFIG).model_dump()
    data["blender"] = BlenderModelConfig().model_dump()
    data.update(kw)
    return LineSpec.model_validate(data)


def stream(bp: BlenderPredictor, run, pulse_late_ticks: int | None = None) -> np.ndarray:
    """Push a run's flows tick by tick; announce its tracer pulses ``pulse_late_ticks`` ticks
    after the flows of their tick (-1: before them, in time; None: not at all). Returns the
    predicted API, % w/w, per tick."""
    got = {}
    pulses = list(run.config.tracers) if pulse_late_ticks is not None else []

    def announce(t: float, late: int) -> None:
        for p in [p for p in pulses if t == p.t_s + late]:
            bp.add_pulse(p.component, p.t_s, p.mass_kg, p.duration_s)

    for i, t in enumerate(run.t_s):
        if pulse_late_ticks == -1:
            announce(t, 0)
        for name, rec in run.feeders.items():
            for tt, conc in bp.push(name, float(t), float(rec.flow_kg_h[i]), rec.refilling[i]):
                got[tt] = conc["api"]
        if pulse_late_ticks is not None and pulse_late_ticks >= 0:
            announce(t, pulse_late_ticks)
    return np.array([got[float(t)] for t in run.t_s])


def test_streaming_prediction_equals_the_declared_line_model():
    """Peer code: twin_core.plant.LineModel (batch convolution of the mass flows) gives the
    same outlet concentration as the streaming blender core, tick by tick."""
    spec = spec_with()
    run, _ = simulate_messages(
        spec,
        900.0,
        seed=2,
        disturbances=[{"feeder": "api", "t_s": 200.0, "delta_kg_h": 0.5, "duration_s": 60.0}],
    )
    ref = LineModel(spec).outlet(run.inputs())["api"]
    np.testing.assert_allclose(stream(BlenderPredictor(spec), run), ref, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("late", [0, 5, 11])
def test_a_tracer_pulse_announced_late_gives_the_declared_model(late):
    """Peer code: LineModel with a 10 g tracer pulse (seed ch. 6). The pulse's event arrives
    after the flows of its tick (up to 11 ticks: less than the plug-flow delay tau_d = 11.92 s
    of seed Table 6.2, where E(t) is exactly 0): the ticks already predicted get their inlet
    corrected, so the prediction equals the declared model's, as if it had come in time."""
    spec = spec_with()
    cfg = spec.model_copy(deep=True)
    cfg.tracers.append(TracerPulse(t_s=300.0, mass_kg=0.010, component="api"))
    run = simulate_line(cfg, 600.0, dt_s=1.0, seed=6)
    ref = LineModel(cfg).outlet(run.inputs())["api"]
    pred = stream(BlenderPredictor(spec), run, pulse_late_ticks=late)
    assert pred.max() > ref[250] + 5.0  # the pulse is there
    np.testing.assert_allclose(pred, ref, rtol=1e-6, atol=1e-6)
    in_time = stream(BlenderPredictor(spec), run, pulse_late_ticks=-1)
    np.testing.assert_array_equal(pred, in_time)


def test_a_tracer_pulse_announced_after_the_delay_corrects_only_later_ticks():
    """Announced 30 ticks late (past the delay, where E(t) carries mass): the ticks predicted
    before the event are not revisited, those after it equal the in-time prediction (the
    corrected inlet is in the convolution's history)."""
    spec = spec_with()
    cfg = spec.model_copy(deep=True)
    cfg.tracers.append(TracerPulse(t_s=300.0, mass_kg=0.010, component="api"))
    run = simulate_line(cfg, 600.0, dt_s=1.0, seed=6)
    pred = stream(BlenderPredictor(spec), run, pulse_late_ticks=30)
    in_time = stream(BlenderPredictor(spec), run, pulse_late_ticks=-1)
    after = run.t_s > 330.0
    np.testing.assert_array_equal(pred[after], in_time[after])
    assert np.max(np.abs(pred[~after] - in_time[~after])) > 1.0


def test_a_tracer_pulse_announced_twice_counts_once():
    spec = spec_with()
    bp = BlenderPredictor(spec)
    assert bp.add_pulse("api", 300.0, 0.010, 1.0)
    assert not bp.add_pulse("api", 300.0, 0.010, 1.0)
    with pytest.raises(ValueError, match="component must be one of"):
        bp.add_pulse("nope", 300.0, 0.010, 1.0)


def test_a_compartment_network_export_matches_its_predict(tmp_path, capsys):
    """Peer code: twin_core.compartment.blender_model_predict (the compartment network of a
    ``schemas.blender_model.BlenderModel``) on the inlet composition; the blender core with ``kind: compartment``
    uses the same export through its impulse response."""
    from schemas.blender_model import BlenderModel
    from services.cli.main import main
    from twin_core.compartment import blender_model_predict

    fields, model = tmp_path / "f.npz", tmp_path / "m.json"
    assert main(["compartment", "synthetic", str(fields), "--shape", "5", "7", "7"]) == 0
    build = ["compartment", "build", str(fields), "--out", str(model)]
    assert main([*build, "--sections", "4", "--surrogate", "2000"]) == 0
    capsys.readouterr()
    spec = spec_with(
        dt_s=0.5, blender={"kind": "compartment", "export_path": str(model), "kernel_s": 200.0}
    )
    bm = BlenderModel.load(model)
    t = np.arange(0, 400, 0.5)
    api = np.where((t >= 100) & (t < 160), 1.8, 1.2)
    exc = 12.0 - api  # constant total: the outlet is the convolution of the composition
    bp = BlenderPredictor(spec)
    got = {}
    for i, ti in enumerate(t):
        for fid, q in (("api", api[i]), ("excipient", exc[i])):
            for tt, conc in bp.push(fid, float(ti), float(q)):
                got[tt] = conc["api"]
    pred = np.array([got[float(x)] for x in t])
    ref = blender_model_predict(bm, t, 100 * api / 12.0)
    assert pred.max() > 14.0  # the step reached the outlet
    np.testing.assert_allclose(pred, ref, atol=0.1)


def test_an_adopted_rtd_estimate_gives_the_declared_model_with_its_parameters():
    """After an RTD estimate (the rtd service's message) the blender predicts with the new E(t):
    once a kernel length has passed, equal to the declared line model with those parameters."""
    spec = spec_with()
    run, _ = simulate_messages(spec, 1200.0, seed=8)
    params = {"tau_d": 8.0, "tau": 25.0, "pe": 12.0}
    bp = BlenderPredictor(spec)
    got = {}
    for i, t in enumerate(run.t_s):
        if t == 400.0:
            bp.adopt_estimate("axial_dispersion_open", params)
        for name, rec in run.feeders.items():
            for tt, conc in bp.push(name, float(t), float(rec.flow_kg_h[i])):
                got[tt] = conc["api"]
    assert bp.kernel.model_name == "axial_dispersion_open"
    np.testing.assert_array_equal(
        bp.e, model_e("axial_dispersion_open", params, tick_grid(spec.dt_s, 300.0))
    )
    cfg = spec.model_copy(deep=True)
    cfg.blender.params = dict(params)
    ref = LineModel(cfg).outlet(run.inputs())["api"]
    pred = np.array([got[float(t)] for t in run.t_s])
    late = run.t_s >= 400 + spec.blender.kernel_s
    np.testing.assert_allclose(pred[late], ref[late], atol=1e-6)
    assert np.max(np.abs(pred[run.t_s < 400] - ref[run.t_s < 400])) > 1e-3  # old model before


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
def test_prediction_with_adopted_effects_equals_the_batch_model(effects):
    """Peer: the batch line model with the same effects on the same reported flows (refills
    included), after the streaming kernel's start-up (the batch model starts from steady state
    analytically)."""
    data = spec_with().model_dump()
    data["feeders"][0]["liw"] = dict(initial_mass_kg=0.6, refill_low_kg=0.45, refill_high_kg=0.65)
    spec = LineSpec.model_validate(data)
    cfg = spec.model_copy(deep=True)
    run = simulate_line(cfg, 900.0, seed=2, disturbances=DIST)
    assert any(r.refilling.any() for r in run.feeders.values())
    bp = BlenderPredictor(spec)
    assert bp.set_effects(effects) == []
    batch = LineModel(cfg, effects).outlet(run.inputs())["api"]
    late = run.t_s >= spec.blender.kernel_s
    np.testing.assert_allclose(stream(bp, run)[late], batch[late], atol=1e-6)


def test_drifts_and_sensor_effects_are_not_adopted():
    bp = BlenderPredictor(spec_with())
    left = bp.set_effects(
        [
            {"name": "feed_factor_drift", "target": "api", "params": {"rate_per_h": 0.2}},
            {"name": "sensor_offset", "params": {"offset": 0.3}},
            {"name": "bypass", "params": {"fraction": 0.1}},
        ]
    )
    assert sorted(e.name for e in left) == ["feed_factor_drift", "sensor_offset"]
    assert [e.name for e in bp.effects] == ["bypass"]


def test_flow_memory_keeps_the_last_samples_in_order_across_wraps():
    """The feeder-effect memory (doubled buffer) against a plain list of the same samples."""
    mem = FlowMemory(7)
    ref = []
    for i in range(40):
        mem.append(float(i), 10.0 + i, i % 5 == 0)
        ref.append((float(i), 10.0 + i, i % 5 == 0))
        t, q, r = mem.window()
        last = ref[-7:]
        assert t.tolist() == [x[0] for x in last]
        assert q.tolist() == [x[1] for x in last]
        assert r.tolist() == [x[2] for x in last]


def test_the_model_version_is_a_content_hash_of_the_model_in_use():
    """The blender and the diverter compute one version for one model (the same E(t) and
    effects), another after an adoption changes either (reference: SHA-256 of the E(t) bytes
    and the effects' JSON, ``model_version``)."""
    from twin_core.online.blender import BlenderKernel, model_version
    from twin_core.online.oos import OosCore

    spec = LineSpec.from_file(CONFIG)
    k = BlenderKernel(spec)
    v0 = k.version
    assert v0 == OosCore(spec).kernel.version == model_version(k.e, spec.dt_s, [])
    assert len(v0) == 16 and int(v0, 16) >= 0
    left = k.adopt_effects([{"name": "extra_delay", "params": {"delay_s": 10.0}}])
    assert left == [] and k.version != v0
    k.adopt_effects([])
    assert k.version == v0
