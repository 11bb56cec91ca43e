"""`twin up` / `twin status` / `twin alerts` as a user runs them (separate processes).

`twin up` supervises the feeder service simulating its loss-in-weight feeders in real time
(twin_core.feeder) and the blender service; `twin status` sees them alive and working;
`twin alerts` prints nothing on a clean line; SIGTERM stops everything cleanly (exit 0, no
service process left).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from schemas.line import LineSpec
from services.bus import free_port

CONFIG = Path(__file__).resolve().parents[2] / "services" / "configs" / "line1.yaml"


def twin(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "services.cli.main", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("cli")
    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(
        bus={"mode": "router", "listen": [f"tcp/127.0.0.1:{free_port()}"], "connect": []},
        services=["feeder", "blender"],
        feeder_mode="simulate",
        state_dir=str(tmp / "state"),
    )
    path = tmp / "line.json"
    LineSpec.model_validate(data).to_file(path)
    return path


def test_up_status_alerts_and_clean_stop(config, tmp_path):
    log = (tmp_path / "up.log").open("w")
    up = subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "up", "--config", str(config)],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    try:
        status = {}
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            r = twin("status", "--config", str(config), "--json", "--timeout", "1.2")
            if r.returncode == 0:
                status = json.loads(r.stdout)
                blender = status.get("blender", {})
                if (
                    status.get("feeder", {}).get("alive")
                    and blender.get("alive")
                    and blender.get("counters", {}).get("published", 0) >= 4
                ):
                    break
            time.sleep(0.5)
        assert status["feeder"]["alive"] and status["blender"]["alive"], status
        assert status["blender"]["counters"]["published"] >= 4  # predictions flowing
        assert status["blender"]["state"] == "running"
        pids = [status[n]["pid"] for n in ("feeder", "blender")]
        r = twin("alerts", "--config", str(config), "--json", "--timeout", "1.0")
        assert r.returncode == 0 and r.stdout.strip() == ""
        up.send_signal(signal.SIGTERM)
        assert up.wait(timeout=30) == 0
        assert not any(alive(p) for p in pids)
        text = (tmp_path / "up.log").read_text()
        assert "ready" in text and "stopped" in text
    finally:
        if up.poll() is None:
            up.kill()
        log.close()


def running(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (an orphan reaped late by init is
    dead)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return alive(pid)
    return state not in ("Z", "X")


def test_no_orphan_after_kill_9_of_twin_up_and_one_twin_per_line(config, tmp_path):
    """A second `twin up` of a running line is refused in one line (exit 2); after SIGKILL of
    `twin up` its services stop by themselves (parent-death signal), none is left running, and
    no lock is left held."""
    log = (tmp_path / "up.log").open("w")
    up = subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "up", "--config", str(config)],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    pids: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(pids) < 2:
            r = twin("status", "--config", str(config), "--json", "--timeout", "1.2")
            if r.returncode == 0:
                status = json.loads(r.stdout)
                pids = [
                    status[n]["pid"] for n in ("feeder", "blender") if "pid" in status.get(n, {})
                ]
            time.sleep(0.5)
        assert len(pids) == 2, "services not up"
        second = twin("up", "--config", str(config))
        assert second.returncode == 2
        [line] = second.stderr.strip().splitlines()
        assert line.startswith("error: a twin of line line1 is already running, pid ")
        up.send_signal(signal.SIGKILL)
        up.wait(timeout=10)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and any(running(p) for p in pids):
            time.sleep(0.2)
        assert not any(running(p) for p in pids), [p for p in pids if running(p)]
    finally:
        if up.poll() is None:
            up.kill()
        for p in pids:
            if running(p):
                os.kill(p, signal.SIGKILL)
        log.close()
