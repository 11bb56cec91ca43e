"""RTD service core and blender core without the bus (fast, single process)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas.line import LineSpec
from services.blender import BlenderPredictor
from services.plant import simulate_messages
from services.rtd import analyze_segment
from twin_core.online import TracerPulseDetector

CONFIG = Path(__file__).resolve().parent.parent / "services" / "configs" / "line1.yaml"


def spec_with(**kw) -> LineSpec:
    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(kw)
    return LineSpec.model_validate(data)


def test_blender_streaming_prediction_equals_declared_line_model():
    """Peer code: twin_core.plant.LineModel (batch FFT convolution of the mass flows) gives the
    same outlet concentration as the streaming blender core, tick by tick."""
    spec = spec_with()
    run, _ = simulate_messages(
        spec,
        900.0,
        seed=2,
        disturbances=[{"feeder": "api", "t_s": 200.0, "delta_kg_h": 0.5, "duration_s": 60.0}],
    )
    from twin_core.plant import LineModel

    ref = LineModel(spec.plant_config()).outlet(run.inputs())["api"]
    bp = BlenderPredictor(spec)
    got = {}
    for i, t in enumerate(run.t_s):
        for name, rec in run.feeders.items():
            for tt, conc in bp.push(name, float(t), float(rec.flow_kg_h[i])):
                got[tt] = conc["api"]
    pred = np.array([got[float(t)] for t in run.t_s])
    np.testing.assert_allclose(pred, ref, rtol=1e-6, atol=1e-6)


def test_rtd_fit_of_a_simulated_tracer_pulse_recovers_seed_table_6_2():
    """Seed Table 6.2: tau_d = 11.92 s, tau = 16.37 s, Pe = 7.67 drive the simulated line; the
    detected, cleaned and fitted pulse (10 g API tracer at 12 kg/h) gives them back."""
    spec = spec_with(dt_s=0.5, sensor={"id": "nir1", "component": "api", "sample_period_s": 0.5})
    from twin_core.plant import TracerPulse, simulate_line

    cfg = spec.plant_config()
    cfg.tracers.append(TracerPulse(t_s=300.0, mass_kg=0.010, component="api"))
    for f in cfg.feeders:
        f.ideal = True  # a steady line: the tracer is the only excursion
    run = simulate_line(cfg, 700.0, dt_s=0.5, seed=5)
    det = TracerPulseDetector(0.5, max_duration_s=spec.rtd.max_duration_s)
    segs = []
    for t, c in zip(run.t_s, run.measured_pct_w_w):
        if t == 300.0:
            det.announce(300.0)
        if np.isfinite(c) and (s := det.push(float(t), float(c))) is not None:
            segs.append(s)
    assert len(segs) == 1
    r = analyze_segment(segs[0], spec)
    assert r.model == "axial_dispersion_open"
    assert r.params["tau_d"] == pytest.approx(11.92, abs=1.5)
    assert r.params["tau"] == pytest.approx(16.37, rel=0.15)
    assert r.params["pe"] == pytest.approx(7.67, rel=0.35)
    assert r.mean_residence_time_s == pytest.approx(32.5, rel=0.08)


def test_diverter_funnel_gain_agrees_with_discrete_pulse_response():
    """twin_core.quality's funnel M(d) (piecewise-linear F) against the exact discrete pulse
    response of the streaming model (window_gain, itself checked against numpy.convolve)."""
    from services.blender import blender_kernel
    from services.oos import funnel_gain
    from twin_core.online import window_gain

    spec = spec_with()
    e = blender_kernel(spec)
    tk = np.arange(e.size) * spec.dt_s
    g_q = funnel_gain(tk, e)
    g_d = window_gain(e / (spec.dt_s * e.sum()), spec.dt_s)
    assert g_q.shape == g_d.shape
    np.testing.assert_allclose(g_q, g_d, atol=0.03)


def test_blender_includes_announced_tracer_pulses_like_the_declared_model():
    """Peer code: twin_core.plant.LineModel with a 10 g tracer pulse; the streaming blender told
    of the pulse by its event (arriving after the flows of its tick) predicts the same peak."""
    from twin_core.plant import LineModel, TracerPulse, simulate_line

    spec = spec_with()
    cfg = spec.plant_config()
    cfg.tracers.append(TracerPulse(t_s=300.0, mass_kg=0.010, component="api"))
    run = simulate_line(cfg, 600.0, dt_s=1.0, seed=6)
    ref = LineModel(cfg).outlet(run.inputs())["api"]
    bp = BlenderPredictor(spec)
    got = {}
    for i, t in enumerate(run.t_s):
        for name, rec in run.feeders.items():
            for tt, conc in bp.push(name, float(t), float(rec.flow_kg_h[i])):
                got[tt] = conc["api"]
        if t == 300.0:
            bp.add_pulse("api", 300.0, 0.010, 1.0)
    pred = np.array([got[float(t)] for t in run.t_s])
    assert pred.max() == pytest.approx(ref.max(), rel=0.02)
    base = ref[250]
    # tracer mass is conserved; the half-bin that arrived after its tick is one tick late
    assert np.sum(pred - base) == pytest.approx(np.sum(ref - base), rel=0.01)
    assert np.max(np.abs(pred - ref)) < 0.1 * (ref.max() - base)


def test_blender_with_a_compartment_network_export_matches_its_predict(tmp_path, capsys):
    """Peer code: schemas.blender_model.BlenderModel.predict (compartment network of
    twin_core.compartment) on the inlet composition; the blender service core with
    ``kind: compartment`` uses the same export through its impulse response."""
    from schemas.blender_model import BlenderModel
    from services.cli.main import main

    fields, model = tmp_path / "f.npz", tmp_path / "m.json"
    assert main(["compartment", "synthetic", str(fields), "--shape", "5", "7", "7"]) == 0
    assert (
        main(
            [
                "compartment",
                "build",
                str(fields),
                "--out",
                str(model),
                "--sections",
                "4",
                "--surrogate",
                "2000",
            ]
        )
        == 0
    )
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
    ref = bm.predict(t, 100 * api / 12.0)
    assert pred.max() > 14.0  # the step reached the outlet
    np.testing.assert_allclose(pred, ref, atol=0.1)


def test_blender_adopts_an_rtd_estimate():
    """After an RTD estimate (the rtd service's message) the blender predicts with the new E(t):
    once a kernel length has passed, equal to the declared line model with those parameters."""
    from schemas.messages import RtdEstimate
    from services.blender import rtd_kernel
    from twin_core.plant import LineModel

    spec = spec_with()
    run, _ = simulate_messages(spec, 1200.0, seed=8)
    est = RtdEstimate(
        t=0.0,
        seq=0,
        model="axial_dispersion_open",
        params={"tau_d": 8.0, "tau": 25.0, "pe": 12.0},
        mean_residence_time_s=33.0,
    )
    bp = BlenderPredictor(spec)
    got = {}
    for i, t in enumerate(run.t_s):
        if t == 400.0:
            bp.set_kernel(rtd_kernel(est.model, est.params, spec.dt_s, spec.blender.kernel_s))
        for name, rec in run.feeders.items():
            for tt, conc in bp.push(name, float(t), float(rec.flow_kg_h[i])):
                got[tt] = conc["api"]
    cfg = spec.plant_config()
    cfg.blender.params = dict(est.params)
    ref = LineModel(cfg).outlet(run.inputs())["api"]
    pred = np.array([got[float(t)] for t in run.t_s])
    late = run.t_s >= 400 + spec.blender.kernel_s
    np.testing.assert_allclose(pred[late], ref[late], atol=1e-6)
    assert np.max(np.abs(pred[run.t_s < 400] - ref[run.t_s < 400])) > 1e-3  # old model before


def test_diverter_traces_an_announced_tracer_pulse_early():
    """A 10 g API tracer pulse (seed ch. 6) is an OOS event: the diverter traces it from its
    event (arriving after the flows of its tick) to the outlet window of RTD traceability
    (seed lot boundaries with Table 6.2's E(t)), with the early divert command issued before the
    window opens; the predicted and measured excursions confirm it (no second alert)."""
    from schemas import keys
    from schemas.messages import Event, FeederFlow, MeasuredConcentration
    from services.blender import blender_kernel
    from services.oos import OosCore
    from services.plant import run_messages
    from twin_core.plant import TracerPulse, simulate_line
    from twin_core.quality.lots import diversion_window

    spec = spec_with(services=["blender", "oos"])
    cfg = spec.plant_config()
    cfg.tracers.append(TracerPulse(t_s=300.0, mass_kg=0.010, component="api"))
    run = simulate_line(cfg, 600.0, dt_s=1.0, seed=9)
    bp, core = BlenderPredictor(spec), OosCore(spec)
    outs = []
    for k, m in run_messages(run, spec):
        if isinstance(m, FeederFlow):
            f = keys.parse_key(k).id
            outs += core.flow(f, m.t, m.mass_flow_kg_h)
            for t, conc in bp.push(f, m.t, m.mass_flow_kg_h):
                outs += core.predicted("api", t, conc["api"])
        elif isinstance(m, MeasuredConcentration):
            outs += core.measured("api", m.t, m.concentration_pct_w_w)
        elif isinstance(m, Event) and m.kind == "tracer_pulse":
            core.tracer_pulse("api", m.t, m.mass_kg, m.duration_s)
            bp.add_pulse("api", m.t, m.mass_kg, m.duration_s)
    outs += core.end_of_stream()
    alerts = [o for o in outs if o.kind == "alert"]
    assert [a.id for a in alerts] == ["line1.api.feed-000000300000"]
    e = blender_kernel(spec)
    lo, hi = diversion_window(300.0, 301.0, np.arange(e.size) * 1.0, e)  # bins 300 and 301
    assert alerts[0].t_start == pytest.approx(lo) and alerts[0].t_end == pytest.approx(hi)
    opened = [o for o in outs if o.id.endswith(".open")]
    assert len(opened) == 1 and opened[0].t < lo
    d = core.deciders["api"]
    assert d.confirmed_["predicted"] == 1 and d.confirmed_["measured"] == 1


def test_rtd_service_fits_the_announced_pulse_and_skips_a_feeder_disturbance():
    """A run with a feeder disturbance (announced by its events) and an announced 10 g tracer
    pulse: the rtd service (auto detection on) fits only the tracer, near seed Table 6.2."""
    from schemas.messages import RtdEstimate
    from services.plant import run_messages
    from services.rtd import RtdService
    from twin_core.plant import TracerPulse, simulate_line

    spec = spec_with()
    cfg = spec.plant_config()
    cfg.tracers.append(TracerPulse(t_s=900.0, mass_kg=0.010, component="api"))
    for f in cfg.feeders:
        f.ideal = True
    run = simulate_line(
        cfg,
        1500.0,
        dt_s=1.0,
        seed=12,
        disturbances=[{"feeder": "api", "t_s": 300.0, "delta_kg_h": 0.6, "duration_s": 30.0}],
    )

    class Pub:
        seq = 0
        sent: list[RtdEstimate] = []

        def publish(self, msg):
            self.sent.append(msg)

    svc = RtdService(spec, install_signal_handlers=False)
    svc.pub = Pub()
    for k, m in run_messages(run, spec):
        if k.endswith(("/event", "/concentration")):
            svc.handle(k, m)
    assert svc.counters.get("pulses_skipped_disturbance") == 1, (
        svc.counters.snapshot(),
        [(e.pulse_t_s, e.params) for e in svc.pub.sent],
        svc._excluded,
    )
    assert [e.pulse_t_s for e in svc.pub.sent] == [900.0]
    est = svc.pub.sent[0]
    assert est.params["tau_d"] == pytest.approx(11.92, abs=2.0)
    assert est.mean_residence_time_s == pytest.approx(32.5, rel=0.1)


def test_diverter_decisions_do_not_depend_on_arrival_order():
    """Streams delayed independently (up to 2 min of plant time, as after a restart or under
    load; order kept within each stream) give exactly the outputs of the in-order run."""
    from schemas import keys
    from schemas.messages import FeederFlow, MeasuredConcentration, PredictedConcentration
    from services.oos import OosCore

    spec = spec_with(services=["feeder", "blender", "oos"])
    run, msgs = simulate_messages(
        spec,
        1200.0,
        seed=11,
        disturbances=[{"feeder": "api", "t_s": 600.0, "delta_kg_h": 0.6, "duration_s": 30.0}],
    )
    bp = BlenderPredictor(spec)
    streams: dict[str, list] = {"api": [], "excipient": [], "nir": [], "pred": []}
    for k, m in msgs:
        if isinstance(m, FeederFlow):
            f = keys.parse_key(k).id
            streams[f].append(m)
            for t, conc in bp.push(f, m.t, m.mass_flow_kg_h):
                for c, v in conc.items():
                    streams["pred"].append(
                        PredictedConcentration(
                            t=t, seq=0, model="rtd", component=c, concentration_pct_w_w=v
                        )
                    )
        elif isinstance(m, MeasuredConcentration):
            streams["nir"].append(m)

    def decide(order):
        core = OosCore(spec)
        outs = []
        for name, m in order:
            if name in ("api", "excipient"):
                outs += core.flow(name, m.t, m.mass_flow_kg_h)
            elif name == "nir":
                outs += core.measured(m.component, m.t, m.concentration_pct_w_w)
            else:
                outs += core.predicted(m.component, m.t, m.concentration_pct_w_w)
        outs += core.end_of_stream()
        return [(o.kind, o.id, o.t, o.t_start, o.t_end) for o in outs]

    ref = decide(sorted(((n, m) for n, s in streams.items() for m in s), key=lambda x: x[1].t))
    assert [o[1] for o in ref if o[0] == "alert"] == ["line1.api.feed-000000600000"]
    rng = np.random.default_rng(3)
    for _ in range(3):
        arrivals = []
        for name, items in streams.items():
            delay = np.clip(np.cumsum(rng.normal(0, 3, len(items))), 0, 60) + rng.uniform(0, 60)
            at = np.maximum.accumulate(np.array([m.t for m in items]) + delay)
            arrivals += [(a, i, name, m) for i, (a, m) in enumerate(zip(at, items))]
        arrivals.sort(key=lambda z: (z[0], z[1]))
        assert decide([(n, m) for _, _, n, m in arrivals]) == ref


def test_a_late_tracer_event_counts_in_its_own_tick():
    """The tracer pulse of seed ch. 6 announced after later flows (12 s of plant time late, within
    the no-latency hold t(F = 0.5 %) of Table 6.2's E(t); or 120 s late within the wall-time
    grace of a fast replay) gives exactly the outputs of the in-order run."""
    from schemas import keys
    from schemas.messages import Event, FeederFlow, MeasuredConcentration
    from services.oos import OosCore
    from services.plant import run_messages
    from twin_core.plant import TracerPulse, simulate_line

    spec = spec_with(services=["oos"])
    cfg = spec.plant_config()
    cfg.tracers.append(TracerPulse(t_s=300.0, mass_kg=0.010, component="api"))
    run = simulate_line(cfg, 600.0, dt_s=1.0, seed=9)
    msgs = run_messages(run, spec)
    pulse = next(m for _, m in msgs if isinstance(m, Event) and m.kind == "tracer_pulse")

    def decide(late_s: float, grace_s: float = 0.0) -> list:
        core = OosCore(spec)
        core.inlet_grace_s = grace_s
        outs, sent = [], False
        for k, m in msgs:
            if not sent and m.t > pulse.t + late_s:
                core.tracer_pulse("api", pulse.t, pulse.mass_kg, pulse.duration_s)
                sent = True
            if isinstance(m, FeederFlow):
                outs += core.flow(keys.parse_key(k).id, m.t, m.mass_flow_kg_h)
            elif isinstance(m, MeasuredConcentration):
                outs += core.measured("api", m.t, m.concentration_pct_w_w)
            outs += core.release_inlet()
        outs += core.end_of_stream()
        return [(o.kind, o.id, o.t, o.t_start, o.t_end) for o in outs]

    ref = decide(0.0)
    assert [o[1] for o in ref if o[0] == "alert"] == ["line1.api.feed-000000300000"]
    assert decide(12.0) == ref
    assert decide(120.0, grace_s=1e9) == ref
    assert decide(120.0) != ref  # past both holds the pulse is moved to a later tick
