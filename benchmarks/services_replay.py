"""Benchmark: a one-hour recording replayed through all live services as fast as possible.

Simulates one hour of line1 (1 Hz flows and NIR, a feeder disturbance), writes it to MCAP,
starts feeder, blender, rtd, oos and recorder under the supervisor (separate processes, zenoh
router on loopback), replays the recording with no pacing, and measures the wall time until
the diverter has processed the last sample. Prints the speed-up over real time and checks that
no message was dropped (CongestionControl.BLOCK): the recorder's MCAP must hold every replayed
and every derived message.

Run: ``python benchmarks/services_replay.py [--duration 3600] [--port 17900]``
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from schemas.line import LineSpec
from services.recording import BusReplay, read_recording, write_messages
from services.supervisor import Supervisor
from services.twin_demo import _Tap
from twin_core.plant.messages import simulate_messages

CONFIG = Path(__file__).resolve().parent.parent / "services" / "configs" / "line1.yaml"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=3600.0)
    ap.add_argument("--port", type=int, default=17900)
    ap.add_argument(
        "--express",
        choices=["on", "off"],
        default="off",
        help="zenoh express publishers (off: batching, the fast-replay setting)",
    )
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="twin-bench-"))
    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(
        bus={"mode": "router", "listen": [f"tcp/127.0.0.1:{a.port}"], "connect": []},
        services=["feeder", "blender", "rtd", "oos", "recorder"],
        state_dir=str(tmp),
        record_path="bench.mcap",
    )
    data["express"] = a.express == "on"
    spec = LineSpec.model_validate(data)
    t0 = time.perf_counter()
    _, msgs = simulate_messages(
        spec,
        a.duration,
        seed=11,
        disturbances=[{"feeder": "api", "t_s": 1800.0, "delta_kg_h": 0.6, "duration_s": 30.0}],
    )
    write_messages(tmp / "hour.mcap", msgs)
    rec = read_recording(tmp / "hour.mcap")
    print(
        f"recording: {len(rec.messages)} messages, {rec.duration_s:.0f} s plant time "
        f"(simulated and written in {time.perf_counter() - t0:.1f} s)"
    )
    sup = Supervisor(spec).start()
    try:
        assert sup.wait_ready(120), sup.alive
        tap = _Tap(spec, echo=False)
        time.sleep(1.5)
        last_t = rec.messages[-1].t
        with BusReplay.as_plant(rec, None, spec) as rp:
            w0 = time.perf_counter()
            n = rp.replay(as_fast_as_possible=True).published
            w_pub = time.perf_counter() - w0
            while time.perf_counter() - w0 < 300:
                h = tap.health.get("oos")
                if h is not None and h.t >= last_t and tap.pred and max(tap.pred) >= last_t:
                    break
                time.sleep(0.01)
            w_all = time.perf_counter() - w0
            time.sleep(2.0)
        health = dict(tap.health)
        tap.close()
    finally:
        sup.stop()
    out = read_recording(sup.run_dir / "bench.mcap")
    counts: dict[str, int] = {}
    for m in out.messages:
        counts[m.key] = counts.get(m.key, 0) + 1
    n_ticks = int(a.duration) + 1
    expected = {
        "twin/line1/feeder/api/flow": n_ticks,
        "twin/line1/feeder/excipient/flow": n_ticks,
        "twin/line1/pat/nir1/concentration": n_ticks,
        "twin/line1/blender/outlet/predicted": 2 * n_ticks,
    }
    dropped = {k: v - counts.get(k, 0) for k, v in expected.items() if counts.get(k, 0) != v}
    derived = sum(counts.values()) - n
    print(f"zenoh express: {spec.express}")
    print(
        f"replayed {n} messages: publisher done in {w_pub:.2f} s, diverter caught up in "
        f"{w_all:.2f} s"
    )
    print(
        f"speed-up over real time: {a.duration / w_all:.0f}x (publisher alone "
        f"{a.duration / w_pub:.0f}x); bus messages recorded {sum(counts.values())} "
        f"({derived} derived by the services)"
    )
    print(f"aggregate rate through the services: {sum(counts.values()) / w_all:.0f} msg/s")
    print(f"dropped messages: {sum(dropped.values()) if dropped else 0} {dropped or ''}")
    print(
        f"alerts: {counts.get('twin/line1/oos/alert', 0)}, divert commands: "
        f"{counts.get('twin/line1/divert/command', 0)}"
    )
    for name, h in sorted(health.items()):
        c = {
            k: v
            for k, v in h.counters.items()
            if k.startswith(
                ("received", "published", "rejected", "degraded", "caught", "handler", "alerts")
            )
        }
        print(f"  {name:<9} {c}")
    return 0 if not dropped else 1


if __name__ == "__main__":
    raise SystemExit(main())
