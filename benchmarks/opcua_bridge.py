"""Benchmark: ``twin bridge opcua`` against the loopback OPC UA plant (asyncua server on
loopback serving the bundled recording; 13 mapped nodes: 2 feeders x 6 fields and the NIR),
over the plant's default security (Basic256Sha256 SignAndEncrypt, per-run certificates and
user/password; the table's first runs in docs/opcua.md were with security None).

1. *Throughput*: the plant plays ``--span`` s of plant time at each speed of ``--speeds``
   (node updates per second = 13 x speed); the bridge (no twin attached, a peer bus) must
   publish every message of the span with none incomplete, dropped or missed. Reported: node
   updates/s offered, messages published / expected, wall time; the highest speed with no loss.
2. *Latency*: the twin's blender (and feeder) services supervised on a loopback router, the
   bridge as the plant identity, the plant played at ``--latency-speed``; for each plant tick the
   wall time from the server's write of the tick's last node to the blender's prediction of
   that tick arriving on the bus. Reported: p50, p99, max over the ticks after the first 20.

Run: ``python benchmarks/opcua_bridge.py [--span 300] [--speeds 50,200,800]``
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine import describe  # noqa: E402

from schemas import keys  # noqa: E402
from schemas.bus_config import BusConfig  # noqa: E402
from schemas.messages import PredictedConcentration  # noqa: E402
from services.bus import free_port, open_session  # noqa: E402
from services.opcua_bridge import OpcuaBridge, wait_for  # noqa: E402
from services.opcua_plant import LoopbackPlant, recording_messages  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RECORDING = ROOT / "recordings" / "line1_30min.mcap"


def _loop():
    lp = asyncio.new_event_loop()
    threading.Thread(target=lp.run_forever, daemon=True).start()
    return lambda coro, timeout=600: asyncio.run_coroutine_threadsafe(coro, lp).result(timeout)


def throughput(messages, run, span_s: float, speed: float) -> dict:
    plant = LoopbackPlant(messages, port=free_port(), speed=speed)
    run(plant.start())
    cfg = plant.bridge_config(diverter=None)
    bus = BusConfig(mode="peer", listen=[f"tcp/127.0.0.1:{free_port()}"], connect=[])
    want = sum(1 for k, m in messages if m.t <= span_s and not k.endswith("excipient/event"))
    with OpcuaBridge(cfg, bus) as bridge:
        bridge.connected.wait(30)
        t0 = time.perf_counter()
        run(plant.play(t_to=span_s))
        play_s = time.perf_counter() - t0
        wait_for(lambda: bridge.counters.get("published") >= want, 30)
        done_s = time.perf_counter() - t0
        c = bridge.counters.snapshot()
    run(plant.stop())
    lost = sum(c.get(k, 0) for k in ("incomplete", "dropped", "samples_missed", "late"))
    return {
        "speed": speed,
        "offered_updates_s": plant.written / play_s,
        "published": c.get("published", 0),
        "expected": want,
        "lost": lost,
        "play_s": play_s,
        "done_s": done_s,
    }


def latency(messages, run, span_s: float, speed: float) -> dict:
    from schemas.line import LineSpec
    from services.recording import read_recording
    from services.supervisor import Supervisor
    from services.twin_demo import spec_for_recording

    state = Path(tempfile.mkdtemp(prefix="opcua-bench-"))
    spec = spec_for_recording(read_recording(RECORDING), free_port(), state)
    spec = LineSpec.model_validate(
        {**spec.model_dump(), "services": ["feeder", "blender"], "express": True}
    )
    plant = LoopbackPlant(messages, port=free_port(), speed=speed)
    run(plant.start())
    cfg = plant.bridge_config(diverter=None)
    written: dict[float, float] = {}
    seen: dict[float, float] = {}
    with Supervisor(spec, backoff_s=0.5) as sup:
        if not sup.wait_ready(90):
            raise RuntimeError("services not ready")
        session = open_session(sup.client_config("operator"))
        comp = spec.sensor.component

        def on_pred(sample) -> None:
            p = PredictedConcentration.model_validate_json(sample.payload.to_bytes())
            if p.component == comp:
                seen.setdefault(p.t, time.monotonic())

        sub = session.declare_subscriber(keys.predicted_concentration(spec.name, "outlet"), on_pred)
        with OpcuaBridge(cfg, sup.client_config("plant"), spec=spec) as bridge:
            bridge.connected.wait(30)
            run(
                plant.play(
                    t_to=span_s, on_tick=lambda t, w: written.setdefault(t, time.monotonic())
                )
            )
            wait_for(lambda: max(seen, default=0) >= span_s, 30)
        sub.undeclare()
        session.close()
    run(plant.stop())
    lat = np.array([seen[t] - written[t] for t in sorted(written) if t in seen and t >= 20]) * 1e3
    return {
        "ticks": len(written),
        "predicted": len(seen),
        "p50_ms": float(np.percentile(lat, 50)),
        "p99_ms": float(np.percentile(lat, 99)),
        "max_ms": float(lat.max()),
    }


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--span", type=float, default=300.0, help="plant seconds per throughput run")
    p.add_argument("--speeds", default="50,200,800", help="plant-time speed-ups to try")
    p.add_argument("--latency-span", type=float, default=120.0)
    p.add_argument("--latency-speed", type=float, default=5.0)
    a = p.parse_args()
    print(describe())
    print(f"load average before: {os.getloadavg()}")
    messages = recording_messages(RECORDING)
    run = _loop()
    print("| speed | node updates/s offered | published / expected | lost | play s | all out s |")
    print("|---|---|---|---|---|---|")
    for speed in (float(s) for s in a.speeds.split(",")):
        r = throughput(messages, run, a.span, speed)
        print(
            f"| {r['speed']:g}x | {r['offered_updates_s']:.0f} | {r['published']} / "
            f"{r['expected']} | {r['lost']} | {r['play_s']:.2f} | {r['done_s']:.2f} |",
            flush=True,
        )
    r = latency(messages, run, a.latency_span, a.latency_speed)
    print(
        f"latency OPC UA write -> blender prediction on the bus ({r['ticks']} ticks at "
        f"{a.latency_speed:g}x, {r['predicted']} predicted): p50 {r['p50_ms']:.1f} ms, "
        f"p99 {r['p99_ms']:.1f} ms, max {r['max_ms']:.1f} ms"
    )
    print(f"load average after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
