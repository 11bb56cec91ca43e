"""The online close-loop without the bus: windows and adoption (reference: the plant simulator's
ground truth, the injected effect and its size); its record of the line
(``twin_core.closeloop.record.LineRecord``, the one message-to-array adapter, online and
offline)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas.line import LineSpec
from twin_core.closeloop.online import OnlineCloseLoop, Window
from twin_core.plant import FlowDisturbance, simulate_line

CONFIG = Path(__file__).resolve().parents[3] / "services" / "configs" / "line1.yaml"
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
    cfg = LineSpec.from_file(CONFIG)
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
    cfg = LineSpec.from_file(CONFIG)
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


def test_the_record_keys_flows_by_feeder_and_takes_refills_from_the_flags():
    """Two feeders of one component stay two inputs (the declared model sums them per
    component); refill state is the flags' (a refill event on the bus is not read), and the
    window's events carry refills at the flags' edges; the record of the same messages gives the
    same arrays online (window by window) and offline (from_messages)."""
    from schemas import keys
    from schemas.messages import Event, FeederFlow, MeasuredConcentration
    from twin_core.closeloop.record import LineRecord
    from twin_core.plant.model import inlet_component_flows

    comps = {"api_a": "api", "api_b": "api", "exc": "excipient"}
    msgs = []
    for i in range(20):
        t = float(i)
        for f, q in (("api_a", 0.5 + 0.01 * i), ("api_b", 0.7), ("exc", 10.8)):
            flow = FeederFlow(
                t=t,
                seq=i,
                component=comps[f],
                mass_flow_kg_h=q,
                screw_speed_rpm=30.0,
                hopper_mass_kg=1.0,
                feed_factor_g_rev=0.5,
                refilling=(f == "api_b" and 5 <= i < 9),
            )
            msgs.append((keys.feeder_flow("l", f), flow))
        nir = MeasuredConcentration(
            t=t, seq=i, sensor="nir1", component="api", concentration_pct_w_w=10.0
        )
        msgs.append((keys.measured_concentration("l", "nir1"), nir))
    refill = Event(t=2.0, seq=0, kind="refill_start", source="exc")
    msgs.insert(7, (keys.event("l", "feeder", "exc"), refill))
    offline = LineRecord.from_messages(msgs, comps, 1.0, "api")
    data = offline.run_data("test")
    q = data.inputs.flows_kg_h
    assert sorted(q) == ["api_a", "api_b", "exc"]
    np.testing.assert_allclose(q["api_a"], 0.5 + 0.01 * np.arange(20))
    np.testing.assert_allclose(inlet_component_flows(data.inputs)["api"] * 3600.0, q["api_a"] + 0.7)
    assert data.inputs.refilling["api_b"].nonzero()[0].tolist() == [5, 6, 7, 8]
    assert not data.inputs.refilling["exc"].any()
    kinds = [(e["kind"], e["source"], e["t_s"]) for e in data.events]
    assert kinds == [("refill_start", "api_b", 5.0), ("refill_stop", "api_b", 9.0)]
    online = LineRecord(comps, 1.0, "api")
    assert [online.add_message(k, m) for k, m in msgs[:4]] == ["flow"] * 3 + ["measured"]
    for k, m in msgs[4:]:
        online.add_message(k, m)
    t, y, inputs, events = online.arrays(0.0, 19.0)
    np.testing.assert_array_equal(t, data.t_s)
    np.testing.assert_array_equal(y, data.measured)
    assert events == data.events
    for f in comps:
        np.testing.assert_array_equal(inputs.flows_kg_h[f], q[f])
    assert online.add_message(keys.feeder_flow("l", "nope"), msgs[0][1]) == "unknown_feeder"


def _findings_of_messages(ocl: OnlineCloseLoop, msgs) -> list:
    found = []
    for key, msg in msgs:
        ocl.add_message(key, msg)
        for w in ocl.due():
            found.append(ocl.check(w))
    return found


def test_a_clean_line_with_one_disturbance_claims_nothing():
    """The record of `twin plant simulate --disturbance api:1800:0.6:30` (seed 0, no hidden
    effect): a check every 300 s, each at 5 %, with the 1/f noise taken as the window's own,
    claimed a sensor gain (0.995, z 5.3) and a sensor offset (+0.066 % w/w) and put 1050-2100 s
    of good product at risk. Reference: the plant simulator's truth (no effect). With the
    day's false-claim budget spent over the windows and each window a segment of the day's 1/f
    noise, nothing is claimed and no product is put at risk."""
    from twin_core.plant.messages import simulate_messages

    cfg = LineSpec.from_file(CONFIG)
    dist = [{"feeder": "api", "t_s": 1800.0, "delta_kg_h": 0.6, "duration_s": 30.0}]
    _, msgs = simulate_messages(cfg, 3600.0, seed=0, disturbances=dist)
    ocl = OnlineCloseLoop.from_spec(cfg)
    found = _findings_of_messages(ocl, msgs)
    assert len(found) == 11
    assert [f.effects for f in found if f.effects] == []
    assert not any(f.product_at_risk for f in found)
    assert ocl.model_.effects == []


def test_the_claim_level_spends_a_daily_budget_and_windows_are_segments_of_the_noise():
    """Constant-rate alpha spending (Lan & DeMets 1983): the windows of a day spend
    false_claims_per_day between them (Bonferroni), capped at 0.05 per window."""
    from twin_core.closeloop.data import RunData
    from twin_core.closeloop.online import claim_alpha
    from twin_core.plant.model import LineInputs

    assert claim_alpha(0.05, 300.0) == pytest.approx(0.05 * 300.0 / 86400.0)
    assert claim_alpha(0.05, 300.0) * (86400.0 / 300.0) == pytest.approx(0.05)
    assert claim_alpha(0.5, 86400.0) == 0.05
    with pytest.raises(ValueError, match="false_claims_per_day"):
        claim_alpha(1.0, 300.0)
    cfg = LineSpec.from_file(CONFIG)
    with pytest.raises(ValueError, match="noise_span_s"):
        OnlineCloseLoop(cfg, 1.0, noise_span_s=0.0)
    t = np.arange(600.0)
    inp = LineInputs(t, {"api": np.full(600, 1.2)}, {"api": "api"})
    whole = RunData(t, np.full(600, 10.0), inp)
    assert whole.noise_record_n() == 600
    window = RunData(t, np.full(600, 10.0), inp, noise_span_s=86400.0)
    assert window.noise_record_n() == 86400
    assert window.slice(0.0, 300.0).noise_span_s == 86400.0
