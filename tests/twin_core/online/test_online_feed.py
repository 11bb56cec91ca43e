"""The twin refuses a feed that does not match its line (issue: the README's own workflow gave
a whole-run alert of +130 % w/w when the 5 % bundled recording was fed to the 10 % line)."""

from __future__ import annotations

from pathlib import Path

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import FeederFlow, MeasuredConcentration
from services.oos import OosService
from services.recording import read_recording, recording_mismatches
from twin_core.online.feed import FeedCheck

ROOT = Path(__file__).resolve().parents[3]
BUNDLED = ROOT / "recordings" / "line1_30min.mcap"
LINE1 = ROOT / "services" / "configs" / "line1.yaml"
LINE1_5PCT = ROOT / "services" / "configs" / "line1_5pct.yaml"


def flow(t: float, component: str, setpoint: float) -> FeederFlow:
    return FeederFlow(
        t=t,
        seq=int(t),
        component=component,
        mass_flow_kg_h=setpoint,
        setpoint_kg_h=setpoint,
        screw_speed_rpm=100.0,
        hopper_mass_kg=5.0,
        feed_factor_g_rev=1.0,
    )


def test_the_bundled_recording_matches_its_config_and_not_the_10_percent_line():
    """Provenance and first flows of the 5 % recording (0.6 + 11.4 kg/h) against line1.yaml
    (1.2 + 10.8 kg/h): both set points named with both values; line1_5pct.yaml matches."""
    rec = read_recording(BUNDLED)
    found = {m.field: m for m in recording_mismatches(rec, LineSpec.from_file(LINE1))}
    assert set(found) == {"feeders.api.setpoint_kg_h", "feeders.excipient.setpoint_kg_h"}
    assert abs(found["feeders.api.setpoint_kg_h"].fed - 0.6) < 1e-9
    assert found["feeders.api.setpoint_kg_h"].configured == 1.2
    assert recording_mismatches(rec, LineSpec.from_file(LINE1_5PCT)) == []


def test_first_messages_are_checked_once_per_feeder_and_sensor():
    check = FeedCheck(LineSpec.from_file(LINE1))
    [m] = check.flow("api", "excipient", 1.2)
    assert (m.field, m.fed, m.configured) == ("feeders.api.component", "excipient", "api")
    assert check.flow("api", "excipient", 1.2) == []  # only the first message of a feeder
    assert check.flow("excipient", "excipient", 10.8) == []
    assert [x.field for x in check.measured("nir2", "api")] == ["sensor.id"]
    assert len(check.mismatches) == 2


def test_the_diverter_refuses_a_mismatching_feed_before_any_decision(tmp_path):
    spec = LineSpec.from_file(LINE1)
    spec.state_dir = str(tmp_path)
    svc = OosService(spec, install_signal_handlers=False)
    emitted = []
    svc.emit = emitted.extend
    for t in range(5):
        svc.handle(keys.feeder_flow("line1", "api"), flow(float(t), "api", 0.6))
        svc.handle(keys.feeder_flow("line1", "excipient"), flow(float(t), "excipient", 11.4))
        m = MeasuredConcentration(
            t=float(t), seq=t, sensor="nir1", component="api", concentration_pct_w_w=5.0
        )
        svc.handle(keys.measured_concentration("line1", "nir1"), m)
    assert emitted == []
    assert svc.counters.get("rejected_mismatch") == 15
    assert "feeders.api.setpoint_kg_h: fed 0.6, configured 1.2" in svc.refusal
