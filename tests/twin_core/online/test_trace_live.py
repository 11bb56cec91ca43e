"""The trace service's core (twin_core.online.trace.LiveTracker) against the offline model on
the same record: message by message it gives the lot composition track_lots gives."""

from __future__ import annotations

import numpy as np

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import Event, FeederFlow
from twin_core.online.trace import LiveTracker
from twin_core.plant.messages import simulate_messages
from twin_core.tracking import Refill, mixed_fraction, track_lots

LINE = {
    "name": "line1",
    "feeders": [
        {
            "id": "api",
            "component": "api",
            "setpoint_kg_h": 1.2,
            "liw": {"initial_mass_kg": 0.6, "refill_low_kg": 0.4, "refill_high_kg": 0.6},
        },
        {"id": "excipient", "component": "excipient", "setpoint_kg_h": 10.8, "ideal": True},
    ],
    "blender": {"kind": "rtd"},
    "sensor": {"id": "nir1", "component": "api"},
    "spec": [
        {"component": "api", "target_pct_w_w": 10.0, "lower_pct_w_w": 9.0, "upper_pct_w_w": 11.0}
    ],
    "tracking": {"hopper": "mixture", "mixed_fraction": 0.3},
}


def test_live_tracker_equals_the_offline_model_on_a_simulated_record():
    """Reference: the offline model (track_lots) on the same flows, hopper masses, refills and
    kernel switch (an RTD estimate applying from 900 s): equal lot fractions to 1e-9."""
    spec = LineSpec.model_validate(LINE)
    run, msgs = simulate_messages(spec, 1800.0, 0)
    live = LiveTracker(spec)
    est = ("tanks_in_series", {"tau_d": 8.0, "tau": 30.0, "n": 4.0})
    live.schedule(900.0, "estimate", est)
    got: dict[float, dict[str, float]] = {}
    for key, msg in msgs:
        if isinstance(msg, FeederFlow):
            fid = keys.parse_key(key).id
            for t, lots, _, _, _ in live.push(fid, msg.t, msg.mass_flow_kg_h, msg.hopper_mass_kg):
                got[t] = lots
        elif isinstance(msg, Event):
            live.add_event(msg)
    refills = [e for e in run.events if e.kind == "refill_stop"]
    assert len(refills) >= 3
    from twin_core.online.blender import BlenderKernel

    k = BlenderKernel(spec)
    e0 = k.e.copy()
    k.adopt_estimate(*est)
    n = run.t_s.size
    trace = track_lots(
        run.t_s,
        {f: r.flow_kg_h for f, r in run.feeders.items()},
        spec.components,
        [(0.0, e0), (900.0, k.e)],
        [Refill(e.source, e.t, e.t, e.lot_id) for e in refills],
        {
            f: np.where(np.isfinite(r.hopper_mass_kg), r.hopper_mass_kg, 0.0)
            for f, r in run.feeders.items()
        },
        mixed_fraction("mixture", 0.3),
    )
    frac = trace.fractions()
    assert len(got) >= n - 1
    worst = 0.0
    for i, t in enumerate(run.t_s[: len(got)]):
        for j, lot in enumerate(trace.lots):
            worst = max(
                worst, abs(got[t].get(lot, 0.0) - (frac[i, j] if frac[i, j] > 1e-6 else 0.0))
            )
    assert worst < 1e-9, worst
    assert "api-L0003" in trace.lots
