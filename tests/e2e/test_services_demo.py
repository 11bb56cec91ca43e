"""run_full_twin_demo on a short recording: report, figure, alerts of the known disturbance."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from schemas.line import LineSpec
from services.recording import write_messages
from services.twin_demo import run_full_twin_demo
from twin_core.plant.messages import simulate_messages

CONFIG = Path(__file__).resolve().parents[2] / "services" / "configs" / "line1.yaml"


def test_full_twin_demo_report_and_figure(tmp_path):
    """One feeder disturbance (traced window from seed Table 6.2's RTD) in a 10-minute run:
    one alert; predictions track the NIR to its noise (seed noise model, sd ~0.25 % w/w)."""
    spec = LineSpec.from_file(CONFIG)
    _, msgs = simulate_messages(
        spec,
        600.0,
        seed=21,
        disturbances=[{"feeder": "api", "t_s": 200.0, "delta_kg_h": 0.6, "duration_s": 30.0}],
    )
    rec = tmp_path / "short.mcap"
    write_messages(rec, msgs)
    out = tmp_path / "demo"
    report = run_full_twin_demo(rec, out, speed=100.0, echo=False)
    assert report["messages_replayed"] == len(msgs)
    assert [a["alert_id"] for a in report["alerts"]] == ["line1.api.feed-000000200000"]
    assert len(report["divert_commands"]) == 2 and report["duplicates_seen"] == 0
    assert report["predictions"] == 601
    err = report["prediction_error_pct_w_w"]
    assert abs(err["bias"]) < 0.1 and err["rmse"] < 0.4
    assert all(code == 0 for code in report["exit_codes"].values())
    assert json.loads((out / "report.json").read_text())["alerts"] == report["alerts"]
    assert (out / "outlet.png").stat().st_size > 10_000
    assert "line1.api.feed-000000200000" in (out / "report.md").read_text()
    assert np.isfinite(report["speedup_achieved"])
