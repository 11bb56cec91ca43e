"""Nobody goes blind: `twin alerts --json` and `twin record` started before a restart of the
twin (`twin up` stopped and started again: a new run, new credentials) say at once that they
lost it, reconnect to the new run, and miss nothing: every alert of both runs printed exactly
once, every plant message of both runs recorded once (separate processes, secured bus, free
port)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from schemas import keys
from schemas.line import LineSpec
from services.bus import free_port
from services.recording import read_recording

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "services" / "configs" / "line1_5pct.yaml"
TWIN = [sys.executable, "-m", "services.cli.main"]
ENV = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(ROOT)}
#: the recordings' feeder disturbances (plant time, s): one in the first run, two in the second
FIRST = ["api:100:0.6:30"]
SECOND = ["api:150:0.6:30", "api:220:0.6:20"]


def twin(*args: str, cwd: Path, timeout: float = 120.0) -> subprocess.CompletedProcess:
    r = subprocess.run(
        [*TWIN, *args], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=ENV
    )
    assert r.returncode == 0, r.stderr
    return r


def start(args: list[str], cwd: Path, out: Path, err: Path | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        [*TWIN, *args],
        cwd=cwd,
        stdout=out.open("w"),
        stderr=err.open("w") if err else subprocess.STDOUT,
        env=ENV,
    )


def wait_until(check, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def up(config: Path, cwd: Path, log: Path) -> subprocess.Popen:
    proc = start(["up", "--config", str(config)], cwd, log)
    wait_until(lambda: " ready; run dir" in log.read_text(), 120, f"twin up ({log.read_text()})")
    return proc


def stop(proc: subprocess.Popen) -> int | None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
    return proc.returncode


def test_alerts_and_recorder_survive_a_restart_of_the_twin(tmp_path):
    """Run 1 replays a recording with one feeder disturbance, the twin is stopped (SIGTERM) and
    started again (new run directory, new passwords), run 2 replays one with two: `twin alerts`
    says within 5 s that it lost the twin and that it reconnected, prints the three alerts once
    each; `twin record` holds every plant message of both replays once."""
    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(
        bus={"mode": "router", "listen": [f"tcp/127.0.0.1:{free_port()}"], "connect": []},
        services=["oos"],
        state_dir=str(tmp_path / "state"),
    )
    config = tmp_path / "line.json"
    LineSpec.model_validate(data).to_file(config)
    recs = []
    for name, seed, dists in (("a", 0, FIRST), ("b", 1, SECOND)):
        rec = tmp_path / f"{name}.mcap"
        args = ["plant", "simulate", "--config", str(config), "--out", str(rec), "--seed"]
        twin(*args, str(seed), "--duration", "300", *sum((["--disturbance", d] for d in dists), []),
             cwd=tmp_path)  # fmt: skip
        recs.append(rec)
    alerts_out, alerts_err = tmp_path / "alerts.out", tmp_path / "alerts.err"
    record_log = tmp_path / "record.log"
    procs: list[subprocess.Popen] = []
    try:
        first = up(config, tmp_path, tmp_path / "up1.log")
        procs.append(first)
        alerts = start(
            ["alerts", "--json", "--config", str(config)], tmp_path, alerts_out, alerts_err
        )
        recorder = start(["record", str(tmp_path / "out.mcap"), "--config", str(config)],
                         tmp_path, record_log)  # fmt: skip
        procs += [alerts, recorder]
        wait_until(lambda: "ready" in record_log.read_text(), 60, "the recorder")
        twin("replay", str(recs[0]), "--config", str(config), "--speed", "50", cwd=tmp_path)
        wait_until(lambda: len(alerts_out.read_text().splitlines()) >= 1, 60, "the first alert")

        assert stop(first) == 0
        stopped = time.monotonic()
        wait_until(lambda: "lost the twin" in alerts_err.read_text(), 10, "alerts: lost")
        lost_after = time.monotonic() - stopped
        wait_until(lambda: "lost the twin" in record_log.read_text(), 10, "record: lost")

        second = up(config, tmp_path, tmp_path / "up2.log")
        procs.append(second)
        wait_until(lambda: "reconnected" in alerts_err.read_text(), 30, "alerts: reconnected")
        wait_until(lambda: "reconnected" in record_log.read_text(), 30, "record: reconnected")
        twin("replay", str(recs[1]), "--config", str(config), "--speed", "50", cwd=tmp_path)
        wait_until(lambda: len(alerts_out.read_text().splitlines()) >= 3, 60, "three alerts")
        time.sleep(1.0)  # nothing more may come
        assert stop(alerts) == 0
        assert stop(recorder) == 0
        assert stop(second) == 0
    finally:
        for p in procs:
            stop(p)
    assert lost_after < 5.0
    err = alerts_err.read_text().strip().splitlines()
    assert [line.split(":")[0] for line in err] == ["twin alerts", "twin alerts"], err
    assert "lost the twin of line line1" in err[0] and "reconnected" in err[1]
    ids = [json.loads(line)["alert_id"] for line in alerts_out.read_text().splitlines()]
    assert sorted(ids) == [
        "line1.api.feed-000000100000",
        "line1.api.feed-000000150000",
        "line1.api.feed-000000220000",
    ]
    got: dict[str, list[bytes]] = {}
    for m in read_recording(tmp_path / "out.mcap").messages:
        if not keys.is_service_key(m.key):
            got.setdefault(m.key, []).append(m.payload)
    sent: dict[str, list[bytes]] = {}
    for rec in recs:
        for m in read_recording(rec).messages:
            sent.setdefault(m.key, []).append(m.payload)
    for key, payloads in sent.items():
        assert sorted(got.get(key, [])) == sorted(payloads), key
