"""The rtd service as a shell (its ``handle`` and publications, no bus)."""

from __future__ import annotations

from pathlib import Path

import pytest

from schemas.line import BlenderModelConfig, LineSpec, TracerPulse
from schemas.messages import RtdEstimate
from services.rtd import RtdService
from twin_core.plant import simulate_line
from twin_core.plant.messages import run_messages

CONFIG = Path(__file__).resolve().parents[2] / "services" / "configs" / "line1.yaml"


class Pub:
    """Stands for the service's publisher: keeps what it is given."""

    seq = 0

    def __init__(self) -> None:
        self.sent: list[RtdEstimate] = []

    def publish(self, msg: RtdEstimate) -> RtdEstimate:
        self.sent.append(msg)
        self.seq = msg.seq + 1
        return msg


def test_rtd_service_fits_the_announced_pulse_and_skips_a_feeder_disturbance(tmp_path):
    """A run with a feeder disturbance (announced by its events) and an announced 10 g tracer
    pulse, as the bus carries them: the rtd service (auto detection on) publishes an estimate of
    the tracer only, near seed Table 6.2, and publishes the skipped excursion with its reason; a
    restarted service (same run directory) publishes neither again."""
    spec = LineSpec.from_file(CONFIG)
    spec.state_dir = str(tmp_path)
    spec.blender = BlenderModelConfig()  # seed Table 6.2 drives the simulated line
    cfg = spec.model_copy(deep=True)
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
    svc = RtdService(spec, install_signal_handlers=False)
    svc.pub, svc.skipped_pub = Pub(), Pub()
    for k, m in run_messages(run, spec):
        svc.handle(k, m)
    svc.finish()
    [skipped] = svc.skipped_pub.sent
    assert skipped.reason == "skipped_disturbance" and 300.0 <= skipped.pulse_t_s < 900.0
    assert svc.counters.get("pulses_skipped_disturbance") == 1, svc.counters.snapshot()
    assert svc.counters.get("tracer_events") == 1
    assert [e.pulse_t_s for e in svc.pub.sent] == [900.0]
    est = svc.pub.sent[0]
    assert est.model == "axial_dispersion_open"
    assert est.params["tau_d"] == pytest.approx(11.92, abs=2.0)
    assert est.mean_residence_time_s == pytest.approx(32.5, rel=0.1)
    again = RtdService(spec, install_signal_handlers=False)
    again.pub, again.skipped_pub = Pub(), Pub()
    for k, m in run_messages(run, spec):
        again.handle(k, m)
    again.finish()
    assert again.pub.sent == [] and again.skipped_pub.sent == []
    assert again.counters.get("suppressed_republish") == 2
