"""The diverter's stream core, ``twin_core.online.oos.OosCore`` (no bus, single process)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas import keys
from schemas.line import LineSpec, TracerPulse
from schemas.messages import Event, FeederFlow, MeasuredConcentration, PredictedConcentration
from twin_core.online.blender import BlenderPredictor, declared_kernel
from twin_core.online.merge import WatermarkMerger
from twin_core.online.oos import OosCore
from twin_core.plant import simulate_line
from twin_core.plant.messages import run_messages, simulate_messages
from twin_core.quality.funnel import funnel_gain
from twin_core.quality.lots import diversion_window

CONFIG = Path(__file__).resolve().parents[3] / "services" / "configs" / "line1.yaml"


def spec_with(**kw) -> LineSpec:
    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(kw)
    return LineSpec.model_validate(data)


def tracer_run(spec: LineSpec, seed: int = 9):
    cfg = spec.model_copy(deep=True)
    cfg.tracers.append(TracerPulse(t_s=300.0, mass_kg=0.010, component="api"))
    return simulate_line(cfg, 600.0, dt_s=1.0, seed=seed)


def _traced_tracer_pulse(spec: LineSpec, run) -> list:
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
    d = core.deciders["api"]
    assert d.confirmed_["predicted"] == 1 and d.confirmed_["measured"] == 1
    return outs


def test_an_announced_tracer_pulse_is_traced_early():
    """A 10 g API tracer pulse (seed ch. 6) is an OOS event: the diverter traces it from its
    event (arriving after the flows of its tick) to the outlet window of RTD traceability
    (seed lot boundaries with Table 6.2's E(t), ``oos.divert_window: lot``), with the early
    divert command issued before the window opens; the predicted and measured excursions
    confirm it (no second alert)."""
    spec = spec_with(services=["blender", "oos"])
    spec.oos.divert_window = "lot"
    outs = _traced_tracer_pulse(spec, tracer_run(spec))
    alerts = [o for o in outs if o.kind == "alert"]
    assert [a.id for a in alerts] == ["line1.api.feed-000000300000"]
    e = declared_kernel(spec)
    lo, hi = diversion_window(300.0, 301.0, np.arange(e.size) * 1.0, e)  # bins 300 and 301
    assert alerts[0].t_start == pytest.approx(lo) and alerts[0].t_end == pytest.approx(hi)
    opened = [o for o in outs if o.id.endswith(".open")]
    assert len(opened) == 1 and opened[0].t < lo


def test_the_excursion_window_diverts_what_the_pulse_puts_out_of_spec_and_little_more():
    """With the default ``divert_window: excursion`` the final window is where the pulse's
    predicted outlet (its inlet convolved with the E(t) in use) leaves the guarded
    specification, padded: it covers every sample of the simulator's true outlet outside the
    specification (reference: the plant simulator's noise-free outlet), with at most 2 x
    (pad + 3) s of in-specification product around it, and the early command comes before
    the first out-of-specification sample leaves."""
    spec = spec_with(services=["blender", "oos"])
    run = tracer_run(spec)
    outs = _traced_tracer_pulse(spec, run)
    (alert,) = [o for o in outs if o.kind == "alert"]
    c = run.outlet_true_pct_w_w["api"]
    out = run.t_s[(c > 11.5) | (c < 8.5)]
    assert alert.t_start <= out[0] and alert.t_end >= out[-1]
    extra = (out[0] - alert.t_start) + (alert.t_end - out[-1])
    assert extra <= 2 * (spec.oos.divert_pad_s + 3.0), (alert.t_start, alert.t_end, out[[0, -1]])
    (opened,) = [o for o in outs if o.id.endswith(".open")]
    assert opened.t < out[0] and opened.t_start <= out[0]


def test_no_blind_start_the_first_excursion_is_decided_on_its_last_sample():
    """At start the inlet stream holds its ticks ``inlet_hold_s`` (15 s) of plant time for late
    tracer events; its watermark (``WatermarkMerger.advance``) lets the measured decisions go on:
    three NIR samples out of specification at t = 2, 3, 4 s open an episode when the sample at
    4 s arrives, not 15 s of plant time later (the blind start of the latency benchmark)."""
    spec = spec_with(services=["blender", "oos"])
    core = OosCore(spec)
    assert core.inlet_hold_s >= 10.0
    opened_at = None
    for i in range(8):
        t = float(i)
        outs = []
        for f in spec.feeders:
            outs += core.flow(f.id, t, f.setpoint_kg_h)
        outs += core.predicted("api", t, 10.0)
        outs += core.measured("api", t, 13.0 if 2 <= i <= 4 else 10.0)
        if opened_at is None and any(o.id.endswith(".open") for o in outs):
            opened_at = t
    assert opened_at == 4.0


def test_watermark_advance_releases_without_an_item_and_keeps_the_order():
    """A punctuation moves a stream's watermark: items of the other streams up to it are
    released in time order; an item of that stream at a later time is released after them."""
    m = WatermarkMerger(["inlet", "measured"])
    assert m.push("measured", 1.0, "a") == [] and m.push("measured", 2.0, "b") == []
    assert [x[2] for x in m.advance("inlet", 1.5)] == ["a"]
    assert m.advance("inlet", 0.5) == []  # a watermark never goes back
    assert [x[2] for x in m.push("inlet", 2.0, "i")] == ["i", "b"]


def test_decisions_do_not_depend_on_arrival_order():
    """Streams delayed independently (up to 2 min of plant time, as after a restart or under
    load; order kept within each stream) give exactly the outputs of the in-order run."""
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
    """The tracer pulse of seed ch. 6 announced after later flows (a tick less late than the
    no-latency hold, from t(F = 0.5 %) of the declared blender's E(t): 12 s for line1's default
    models; or 120 s late within the wall-time grace of a fast replay) gives exactly the outputs
    of the in-order run."""
    spec = spec_with(services=["oos"])
    msgs = run_messages(tracer_run(spec), spec)
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
    hold = OosCore(spec).inlet_hold_s
    assert hold >= 5.0
    assert decide(hold - spec.dt_s) == ref
    assert decide(120.0, grace_s=1e9) == ref
    assert decide(120.0) != ref  # past both holds the pulse is moved to a later tick


def test_history_needs_no_wall_grace_after_the_catch_up():
    """A restarted diverter rebuilds its inlet ticks from history at once; the wall-time grace
    meant for live samples (here unbounded) held its first decisions back. Once the history is
    complete (``OosCore.history_complete``) the same decisions come out, and the outputs of the
    whole run equal those of a core without grace (plant time decides, not the wall clock)."""
    spec = spec_with(services=["oos"])
    msgs = run_messages(tracer_run(spec), spec)

    def feed(core: OosCore, part: list) -> list:
        outs = []
        for k, m in part:
            if isinstance(m, Event) and m.kind == "tracer_pulse":
                core.tracer_pulse("api", m.t, m.mass_kg, m.duration_s)
            elif isinstance(m, FeederFlow):
                outs += core.flow(keys.parse_key(k).id, m.t, m.mass_flow_kg_h)
            elif isinstance(m, MeasuredConcentration):
                outs += core.measured("api", m.t, m.concentration_pct_w_w)
            outs += core.release_inlet()
        return outs

    def ids(outs: list) -> list:
        return [(o.kind, o.id, o.t, o.t_start, o.t_end) for o in outs]

    plain = OosCore(spec)
    ref = ids(feed(plain, msgs) + plain.end_of_stream())
    history = [(k, m) for k, m in msgs if m.t <= 400.0]  # the pulse's alert is due by then
    live = [(k, m) for k, m in msgs if m.t > 400.0]
    held = OosCore(spec)
    held.inlet_grace_s = 1e9
    before = feed(held, history)
    assert not [o for o in ids(before) if o[0] == "alert"]  # held by the grace
    caught_up = held.history_complete()
    assert [o[1] for o in ids(before + caught_up) if o[0] == "alert"] == [
        "line1.api.feed-000000300000"
    ]
    held.inlet_grace_s = 0.0  # the live part: nothing more to wait for in this test
    after = feed(held, live) + held.end_of_stream()
    assert ids(before + caught_up + after) == ref


def test_the_diverter_follows_the_rtd_the_blender_adopted():
    """An adopted RTD estimate (a slower blender) moves the traced window to the estimate's lot
    boundaries and the funnel gain to the estimate's (twin_core.quality: diversion_window,
    funnel_gain of the estimate's E(t)), as the blender's prediction does; the predicted
    excursion window (the default) moves with it."""
    spec = spec_with(services=["oos"])
    spec.oos.divert_window = "lot"
    msgs = run_messages(tracer_run(spec), spec)
    slow = {"tau_d": 20.0, "tau": 30.0, "pe": 7.67}

    def alerts(adopt: bool) -> list:
        core = OosCore(spec)
        if adopt:
            core.adopt_estimate("axial_dispersion_open", slow)
        outs = []
        for k, m in msgs:
            if isinstance(m, FeederFlow):
                outs += core.flow(keys.parse_key(k).id, m.t, m.mass_flow_kg_h)
            elif isinstance(m, Event) and m.kind == "tracer_pulse":
                core.tracer_pulse("api", m.t, m.mass_kg, m.duration_s)
        outs += core.end_of_stream()
        return [o for o in outs if o.kind == "alert"], core

    (declared,), _ = alerts(False)
    (adopted,), core = alerts(True)
    e = core.kernel.e
    lo, hi = diversion_window(300.0, 301.0, np.arange(e.size) * 1.0, e)
    assert (adopted.t_start, adopted.t_end) == pytest.approx((lo, hi))
    assert adopted.t_start > declared.t_start + 7.0  # 8 s more plug flow
    np.testing.assert_array_equal(core.deciders["api"].gain, funnel_gain(e, spec.dt_s))
    assert adopted.peak_deviation < declared.peak_deviation  # more back-mixing, lower peak
    spec.oos.divert_window = "excursion"
    (declared,), _ = alerts(False)
    (adopted,), _ = alerts(True)
    assert adopted.t_start > declared.t_start + 7.0


def test_a_product_side_finding_diverts_only_what_it_puts_out_of_spec_and_is_not_yet_diverted():
    """A finding whose product-side reading is out of specification only where a traced
    disturbance was already diverted diverts nothing more; a stretch outside every divert
    window is diverted alone, not the finding's whole window (reference: interval arithmetic
    on the windows)."""
    from twin_core.online.diverter import OosDecider

    d = OosDecider("l", "api", 10.0, 8.5, 11.5, 1.0, None, lambda a, b: (a, b))
    d._windows.append([1814.0, 1889.0])
    assert d.product_risk(2100.0, "f1", 1050.0, 2100.0, 9.2, 13.9, [[1816.0, 1870.0]]) == []
    out = d.product_risk(2400.0, "f2", 1200.0, 2400.0, 9.2, 13.9, [[1880.0, 1950.0]])
    assert [(o.kind, o.t_start, o.t_end) for o in out] == [
        ("alert", 1890.0, 1950.0),
        ("divert", 1890.0, 1950.0),
    ]
    # an older finding without stretches: its whole window, once
    out = d.product_risk(3000.0, "f3", 2500.0, 3000.0, 9.2, 12.0, None)
    assert [(o.kind, o.t_start, o.t_end) for o in out] == [
        ("alert", 2500.0, 3000.0),
        ("divert", 2500.0, 3000.0),
    ]
    assert d.product_risk(3000.0, "f3", 2500.0, 3000.0, 9.2, 12.0, None) == []


def test_a_long_disturbance_stays_diverted_until_its_final_window():
    """A flagged feeder disturbance longer than the blender's lot window: the provisional
    divert window holds until the final one replaces it. It used to end at the lot boundary
    of the episode so far (flag time + 63 s), and the product between that end and the final
    window (an 88 s disturbance: 24 s of out-of-specification product) was not diverted;
    reference: the plant simulator's true outlet."""
    spec = spec_with(services=["oos"])
    dist = [{"feeder": "api", "t_s": 300.0, "delta_kg_h": -0.6, "duration_s": 120.0}]
    run, msgs = simulate_messages(spec, 900.0, seed=3, disturbances=dist)
    core = OosCore(spec)
    outs = []
    for k, m in msgs:
        if isinstance(m, FeederFlow):
            outs += core.flow(keys.parse_key(k).id, m.t, m.mass_flow_kg_h)
    outs += core.end_of_stream()
    (opened,) = [o for o in outs if o.id.endswith(".open")]
    (final,) = [o for o in outs if o.id.endswith(".final")]
    assert opened.t_end >= final.t  # the gate diverts until the final window comes
    c = run.outlet_true_pct_w_w["api"]
    out = run.t_s[(c < 8.5) | (c > 11.5)]
    covered = [(opened.t_start, min(opened.t_end, final.t)), (final.t_start, final.t_end)]
    assert all(any(a <= t <= b for a, b in covered) for t in out)
