"""twin trace and twin batch report on a simulated record whose refills carry lot ids and one
API lot of 90 % of label (docs/traceability.md)."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from schemas import keys
from schemas.closeloop import ModelFinding
from schemas.line import LineSpec
from schemas.messages import DivertCommand, OosAlert
from services.cli.main import main
from services.recording import write_messages
from twin_core.plant.messages import simulate_messages
from twin_core.plant.model import LineModel
from twin_core.tracking.assay import LotAssay

LINE = {
    "name": "line1",
    "dt_s": 1.0,
    "feeders": [
        {
            "id": "api",
            "component": "api",
            "setpoint_kg_h": 1.2,
            "liw": {"initial_mass_kg": 0.8, "refill_low_kg": 0.4, "refill_high_kg": 0.8},
        },
        {"id": "excipient", "component": "excipient", "setpoint_kg_h": 10.8, "ideal": True},
    ],
    "blender": {"kind": "rtd"},
    "sensor": {"id": "nir1", "component": "api"},
    "spec": [
        {"component": "api", "target_pct_w_w": 10.0, "lower_pct_w_w": 9.5, "upper_pct_w_w": 10.5}
    ],
    "batch": {"by": "product_mass", "size": 5.0},
}


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    """1 h of the line: the API hopper refilled every ~20 min (lots api-L0001..), lot
    api-L0001 at 90 % of label in the truth; a copy with an alert and its divert command."""
    tmp = tmp_path_factory.mktemp("trace")
    spec = LineSpec.model_validate(LINE)
    cfg = tmp / "line.json"
    spec.to_file(cfg)
    run, msgs = simulate_messages(spec, 3600.0, 0, lot_assays=[LotAssay("api", "api-L0001", 0.9)])
    plain = tmp / "plain.mcap"
    write_messages(plain, msgs)
    alert = OosAlert(
        t=2000.0,
        seq=0,
        alert_id="a1",
        component="api",
        t_start_s=1990.0,
        t_end_s=2000.0,
        peak_deviation_pct_w_w=-0.8,
        limit_pct_w_w=0.5,
        cause="lot api-L0001 low assay",
    )
    cmd = DivertCommand(
        t=2000.0,
        seq=0,
        command_id="d1",
        action="divert",
        t_start_s=1990.0,
        t_end_s=2050.0,
        alert_id="a1",
        reason="predicted outlet below the limit",
        model_version="0123456789abcdef",
    )
    w = {"rmse": 0.1, "mae": 0.1, "n": 10}
    finding = ModelFinding(
        t=2400.0,
        seq=0,
        finding_id="line1.closeloop-2400000",
        status="data_quality",
        t_start_s=1200.0,
        t_end_s=2400.0,
        errors={"before": {"train": w, "heldout": w}, "after": {"train": w, "heldout": w}},
        data_quality=[
            {
                "kind": "stuck",
                "series": "nir",
                "t_start_s": 2100.0,
                "t_end_s": 2160.0,
                "n_samples": 60,
            }
        ],
    )
    extra = [
        (keys.oos_alert("line1"), alert),
        (keys.divert_command("line1"), cmd),
        (keys.model_finding("line1"), finding),
    ]
    decided = tmp / "decided.mcap"
    write_messages(decided, sorted([*msgs, *extra], key=lambda km: km[1].t))
    return cfg, plain, decided, run


def test_refills_carry_lot_ids(record):
    _, _, _, run = record
    starts = [e for e in run.events if e.kind == "refill_start" and e.source == "api"]
    assert [e.lot_id for e in starts][:2] == ["api-L0001", "api-L0002"]


def test_trace_a_lot_lists_its_product_and_its_content_deviation(record, capsys):
    """The lot's interval holds what of it left (the rest is in the hopper at the end), the
    recall covers >= 99.9 % of it,
    and the predicted content deviation from its assay (Eq. (2) of twin_core.tracking.assay)
    matches the truth's outlet to 0.02 % w/w where it leaves."""
    cfg, plain, _, run = record
    rc = main(
        [
            "trace",
            str(plain),
            "--config",
            str(cfg),
            "--lot",
            "api-L0001",
            "--json",
            "--assay",
            "api-L0001:0.9",
        ]
    )
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["coverage"] >= 0.999
    assert len(out["intervals"]) == 1
    iv = out["intervals"][0]
    assert iv["lot_kg"] == pytest.approx(out["lot_mass_out_kg"], rel=0.001)
    assert out["lot_mass_in_kg"] == pytest.approx(0.4, abs=0.02)  # refill 0.4 -> 0.8 kg
    assert 0.9 * out["lot_mass_in_kg"] < out["lot_mass_out_kg"] <= out["lot_mass_in_kg"]
    assert iv["batches"]
    dev = out["content_deviation_pct_w_w"]
    # the truth's lot effect: its outlet minus the declared model's on the reported flows
    truth = run.outlet_true_pct_w_w["api"] - LineModel(run.config).outlet(run.inputs())["api"]
    k = int(np.argmin(truth))
    assert dev["max"] == pytest.approx(truth[k], abs=0.02)
    assert abs(dev["t_s"] - run.t_s[k]) <= 60.0
    assert iv["t_start_s"] <= run.t_s[k] <= iv["t_end_s"]


def test_trace_at_a_time_gives_the_composition(record, capsys):
    cfg, plain, _, _ = record
    rc = main(["trace", str(plain), "--config", str(cfg), "--at", "600", "--json"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    lots = {r["lot"]: r for r in out["lots"]}
    assert out["batch"] == 1
    assert lots["api-L0000"]["component_fraction"] == pytest.approx(1.0)
    assert lots["api-L0000"]["fraction"] == pytest.approx(0.1, abs=0.01)
    assert sum(r["fraction"] for r in out["lots"]) == pytest.approx(1.0, abs=1e-5)


def test_batch_report_of_plant_data_only(record, tmp_path, capsys):
    cfg, plain, _, _ = record
    assert main(["batch", "report", str(plain), "--config", str(cfg), "--out", str(tmp_path)]) == 0
    index = json.loads((tmp_path / "batches.json").read_text())
    assert len(index) == 3 and index[1]["complete"] and not index[2]["complete"]
    assert index[0]["product_kg"] == pytest.approx(5.0, abs=0.02)
    rec = json.loads((tmp_path / "batch_001.json").read_text())
    assert rec["recording"]["sha256"] == hashlib.sha256(plain.read_bytes()).hexdigest()
    assert sum(x["mass_kg"] for x in rec["lots"]) == pytest.approx(rec["product_kg"], rel=1e-9)
    assert not rec["decisions_recorded"] and "plant data only" in rec["note"]
    page = (tmp_path / "batch_001.html").read_text()
    assert "api-L0000" in page and rec["recording"]["sha256"] in page


def test_batch_report_quotes_the_recorded_divert_window_and_alert(record, tmp_path):
    cfg, _, decided, _ = record
    assert (
        main(["batch", "report", str(decided), "--config", str(cfg), "--out", str(tmp_path)]) == 0
    )
    recs = [json.loads(p.read_text()) for p in sorted(tmp_path.glob("batch_0*.json"))]
    wins = [w for r in recs for w in r["divert_windows"]]
    assert [w["alert_cause"] for w in wins] == ["lot api-L0001 low assay"]
    assert [w["model_version"] for w in wins] == ["0123456789abcdef"]
    assert sum(r["diverted_kg"] for r in recs) == pytest.approx(12.0 * 61 / 3600, rel=0.02)
    assert any(r["oos_episodes"] for r in recs)
    dq = [q for r in recs for q in r["data_quality_periods"]]
    assert [(q["kind"], q["series"], q["t_start_s"]) for q in dq] == [("stuck", "nir", 2100.0)]
    assert any(r["closeloop_findings"] for r in recs)
    assert all(r["decisions_recorded"] for r in recs)


def test_trace_with_a_wanted_coverage(record, capsys):
    cfg, plain, _, _ = record
    argv = ["trace", str(plain), "--config", str(cfg), "--lot", "api-L0001", "--json"]
    assert main([*argv, "--coverage", "0.9995"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["coverage"] >= 0.9995 and out["threshold"] > 1e-3


def test_the_demo_recording_in_batches_with_their_lots(tmp_path):
    """twin demo's report lists each batch with its lots (services.twin_demo._batches, on the
    live twin's recording; here the bundled one: plant data only): 10 min batches by run time,
    the excipient's refill lot entering in the third."""
    from pathlib import Path

    from services.batch_report import batches_markdown, batches_of_recording
    from services.recording import read_recording
    from services.twin_demo import spec_for_recording

    bundled = Path(__file__).resolve().parents[2] / "recordings" / "line1_30min.mcap"
    spec = spec_for_recording(read_recording(bundled), 7999, tmp_path / "state")
    rows = batches_of_recording(bundled, spec, tmp_path / "batches")
    assert [r["complete"] for r in rows][:3] == [True, True, True]
    assert [x["lot"] for x in rows[0]["lots"]] == ["api-L0000", "excipient-L0000"]
    assert "excipient-L0001" in [x["lot"] for x in rows[2]["lots"]]
    assert (tmp_path / "batches" / "batch_003.html").is_file()
    text = "\n".join(batches_markdown(rows))
    assert "## Batches" in text and "excipient-L0001" in text


def test_refills_from_the_refill_flag_when_no_event_names_them(record, tmp_path, capsys):
    """A feed without refill events (an OPC UA or historian feed: only FeederFlow.refilling)
    gives the same lots, unnamed lots numbered as the simulator names them: the recall of
    api-L0001 within 2 s and 0.5 % of the recall from the events."""
    from services.recording import read_recording

    cfg, plain, _, _ = record
    rec = read_recording(plain)
    msgs = [(m.key, m.decode()) for m in rec.messages if not m.key.endswith("/event")]
    flags = tmp_path / "flags.mcap"
    write_messages(flags, msgs)
    out = []
    for path in (plain, flags):
        argv = ["trace", str(path), "--config", str(cfg), "--lot", "api-L0001", "--json"]
        assert main(argv) == 0
        out.append(json.loads(capsys.readouterr().out)["intervals"])
    (a,), (b,) = out
    assert abs(a["t_start_s"] - b["t_start_s"]) <= 2 and abs(a["t_end_s"] - b["t_end_s"]) <= 2
    assert b["lot_kg"] == pytest.approx(a["lot_kg"], rel=0.005)


def test_the_bundled_lots_recording_answers_the_readme(capsys):
    """README 'Which product contains lot X': recordings/line1_lots_1h.mcap with
    services/configs/line1_lots.yaml gives the intervals and numbers the README quotes."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    argv = [
        "trace",
        str(root / "recordings" / "line1_lots_1h.mcap"),
        "--config",
        str(root / "services" / "configs" / "line1_lots.yaml"),
        "--lot",
        "api-L0001",
        "--assay",
        "api-L0001:0.9",
        "--json",
    ]
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    [iv] = out["intervals"]
    assert (iv["t_start_s"], iv["t_end_s"], iv["batches"]) == (2415.0, 3600.0, [3, 4])
    assert iv["lot_kg"] == pytest.approx(0.391, abs=0.001)
    assert iv["product_kg"] == pytest.approx(3.96, abs=0.01)
    assert out["content_deviation_pct_w_w"]["max"] == pytest.approx(-1.02, abs=0.01)
