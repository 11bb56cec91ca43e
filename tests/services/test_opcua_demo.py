"""``twin demo --opcua``: the whole live twin fed through the OPC UA bridge from the loopback
OPC UA plant gives the same alerts, divert commands and RTD estimates as the twin fed by the
bus replay (the seed's pulse at 300 s of the bundled recording, its first 400 s), and the
diverter's commands are written back to the plant's gate node."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.recording import read_recording, write_messages
from services.twin_demo import run_full_twin_demo

ROOT = Path(__file__).resolve().parents[2]
SPAN_S = 400.0

pytestmark = pytest.mark.e2e


def test_the_twin_through_opcua_equals_the_replayed_twin(tmp_path):
    rec = read_recording(ROOT / "recordings" / "line1_30min.mcap")
    cut = tmp_path / "first.mcap"
    write_messages(cut, [(m.key, m.decode()) for m in rec.messages if m.t <= SPAN_S])
    runs = {
        feed: run_full_twin_demo(cut, tmp_path / feed, speed=100, echo=False, opcua=feed == "opcua")
        for feed in ("replay", "opcua")
    }
    replayed, bridged = runs["replay"], runs["opcua"]
    assert replayed["alerts"], "the pulse at 300 s gives an alert"
    assert bridged["alerts"] == replayed["alerts"]
    key = lambda d: d["command_id"]  # noqa: E731
    assert sorted(bridged["divert_commands"], key=key) == sorted(
        replayed["divert_commands"], key=key
    )
    assert bridged["rtd_estimates"] == replayed["rtd_estimates"]
    assert bridged["predictions"] == replayed["predictions"]
    assert bridged["divert_commands_written_to_gate"] == len(bridged["divert_commands"])
    assert all(code == 0 for code in bridged["exit_codes"].values())
    assert bridged["duplicates_seen"] == 0
