"""The rtd service's core, ``twin_core.online.rtd`` (no bus, single process)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from schemas.line import BlenderModelConfig, LineSpec, TracerPulse
from twin_core.online.rtd import RtdCore, analyze_segment
from twin_core.online.tracer import TracerPulseDetector
from twin_core.plant import simulate_line

CONFIG = Path(__file__).resolve().parents[3] / "services" / "configs" / "line1.yaml"


def spec_with(**kw) -> LineSpec:
    """line1 with the seed's Table 6.2 axial-dispersion blender driving the simulated line."""
    data = LineSpec.from_file(CONFIG).model_dump()
    data["blender"] = BlenderModelConfig().model_dump()
    data.update(kw)
    return LineSpec.model_validate(data)


def test_the_fit_of_a_simulated_tracer_pulse_recovers_seed_table_6_2():
    """Seed Table 6.2: tau_d = 11.92 s, tau = 16.37 s, Pe = 7.67 drive the simulated line; the
    detected, cleaned and fitted pulse (10 g API tracer at 12 kg/h) gives them back."""
    spec = spec_with(dt_s=0.5, sensor={"id": "nir1", "component": "api", "sample_period_s": 0.5})
    cfg = spec.model_copy(deep=True)
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
    r = analyze_segment(segs[0], spec.rtd)
    assert r.model == "axial_dispersion_open"
    assert r.params["tau_d"] == pytest.approx(11.92, abs=1.5)
    assert r.params["tau"] == pytest.approx(16.37, rel=0.15)
    assert r.params["pe"] == pytest.approx(7.67, rel=0.35)
    assert r.mean_residence_time_s == pytest.approx(32.5, rel=0.08)


def pulse_run(refill_at: float | None):
    """A steady line (ideal feeders) with an unannounced 10 g API tracer at 900 s, and an API
    hopper refill flagged by the feeder from ``refill_at`` for 30 s."""
    spec = spec_with(rtd={"detect": "auto"})
    cfg = spec.model_copy(deep=True)
    cfg.tracers.append(TracerPulse(t_s=900.0, mass_kg=0.010, component="api"))
    for f in cfg.feeders:
        f.ideal = True
    run = simulate_line(cfg, 1300.0, dt_s=1.0, seed=12)
    flags = np.zeros(run.t_s.size, dtype=bool)
    if refill_at is not None:
        flags[(run.t_s >= refill_at) & (run.t_s < refill_at + 30.0)] = True
    return spec, run, flags


@pytest.mark.parametrize(
    "refill_at, kind", [(None, "fitted"), (400.0, "fitted"), (850.0, "skipped_disturbance")]
)
def test_a_pulse_found_by_itself_during_a_refill_is_not_a_tracer_experiment(refill_at, kind):
    """Refill state comes from the feeders' flags: a pulse the detector finds by itself (not
    announced) is fitted unless a refill (its flag window plus the blender's 300 s kernel) can
    reach the outlet while it is seen: a refill at 400-430 s cannot (gone by 730 s), one at
    850-880 s can."""
    spec, run, flags = pulse_run(refill_at)
    core = RtdCore(spec)
    outcomes = []
    for i, t in enumerate(run.t_s):
        core.flow("api", float(t), bool(flags[i]))
        c = run.measured_pct_w_w[i]
        if np.isfinite(c) and (o := core.measured(float(t), float(c))) is not None:
            outcomes.append(o)
    assert [(o.kind, o.segment.announced) for o in outcomes] == [(kind, False)]
    assert (outcomes[0].result is not None) == (kind == "fitted")


def test_an_announced_pulse_is_fitted_despite_a_disturbance_and_counted_once():
    """An announced tracer (its event) is a tracer experiment whatever else happened; the same
    event again (history after a restart) is not a second announcement."""
    spec, run, _ = pulse_run(None)
    core = RtdCore(spec)
    ev = {"t_s": 890.0, "kind": "disturbance", "source": "api", "duration_s": 20.0}
    core.add_event(ev)
    pulse = {"t_s": 900.0, "kind": "tracer_pulse", "source": "api", "mass_kg": 0.01}
    assert core.add_event(pulse) and not core.add_event(pulse)
    assert core.duplicates == 1
    outcomes = [
        o
        for t, c in zip(run.t_s, run.measured_pct_w_w)
        if np.isfinite(c) and (o := core.measured(float(t), float(c))) is not None
    ]
    assert [(o.kind, o.segment.announced, o.segment.t0) for o in outcomes] == [
        ("fitted", True, 900.0)
    ]
    assert outcomes[0].result.params["tau_d"] == pytest.approx(11.92, abs=2.0)
