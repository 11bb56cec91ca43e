"""`twin demo`'s replay/record check and the bundled recording (30 min synthetic line run)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from schemas import keys
from schemas.line import LineConfig
from schemas.messages import FeederFlow
from services.demo import BUNDLED_RECORDING, run_replay_check
from services.recording import McapRecorder, load_line_data, read_recording

ROOT = Path(__file__).resolve().parents[2]


def test_replay_check_on_bundled_recording_captures_everything(tmp_path):
    result = run_replay_check(
        BUNDLED_RECORDING, as_fast_as_possible=True, capture=tmp_path / "cap.mcap", timeout_s=120
    )
    assert result.ok, result.summary()
    assert result.source_total == result.captured_total == 5408
    assert "capture equals source" in result.summary()
    cap = read_recording(tmp_path / "cap.mcap")
    assert [m.payload for m in cap.messages] == [
        m.payload for m in read_recording(BUNDLED_RECORDING).messages
    ]


def test_replay_check_reports_invalid_source_messages(tmp_path):
    src = tmp_path / "src.mcap"
    key = keys.feeder_flow("line1", "api")
    with McapRecorder(src) as rec:
        for i in range(20):
            rec.write_message(
                key,
                FeederFlow(
                    t=i,
                    seq=i,
                    component="api",
                    mass_flow_kg_h=1,
                    screw_speed_rpm=1,
                    hopper_mass_kg=1,
                    feed_factor_g_rev=1,
                ),
            )
        rec.write(key, b'{"t": 20.0, "seq": 20}', 20.0)  # schema violation
    result = run_replay_check(src, as_fast_as_possible=True, capture=tmp_path / "c.mcap")
    assert not result.ok
    assert result.source_counts == {key: 20} and result.captured_counts == {key: 20}
    assert "invalid messages" in result.problems[0] and "rejected_schema" in result.problems[0]
    assert "FAILED" in result.summary()


def test_bundled_recording_content():
    """30 min at 12 kg/h in total, one refill, NIR at 1 Hz with noise, three tracer pulses of the
    seed's masses (docs/seed.md: 10 / 7.5 / 6 / 5 g pulses; noise types white, pink,
    proportional, outliers), under 2 MB."""
    assert BUNDLED_RECORDING.stat().st_size < 2_000_000
    rec = read_recording(BUNDLED_RECORDING)
    assert not rec.truncated and rec.duration_s == 1800.0
    signals, events = load_line_data(BUNDLED_RECORDING)
    conc = signals["conc_nir1_api_pct_w_w"].dropna()
    assert len(conc) == 1801 and np.allclose(np.diff(conc.index), 1.0)
    total = signals["total_flow_kg_h"].dropna()
    assert abs(total.mean() - 12.0) < 0.25
    pulses = events[events.kind == "tracer_pulse"]
    assert list(pulses.mass_kg * 1000) == [10.0, 7.5, 5.0]
    assert (events.kind == "refill_start").sum() == 1 and (events.kind == "refill_stop").sum() == 1
    refill = events[events.kind == "refill_start"].iloc[0]
    assert (
        signals.loc[np.ceil(refill.t_s) : refill.t_s + 5, f"refilling_{refill.source}"].max() == 1
    )
    # each pulse shows at the outlet after the blender's delay; the baseline is noisy
    for t_p in pulses.t_s:
        window = conc.loc[t_p : t_p + 120]
        assert window.idxmax() > t_p + 10 and window.max() > conc.loc[t_p - 60 : t_p].mean() + 3
    baseline = conc.loc[10:290]
    assert 0.05 < baseline.std() < 0.5
    assert len(np.unique(np.round(baseline.to_numpy(), 4))) > 200


def test_bundled_recording_script_is_reproducible(tmp_path):
    """The script regenerates the recording byte for byte (seeded)."""
    spec = importlib.util.spec_from_file_location(
        "make_bundled_recording", ROOT / "recordings" / "make_bundled_recording.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    a = module.make(tmp_path / "a.mcap")
    b = module.make(tmp_path / "b.mcap")
    assert a.read_bytes() == b.read_bytes()
    # the 1 Hz channels match the bundled file (event counts follow the plant simulator)
    regenerated, bundled = read_recording(a).channels, read_recording(BUNDLED_RECORDING).channels
    for key in ("twin/line1/feeder/api/flow", "twin/line1/pat/nir1/concentration"):
        assert regenerated[key].message_count == bundled[key].message_count == 1801
    # the provenance holds the declared line, which loads as the one line configuration model
    configs = [
        LineConfig.model_validate(json.loads(_metadata(p)["provenance"]["line_config"]))
        for p in (a, BUNDLED_RECORDING)
    ]
    assert configs[0] == configs[1]
    assert [f.id for f in configs[1].feeders] == ["api", "excipient"]
    assert [p.mass_kg for p in configs[1].tracers] == [0.01, 0.0075, 0.005]


def _metadata(path: Path) -> dict[str, dict[str, str]]:
    """The MCAP metadata records of a file, by name."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}


def test_twin_demo_cli(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "services.cli.main",
            "demo",
            "--as-fast-as-possible",
            "--capture",
            str(tmp_path / "cap.mcap"),
            "--out",
            str(tmp_path / "demo"),
        ],
        capture_output=True,
        text=True,
        timeout=400,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "RESULT: capture equals source, message for message" in r.stdout
    assert (tmp_path / "cap.mcap").exists()
    # step 2: the live twin on the same recording, with its report and figure
    report = json.loads((tmp_path / "demo" / "report.json").read_text())
    assert report["recording_status"].startswith("complete")
    assert report["predictions"] > 1000 and report["duplicates_seen"] == 0
    # the bundled recording's only excursions are its three tracer pulses (300, 900, 1,500 s):
    # each raises an alert, and none is raised outside the pulses' passage (120 s each)
    pulses = (300.0, 900.0, 1500.0)
    starts = [a["t_start_s"] for a in report["alerts"]]
    assert all(any(p <= t <= p + 120.0 for p in pulses) for t in starts), starts
    assert all(any(p <= t <= p + 120.0 for t in starts) for p in pulses), starts
    # the report compares the live (compartment) blender with the seed's Table 6.2 AD
    assert report["blender_model"] == "compartment"
    assert report["reference_prediction_error_pct_w_w"]["n"] > 1000
    assert [m["reason"] for m in report["models_in_use"]][0] == "start"
    assert (tmp_path / "demo" / "outlet.png").stat().st_size > 10_000
    # in the words of the plant: the alerts are the tracer pulses, named as such; each status of
    # the close-loop's windows is explained; the two blenders' errors with why they differ
    md = (tmp_path / "demo" / "report.md").read_text()
    assert all(a["cause"].startswith("tracer pulse of api (") for a in report["alerts"])
    assert "inlet disturbance" not in md
    assert f"OOS alerts: {len(report['alerts'])} ({len(report['alerts'])} tracer pulses)" in md
    for status in {f["status"] for f in report["model_findings"]}:
        assert f"- `{status}` (" in md
    why = report["blender_comparison"]
    assert why["pulses"] == 3 and why["excess_share_in_pulses"] > 0.5
    assert "mean residence time" in why["text"] and f"why they differ: {why['text']}" in md
