"""The trace service as a shell (its ``handle`` and publications, no bus), and across a
restart."""

from __future__ import annotations

import numpy as np

from schemas.line import LineSpec
from services.recording import write_messages
from services.trace import trace_recording
from services.trace_service import TraceService
from twin_core.plant.messages import simulate_messages

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
    "services": ["feeder", "blender", "trace", "recorder"],
    "tracking": {"hopper": "mixed"},
}


class Pub:
    """Stands for the service's publisher: keeps what it is given."""

    def __init__(self) -> None:
        self.sent: list = []

    def publish(self, msg):
        self.sent.append(msg)
        return msg


def test_trace_service_publishes_the_lot_composition_of_every_tick(tmp_path):
    """Every tick one LotComposition whose lots equal twin trace's offline model on the same
    record (1e-12); a restarted service (same state directory, the history delivered again)
    publishes only the last republish_ticks again, with the same values."""
    spec = LineSpec.model_validate({**LINE, "state_dir": str(tmp_path)})
    run, msgs = simulate_messages(spec, 1200.0, 0)
    svc = TraceService(spec, install_signal_handlers=False)
    svc.pub = Pub()
    for k, m in msgs:
        svc.handle(k, m)
    svc.finish()
    sent = svc.pub.sent
    assert [m.t for m in sent] == list(run.t_s)
    assert "api-L0001" in {lot for m in sent for lot in m.lots}
    write_messages(tmp_path / "rec.mcap", msgs)
    _, trace = trace_recording(tmp_path / "rec.mcap", spec)
    frac = trace.fractions()
    for i, m in enumerate(sent):
        for j, lot in enumerate(trace.lots):
            want = frac[i, j] if frac[i, j] > 1e-6 else 0.0
            assert abs(m.lots.get(lot, 0.0) - want) < 1e-12
        assert abs(sum(m.lots.values()) - 1.0) < 1e-5
    again = TraceService(spec, install_signal_handlers=False)
    again.pub = Pub()
    for k, m in msgs:
        again.handle(k, m)
    again.finish()
    assert len(again.pub.sent) == again.republish_ticks
    for a, b in zip(again.pub.sent, sent[-len(again.pub.sent) :]):
        assert a.t == b.t and a.lots == b.lots
    assert np.isclose(sent[-1].outlet_kg_h, 12.0, rtol=0.05)


def test_trace_service_publishes_batch_boundaries_as_twin_batch_report_cuts(tmp_path):
    """With batch: (1 kg of product), the service publishes each batch's start and end at the
    ticks twin batch report cuts the same record at (twin_core.tracking.batches.batch_bounds)."""
    from twin_core.tracking.batches import batch_bounds

    spec = LineSpec.model_validate(
        {**LINE, "state_dir": str(tmp_path), "batch": {"by": "product_mass", "size": 1.0}}
    )
    _, msgs = simulate_messages(spec, 1200.0, 0)
    svc = TraceService(spec, install_signal_handlers=False)
    svc.pub, svc.batch_pub = Pub(), Pub()
    for k, m in msgs:
        svc.handle(k, m)
    svc.finish()
    write_messages(tmp_path / "rec.mcap", msgs)
    _, trace = trace_recording(tmp_path / "rec.mcap", spec)
    bounds = batch_bounds(trace, "product_mass", 1.0)
    t = trace.t_s
    want = []
    for b, (a, e, complete) in enumerate(bounds, start=1):
        want.append((b, "start", t[a]))
        if complete:
            want.append((b, "end", t[e - 1]))
    got = [(m.batch, m.boundary, m.t) for m in svc.batch_pub.sent]
    assert got == want
    assert len(bounds) == 5  # 12 kg/h: 1 kg every 300 ticks, then the last tick
    ends = [m for m in svc.batch_pub.sent if m.boundary == "end"]
    assert [int(m.total) for m in ends] == [1, 2, 3, 4]  # the tick that reaches k kg
