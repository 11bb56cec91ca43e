"""The live twin's decisions on the issue's clean record, started as users start it.

`twin plant simulate --disturbance api:1800:0.6:30` (no hidden effect) replayed into `twin up`
with the shipped `line1.yaml` (secured bus, every service, the live close-loop) used to divert
the disturbance's window and also 1050-2100 s of good product: the live close-loop claimed a
sensor gain and a sensor offset in an effect-free record and put the product at risk.
Reference: the plant simulator's truth (the true outlet API content, no hidden effect); the
scoring is ``benchmarks/live_decisions.py``'s (what the gate diverted from each command's
decision time on). The record is 45 minutes long here (the issue's 1 h cut to the windows that
claimed: 600 s and 2100 s).
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from schemas.line import LineSpec
from services.recording import write_messages
from twin_core.plant.messages import simulate_messages

ROOT = Path(__file__).resolve().parents[2]
BENCH = ROOT / "benchmarks" / "live_decisions.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("live_decisions", BENCH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["live_decisions"] = mod
    spec.loader.exec_module(mod)
    return mod


def test_a_clean_record_with_one_disturbance_diverts_only_its_window(bench, tmp_path):
    spec = LineSpec.from_file(bench.LINE)
    dist = [{"feeder": "api", "t_s": 1800.0, "delta_kg_h": 0.6, "duration_s": 30.0}]
    run, msgs = simulate_messages(spec, 2700.0, seed=0, disturbances=dist)
    rec = tmp_path / "plant.mcap"
    write_messages(rec, msgs)
    live, _ = bench.live_run(rec, tmp_path, speed=200.0)
    info = {"family": "ordinary", "case": "issue", "disturbances": [(1800.0, 1830.0)]}
    row = bench.score(run, info, live, spec)
    assert row["oos_kg"] > 0.1  # the disturbance puts product out of specification
    assert row["missed_oos_kg"] == 0.0, row
    assert row["stray_divert_s"] == 0.0, row  # nothing diverted outside its RTD window
    assert row["adopted"] == [] and row["product_at_risk"] == 0, row
    # good product diverted: the padded excursion's margins only (< 30 s of production)
    assert row["false_divert_kg"] < 30.0 * 12.0 / 3600.0, row
    # the run's audit trail is in its recording, whole: every service started, the alert and
    # its divert commands, the trail's end (services.audit; HMAC-SHA256, RFC 2104)
    from services.audit import read_key, verify_trail
    from services.recording import read_recording

    trail = [m.payload for m in read_recording(live).messages if m.key.endswith("/audit/record")]
    verdict = verify_trail(trail, read_key(tmp_path / "state" / "audit.key"))
    assert verdict.ok, verdict.problem
    actions = [json.loads(p)["action"] for p in trail]
    assert actions[:2] == ["trail_start", "config_loaded"] and actions[-1] == "trail_end"
    assert actions.count("service_start") == len(spec.services)
    assert "alert" in actions and "divert_command" in actions
    # every decision names the version of the model it was made with: the blender's
    rec = read_recording(live)
    versions: dict[str, set] = {}
    ends = ("/blender/outlet/predicted", "/oos/alert", "/divert/command", "/model_in_use")
    for m in rec.messages:
        if m.key.endswith(ends):
            name = m.key.split("/")[-1]
            versions.setdefault(name, set()).add(json.loads(m.payload).get("model_version"))
    (model,) = versions["predicted"]
    assert versions["alert"] == {model} and versions["command"] == {model}, versions
    assert versions["model_in_use"] == {model}
