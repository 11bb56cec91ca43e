"""Benchmark: latency from an NIR sample to its OOS decision, at real-time rate on loopback.

The benchmark process plays the plant at real time (10 Hz flows and NIR, ideal feeders) with
short NIR excursions out of the specification every second (3 samples out: an
episode opens, then closes after 3 samples back in); blender and oos run as supervised
processes. For every decision of the diverter (the ``.open`` divert command when an episode
opens, the alert when it closes) the latency is the wall time from publishing the NIR sample
that completed the decision (its plant time is the decision's ``t``) to receiving the decision.
The path includes the router hop to the diverter, validation, the event-time merge (which waits
for the blender's prediction of the same tick: a second hop) and the hop back.

Run: ``python benchmarks/services_latency.py [--seconds 90] [--port 17910]``
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import DivertCommand, FeederFlow, MeasuredConcentration, OosAlert
from services.bus import open_session
from services.service import Service
from services.supervisor import Supervisor

CONFIG = Path(__file__).resolve().parent.parent / "services" / "configs" / "line1.yaml"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--port", type=int, default=17910)
    ap.add_argument("--services", default="blender,oos", help="supervised services")
    ap.add_argument(
        "--express",
        choices=["on", "off"],
        default="on",
        help="zenoh express publishers (on: the real-time setting of line1.yaml)",
    )
    a = ap.parse_args()
    dt = 0.1
    tmp = Path(tempfile.mkdtemp(prefix="twin-lat-"))
    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(
        dt_s=dt,
        sensor={"id": "nir1", "component": "api", "sample_period_s": dt},
        bus={"mode": "router", "listen": [f"tcp/127.0.0.1:{a.port}"], "connect": []},
        services=a.services.split(","),
        express=a.express == "on",
        state_dir=str(tmp),
    )
    data["blender"]["kernel_s"] = 150.0
    spec = LineSpec.model_validate(data)
    sup = Supervisor(spec).start()
    recv: dict[tuple[str, float], float] = {}
    lock = threading.Lock()
    try:
        assert sup.wait_ready(120), sup.alive
        s = open_session(spec.client_bus())

        def on(model):
            def cb(sample: zenoh.Sample) -> None:
                now = time.perf_counter()
                m = model.model_validate_json(sample.payload.to_bytes())
                kind = "alert" if model is OosAlert else m.command_id.rsplit(".", 1)[-1]
                with lock:
                    recv.setdefault((kind, round(m.t, 6)), now)

            return zenoh.handlers.Callback(cb, lambda: None)

        subs = [
            s.declare_subscriber(keys.oos_alert(spec.name), on(OosAlert)),
            s.declare_subscriber(keys.divert_command(spec.name), on(DivertCommand)),
        ]
        plant = Service("plant", spec=spec, install_signal_handlers=False).open()
        flow_pubs = {
            f.id: plant.publisher(keys.feeder_flow(spec.name, f.id), FeederFlow, history=True)
            for f in spec.feeders
        }
        nir = plant.publisher(
            keys.measured_concentration(spec.name, "nir1"), MeasuredConcentration, history=True
        )
        time.sleep(1.5)
        sent: dict[float, float] = {}
        n = int(a.seconds / dt)
        t_wall0 = time.perf_counter()
        for i in range(n):
            t = round(i * dt, 6)
            due = t_wall0 + i * dt
            pause = due - time.perf_counter()
            if pause > 0:
                time.sleep(pause)
            for f in spec.feeders:
                flow_pubs[f.id].publish(
                    FeederFlow(
                        t=t,
                        seq=i,
                        component=f.component,
                        mass_flow_kg_h=f.setpoint_kg_h,
                        screw_speed_rpm=100.0,
                        hopper_mass_kg=5.0,
                        feed_factor_g_rev=1.0,
                    )
                )
            c = 13.0 if 2 <= i % 10 < 5 else 10.0  # 1 s period: 3 samples out of spec
            nir.publish(
                MeasuredConcentration(
                    t=t, seq=i, sensor="nir1", component="api", concentration_pct_w_w=c
                )
            )
            sent[t] = time.perf_counter()
        time.sleep(2.0)
        for sub in subs:
            sub.undeclare()
        plant.close()
        s.close()
    finally:
        sup.stop()
    lat = {k: v - sent[k[1]] for k, v in recv.items() if k[1] in sent}
    by_kind: dict[str, list[float]] = {}
    for (kind, _), v in lat.items():
        by_kind.setdefault(kind, []).append(v)
    allv = np.array(list(lat.values())) * 1e3
    print(f"zenoh express: {spec.express}; services: {', '.join(spec.services)}")
    print(f"{len(lat)} decisions from {n} NIR samples at 10 Hz over {a.seconds:.0f} s (real time)")
    for kind, v in sorted(by_kind.items()):
        v = np.array(v) * 1e3
        print(
            f"  {kind:<6} n={v.size:4d}  median {np.median(v):.2f} ms  p99 "
            f"{np.percentile(v, 99):.2f} ms  max {v.max():.2f} ms"
        )
    print(
        f"  all    n={allv.size:4d}  median {np.median(allv):.2f} ms  p99 "
        f"{np.percentile(allv, 99):.2f} ms  (target p99 < 5 ms)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
