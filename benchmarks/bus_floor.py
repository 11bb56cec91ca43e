"""Benchmark: the transport floor of the diverter's decision path on this machine.

The live twin's decision on an NIR sample waits for the blender's prediction of the same tick
(``benchmarks/services_latency.py``): plant -> router -> blender -> router -> diverter -> router
-> observer, six loopback TCP hops through the router, three of them into Python callbacks in
separate processes. This script times the same topology with nothing in it but zenoh: one
process per node (a router, two stages that re-publish every sample they get, from inside the
subscriber callback, on an express publisher, and the observer that publishes and receives),
no validation, no computation, 200-byte payloads at 10 Hz. Whatever latency this shows, the
services cannot go below it; ``services_latency.py --floor`` prints both side by side.

Run: ``python benchmarks/bus_floor.py [--seconds 60] [--rate-hz 10]``
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: each stage's input and output key: the observer publishes ``floor/plant`` and hears ``floor/oos``
STAGES = {"blender": ("floor/plant", "floor/blender"), "oos": ("floor/blender", "floor/oos")}
PAYLOAD = 200


def _session(mode: str, listen: list[str], connect: list[str]):
    """A zenoh session of the twin's own configuration (``services.bus.open_session``)."""
    from schemas.bus_config import BusConfig
    from services.bus import open_session

    return open_session(BusConfig(mode=mode, listen=listen, connect=connect))


def serve_node(role: str, locator: str) -> None:
    """Run one node until killed: the router on ``locator``, or a stage connected to it."""
    import zenoh

    if role == "router":
        session = _session("router", [locator], [])
    else:
        session = _session("client", [], [locator])
        src, dst = STAGES[role]
        pub = session.declare_publisher(dst, express=True)
        session.declare_subscriber(
            src, zenoh.handlers.Callback(lambda s: pub.put(s.payload.to_bytes()), lambda: None)
        )
    while True:
        time.sleep(3600)
    session.close()  # pragma: no cover


def measure(seconds: float = 60.0, rate_hz: float = 10.0) -> np.ndarray:
    """Latencies (ms) of ``seconds * rate_hz`` samples through the chain (module docstring)."""
    import zenoh

    from services.bus import free_port

    locator = f"tcp/127.0.0.1:{free_port()}"
    me = [sys.executable, str(Path(__file__).resolve()), "--node"]
    procs = [subprocess.Popen([*me, "router", locator])]
    try:
        time.sleep(1.0)
        procs += [subprocess.Popen([*me, role, locator]) for role in STAGES]
        session = _session("client", [], [locator])
        recv: dict[int, float] = {}

        def on_back(sample: zenoh.Sample) -> None:
            recv.setdefault(int(sample.payload.to_bytes()[:8]), time.perf_counter())

        sub = session.declare_subscriber(
            STAGES["oos"][1], zenoh.handlers.Callback(on_back, lambda: None)
        )
        pub = session.declare_publisher(STAGES["blender"][0], express=True)
        time.sleep(3.0)  # the stages' subscriptions reach the router
        sent: dict[int, float] = {}
        t0 = time.perf_counter()
        for i in range(int(seconds * rate_hz)):
            pause = t0 + i / rate_hz - time.perf_counter()
            if pause > 0:
                time.sleep(pause)
            sent[i] = time.perf_counter()
            pub.put(f"{i:08d}".encode().ljust(PAYLOAD, b"x"))
        time.sleep(0.5)
        sub.undeclare()
        session.close()
    finally:
        for p in procs:
            p.kill()
            p.wait(5)
    return np.array([recv[i] - sent[i] for i in sent if i in recv]) * 1e3


def summary(lat: np.ndarray, n_sent: int) -> str:
    """One line: received of sent, median, p90, p99, max (ms)."""
    return (
        f"{lat.size} of {n_sent} samples; median {np.median(lat):.2f} ms  p90 "
        f"{np.percentile(lat, 90):.2f} ms  p99 {np.percentile(lat, 99):.2f} ms  max "
        f"{lat.max():.2f} ms"
    )


def main() -> int:
    if len(sys.argv) == 4 and sys.argv[1] == "--node":
        serve_node(sys.argv[2], sys.argv[3])
        return 0
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--rate-hz", type=float, default=10.0)
    a = ap.parse_args()
    from machine import describe

    lat = measure(a.seconds, a.rate_hz)
    load = os.getloadavg()
    print(describe())
    print(f"load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}")
    print("raw zenoh, plant -> router -> stage -> router -> stage -> router -> plant:")
    print("  " + summary(lat, int(a.seconds * a.rate_hz)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
