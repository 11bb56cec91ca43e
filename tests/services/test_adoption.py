"""Plant-time adoption of RTD estimates and findings (the blender as a shell, no bus): an update
applies from its ``applies_from_s`` whenever it arrives, the flows wait for the producers'
progress, and an update that comes after its plant time is counted with its lateness.

Reference: the blender's own predictions with the update scheduled before any flow (the
outputs must not depend on when it arrived); the lateness is the plant-time difference
between the tick it is applied from and its ``applies_from_s``.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import pytest

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import AdoptionProgress, RtdEstimate
from services.blender import BlenderService
from services.common import AdoptionGate, ProducerProgress, ProgressReport
from services.twin_demo import report_markdown
from twin_core.plant.messages import feeder_flow_messages

CONFIG = Path(__file__).resolve().parents[2] / "services" / "configs" / "line1.yaml"
SLOW = {"tau_d": 20.0, "tau": 25.0, "pe": 5.0}


class Pub:
    """Stands for a publisher: keeps what it is given."""

    seq = 0

    def __init__(self) -> None:
        self.sent: list = []

    def publish(self, msg):
        self.sent.append(msg)
        return msg


def spec_for(tmp_path: Path, services: list[str]) -> LineSpec:
    spec = LineSpec.from_file(CONFIG)
    spec.state_dir = str(tmp_path)
    spec.services = services
    spec.blender.adopt_rtd_estimates = True
    return spec


def estimate(applies_from_s: float) -> RtdEstimate:
    return RtdEstimate(
        t=100.0,
        seq=0,
        model="axial_dispersion_open",
        params=SLOW,
        mean_residence_time_s=50.0,
        applies_from_s=applies_from_s,
    )


def blender(spec: LineSpec, state: Path) -> BlenderService:
    spec = spec.model_copy(update={"state_dir": str(state)})
    svc = BlenderService(spec, install_signal_handlers=False)
    svc.pub, svc.model_pub = Pub(), Pub()
    return svc


def predictions(svc: BlenderService) -> dict[tuple[float, str], float]:
    return {(p.t, p.component): p.concentration_pct_w_w for p in svc.pub.sent}


def run(svc, flows, insert_at: float | None, msg) -> None:
    """The flows in order, ``msg`` handed over before the first flow at or after
    ``insert_at`` (None: first)."""
    sent = insert_at is None
    if sent:
        svc.handle(keys.rtd_estimate("line1"), msg)
    for k, f in flows:
        if not sent and f.t >= insert_at:
            svc.handle(keys.rtd_estimate("line1"), msg)
            sent = True
        svc.handle(k, f)


def test_an_estimate_applies_from_its_plant_time_whenever_it_arrives(tmp_path):
    """Without a gate (no rtd service running): the estimate applying from 200 s gives the same
    predictions whether it arrives first or at 150 s; the ticks before 200 s are those of the
    declared model, the later ones differ; arriving at 250 s it is applied from the tick after
    the last predicted (250 s: 51 s late), counted and its lateness kept."""
    spec = spec_for(tmp_path, ["feeder", "blender", "oos"])
    flows = feeder_flow_messages(spec, 400.0)
    ref, early, plain, late = (blender(spec, tmp_path / n) for n in ("r", "e", "p", "l"))
    run(ref, flows, None, estimate(200.0))
    run(early, flows, 150.0, estimate(200.0))
    run(plain, flows, math.inf, estimate(200.0))
    run(late, flows, 250.0, estimate(200.0))
    a, b, p, c = map(predictions, (ref, early, plain, late))
    assert a == b
    assert {k: v for k, v in a.items() if k[0] < 200.0} == {
        k: v for k, v in p.items() if k[0] < 200.0
    }
    assert a[(260.0, "api")] != p[(260.0, "api")]
    assert ref.counters.get("adopted_late") == 0 and early.counters.get("adopted_late") == 0
    assert late.counters.get("adopted_late") == 1
    assert late.counters.get("adopted_late_max_ms") == 50_000
    assert {k: v for k, v in c.items() if k[0] < 249.5} == {
        k: v for k, v in p.items() if k[0] < 249.5
    }


def test_flows_wait_for_the_producers_progress(tmp_path):
    """With the rtd service running, no tick is predicted past the rtd's reported progress; a
    progress report naming an update not yet received does not count until it arrives; the
    estimate then applies at its plant time even though the flows came long before it."""
    spec = spec_for(tmp_path, ["feeder", "blender", "rtd", "oos"])
    flows = feeder_flow_messages(spec, 400.0)
    ref = blender(spec_for(tmp_path, ["feeder", "blender", "oos"]), tmp_path / "ref")
    run(ref, flows, None, estimate(200.0))
    svc = blender(spec, tmp_path / "gated")
    for k, f in flows:
        svc.handle(k, f)
    assert svc.pub.sent == [] and svc.counters.get("held_for_adoption") == len(flows)
    progress = keys.adoption_progress("line1", "rtd")
    svc.handle(progress, AdoptionProgress(t=90.0, seq=0, complete_to_s=150.0))
    assert max(p.t for p in svc.pub.sent) == 150.0
    svc.handle(
        progress, AdoptionProgress(t=400.0, seq=1, complete_to_s=460.0, last_update_t_s=100.0)
    )
    assert max(p.t for p in svc.pub.sent) == 150.0  # the estimate of t=100 s is on its way
    svc.handle(keys.rtd_estimate("line1"), estimate(200.0))
    assert predictions(svc) == predictions(ref)
    assert svc.counters.get("adopted_late") == 0


def test_gate_keeps_each_keys_order_and_a_silent_producer_is_bypassed():
    gate = AdoptionGate(["rtd", "closeloop"])
    assert gate.complete_to_s == -math.inf

    class F:
        def __init__(self, t):
            self.t = t

    assert gate.hold("a", F(1.0)) and gate.hold("b", F(1.0)) and gate.hold("a", F(2.0))
    assert gate.report("rtd", 1.5, None) and gate.complete_to_s == -math.inf  # closeloop?
    assert gate.free() == []
    assert gate.report("closeloop", 5.0, None) and gate.complete_to_s == 1.5
    assert [(k, f.t) for k, f in gate.free()] == [("a", 1.0), ("b", 1.0)]
    assert len(gate) == 1
    assert not gate.stalled(60.0) and gate.stalled(-1.0)
    assert not gate.silent_for(-1.0, waiting_since=time.monotonic() + 10.0)
    assert [(k, f.t) for k, f in gate.release_all()] == [("a", 2.0)]
    assert gate.bypass and not gate.hold("a", F(9.0))
    assert gate.report("rtd", 20.0, None) and not gate.bypass
    assert not ProducerProgress([]).silent_for(-1.0)


def test_progress_report_is_monotone_across_a_restart(tmp_path):
    rep = ProgressReport(tmp_path / "rtd.progress", step_s=5.0)
    rep.advance(10.0, 70.0)  # no publisher yet: kept
    rep.pub = Pub()
    rep.advance(11.0, 71.0)
    rep.updated(11.0)
    rep.advance(20.0, 80.0)
    rep.flush()
    assert [(m.complete_to_s, m.last_update_t_s) for m in rep.pub.sent] == [
        (71.0, None),
        (80.0, 11.0),
    ]
    rep.close()
    again = ProgressReport(tmp_path / "rtd.progress", step_s=5.0)
    again.pub = Pub()
    again.advance(15.0, 75.0)
    again.flush()
    assert again.pub.sent == [] and again.sent == 80.0
    again.close()


@pytest.mark.parametrize("counter", ["window_errors", "fit_failed", "adopted_late"])
def test_report_lists_failures_skips_and_late_adoptions(counter):
    """``twin demo``'s report.md names every failure counter a service reported, with its last
    error, and every pulse without an estimate."""
    report = {
        "recording": "x.mcap",
        "recording_status": "complete",
        "messages_replayed": 10,
        "plant_span_s": 10.0,
        "timings_s": {"replay_wall_s": 1.0, "startup_s": 1.0, "total_s": 3.0},
        "speedup_achieved": 10.0,
        "predictions": 0,
        "prediction_error_pct_w_w": {"n": 0},
        "alerts": [],
        "divert_commands": [],
        "rtd_estimates": [],
        "rtd_skipped": [
            {"pulse_t_s": 900.0, "reason": "fit_failed", "detail": "profile area must be > 0"}
        ],
        "duplicates_seen": 0,
        "model_findings": [],
        "service_health": {
            "rtd": {"counters": {counter: 2}, "last_error": "profile area must be > 0"},
            "oos": {"counters": {"alerts": 1}, "last_error": None},
        },
    }
    md = report_markdown(report)
    assert f"- rtd: {counter}=2 (last error: profile area must be > 0)" in md
    assert "- oos" not in md
    assert "RTD pulse at 900.0 s without estimate (fit_failed)" in md
