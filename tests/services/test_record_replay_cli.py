"""`twin record OUT.mcap` + `twin replay REC.mcap` as the README shows them (separate processes).

With a running, secured `twin up` (found through the run's lock file in the working directory,
as `twin alerts` finds it) the recorder captures every plant message the replay sends, byte for
byte, and `--idle-timeout` stops it once the plant is quiet although the services' health goes
on. Without a twin, record and replay meet peer to peer on the line's endpoint; a replay that
finds nobody is a one-line error, exit 2. The idle clock counts plant messages only, not the
health of the recorder or of other tools.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from schemas import keys
from schemas.bus_config import BusConfig
from schemas.line import LineSpec
from schemas.messages import MeasuredConcentration, ServiceHealth
from services.bus import Publisher, free_port, open_session
from services.recording import read_recording, record_bus

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "services" / "configs" / "line1_5pct.yaml"
TWIN = [sys.executable, "-m", "services.cli.main"]
ENV = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(ROOT)}


def line_config(folder: Path, services: list[str]) -> Path:
    """The 5 % line on a free port, its state in ``.twin-state`` of the working directory (the
    default of `line1.yaml`: the tools started there without --config find the twin)."""
    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(
        bus={"mode": "router", "listen": [f"tcp/127.0.0.1:{free_port()}"], "connect": []},
        services=services,
        state_dir=".twin-state",
    )
    path = folder / "line.json"
    LineSpec.model_validate(data).to_file(path)
    return path


def simulate(folder: Path, config: Path, duration: float = 120.0) -> Path:
    out = folder / "rec.mcap"
    r = subprocess.run(
        [*TWIN, "plant", "simulate", "--config", str(config), "--out", str(out)]
        + ["--duration", str(duration)],
        cwd=folder,
        capture_output=True,
        text=True,
        timeout=120,
        env=ENV,
    )
    assert r.returncode == 0, r.stderr
    return out


def plant_payloads(path: Path) -> dict[str, list[bytes]]:
    """The payloads of a recording per plant key (the services' own keys left out)."""
    out: dict[str, list[bytes]] = {}
    for m in read_recording(path).messages:
        if not keys.is_service_key(m.key):
            out.setdefault(m.key, []).append(m.payload)
    return out


def start(args: list[str], cwd: Path, log: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [*TWIN, *args], cwd=cwd, stdout=log.open("w"), stderr=subprocess.STDOUT, env=ENV
    )


def wait_for(path: Path, text: str, timeout: float, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if text in path.read_text():
            return
        assert proc.poll() is None, path.read_text()
        time.sleep(0.2)
    raise AssertionError(f"{text!r} not seen in {path}: {path.read_text()}")


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()


def test_record_and_replay_of_the_readme_capture_every_plant_message(tmp_path):
    """`twin up` (secured) runs; `twin record OUT.mcap --idle-timeout 3` and `twin replay
    REC.mcap --speed 100`, neither given a bus option nor --config, started in the twin's
    working directory: the recording holds every replayed plant message, byte for byte, and
    the recorder stops by itself 3 s after the replay's last message (the feeder's and the
    supervisor's health go on meanwhile)."""
    config = line_config(tmp_path, ["feeder"])
    rec = simulate(tmp_path, config)
    up = start(["up", "--config", str(config)], tmp_path, tmp_path / "up.log")
    recorder = None
    try:
        wait_for(tmp_path / "up.log", " ready; run dir", 120, up)
        out = tmp_path / "out.mcap"
        recorder = start(
            ["record", str(out), "--idle-timeout", "3"], tmp_path, tmp_path / "record.log"
        )
        wait_for(tmp_path / "record.log", "ready", 60, recorder)
        r = subprocess.run(
            [*TWIN, "replay", str(rec), "--speed", "100"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=120,
            env=ENV,
        )
        assert r.returncode == 0, r.stderr
        assert "replayed 363 messages" in r.stdout
        recorder.wait(40)  # the idle timeout stops it
        text = (tmp_path / "record.log").read_text()
        assert recorder.returncode == 0, text
        assert "stopped by idle" in text and "from the running twin of line line1" in text
        got, sent = plant_payloads(out), plant_payloads(rec)
        for key, payloads in sent.items():
            assert got.get(key) == payloads, key
        assert sum(len(v) for v in sent.values()) == 363
    finally:
        if recorder is not None:
            stop(recorder)
        stop(up)


def test_without_a_twin_record_and_replay_meet_peer_to_peer(tmp_path):
    """No `twin up`: `twin record --config LINE` listens on the line's endpoint and `twin replay
    --config LINE` connects to it: every plant message recorded; a replay that finds nobody
    there is one line `error: ...` naming the endpoint, exit 2."""
    config = line_config(tmp_path, ["feeder"])
    rec = simulate(tmp_path, config)
    endpoint = LineSpec.from_file(config).bus.listen[0]
    alone = subprocess.run(
        [*TWIN, "replay", str(rec), "--config", str(config)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
        env=ENV,
    )
    assert alone.returncode == 2
    [line] = alone.stderr.strip().splitlines()
    assert line.startswith("error: no twin of line line1 runs here") and endpoint in line
    out = tmp_path / "out.mcap"
    recorder = start(
        ["record", str(out), "--config", str(config), "--idle-timeout", "2"],
        tmp_path,
        tmp_path / "record.log",
    )
    try:
        wait_for(tmp_path / "record.log", "ready", 60, recorder)
        r = subprocess.run(
            [*TWIN, "replay", str(rec), "--config", str(config), "--speed", "200"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=120,
            env=ENV,
        )
        assert r.returncode == 0, r.stderr
        recorder.wait(40)
        assert (
            recorder.returncode == 0 and "stopped by idle" in (tmp_path / "record.log").read_text()
        )
        got, sent = plant_payloads(out), plant_payloads(rec)
        for key, payloads in sent.items():
            assert got.get(key) == payloads, key
    finally:
        stop(recorder)


def test_idle_timeout_counts_plant_messages_only(tmp_path):
    """Five plant messages, then only another tool's health every 0.2 s: the recorder stops by
    its idle timeout (1.5 s), and its own health is not in the file."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    line = "idle"
    result = {}
    ready = threading.Event()

    def run() -> None:
        result["stats"] = record_bus(
            tmp_path / "idle.mcap",
            BusConfig(listen=[ep], connect=[], line=line),
            idle_timeout_s=1.5,
            duration_s=20.0,
            install_signal_handlers=False,
            on_ready=ready.set,
        )

    thread = threading.Thread(target=run)
    thread.start()
    assert ready.wait(20)
    with open_session(BusConfig(connect=[ep], line=line)) as s:
        conc = Publisher(s, keys.measured_concentration(line, "nir1"), MeasuredConcentration)
        health = Publisher(s, keys.service_health(line, "tool"), ServiceHealth)
        deadline = time.monotonic() + 10
        while not conc.has_subscribers() and time.monotonic() < deadline:
            time.sleep(0.02)
        for i in range(5):
            conc.publish(
                MeasuredConcentration(
                    t=float(i), seq=i, sensor="nir1", component="api", concentration_pct_w_w=5.0
                )
            )
        t0 = time.monotonic()
        while thread.is_alive() and time.monotonic() - t0 < 15:
            health.publish(
                ServiceHealth(
                    t=4.0, seq=health.seq, service="tool", state="running", pid=os.getpid(),
                    uptime_s=1.0, wall_time_unix_s=time.time(), counters={},
                )
            )  # fmt: skip
            time.sleep(0.2)
    thread.join(20)
    stats = result["stats"]
    assert stats.reason == "idle"
    assert stats.counts[keys.measured_concentration(line, "nir1")] == 5
    assert not any(k.split("/")[3] == "recorder" for k in stats.counts if keys.is_service_key(k))
