"""Benchmark: messages per second the blender service sustains, and where the time goes.

Part 1, in one process (no bus): per-message cost of each stage of the blender on N ticks of
two feeders: JSON validation of a FeederFlow (pydantic), the prediction core (alignment, two
streaming convolutions of a 300 s kernel, composition), building and encoding the
PredictedConcentration messages, and a zenoh put; with the pydantic validate+encode pair alone
as the reference ceiling (the same run, so the ratio is meaningful on a noisy machine).

Part 2, over the bus: the blender as a supervised process; this process publishes flows as
fast as BLOCK congestion control lets it and counts the predictions coming back.

Run: ``python benchmarks/services_blender.py [--ticks 20000] [--port 17920]``
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
from schemas.messages import FeederFlow, PredictedConcentration
from services.bus import open_session
from services.service import Service
from services.supervisor import Supervisor
from twin_core.online import StreamingConvolver
from twin_core.online.blender import BlenderPredictor

CONFIG = Path(__file__).resolve().parent.parent / "services" / "configs" / "line1.yaml"


def stage_costs(spec: LineSpec, n: int) -> None:
    rng = np.random.default_rng(0)
    payloads = []
    for i in range(n):
        for f in spec.feeders:
            payloads.append(
                (
                    f.id,
                    FeederFlow(
                        t=float(i),
                        seq=i,
                        component=f.component,
                        mass_flow_kg_h=f.setpoint_kg_h * (1 + 0.02 * rng.standard_normal()),
                        screw_speed_rpm=100.0,
                        hopper_mass_kg=5.0,
                        feed_factor_g_rev=1.0,
                    ).to_json_bytes(),
                )
            )
    m = len(payloads)
    t0 = time.perf_counter()
    msgs = [(fid, FeederFlow.model_validate_json(p)) for fid, p in payloads]
    t_val = (time.perf_counter() - t0) / m
    core = BlenderPredictor(spec)
    t0 = time.perf_counter()
    preds = []
    for fid, msg in msgs:
        preds += core.push(fid, msg.t, msg.mass_flow_kg_h)
    t_core = (time.perf_counter() - t0) / m
    t0 = time.perf_counter()
    out = []
    for t, conc in preds:
        for j, (c, v) in enumerate(conc.items()):
            out.append(
                PredictedConcentration(
                    t=t, seq=2 * int(t) + j, model="rtd", component=c, concentration_pct_w_w=v
                ).to_json_bytes()
            )
    t_enc = (time.perf_counter() - t0) / len(out)
    with zenoh.open(zenoh.Config()) as s:
        pub = s.declare_publisher("twin/line1/blender/outlet/predicted")
        t0 = time.perf_counter()
        for p in out:
            pub.put(p)
        t_put = (time.perf_counter() - t0) / len(out)
    e = core.e
    sc = StreamingConvolver(e, spec.dt_s, initial=1.0)
    t0 = time.perf_counter()
    for x in range(m):
        sc.push(1.0 + 1e-3 * (x % 7))
    t_conv = (time.perf_counter() - t0) / m
    per_flow = t_val + t_core + (t_enc + t_put) * len(out) / m
    print(f"Part 1: {m} flow messages (2 feeders x {n} ticks), kernel {e.size} samples")
    print(f"  validate FeederFlow (pydantic JSON)  {t_val * 1e6:7.2f} us/msg")
    print(
        f"  prediction core per flow message     {t_core * 1e6:7.2f} us/msg "
        f"(of which one streaming convolution push {t_conv * 1e6:.2f} us)"
    )
    print(f"  build+encode PredictedConcentration  {t_enc * 1e6:7.2f} us/msg")
    print(f"  zenoh put (no subscriber)            {t_put * 1e6:7.2f} us/msg")
    print(
        f"  total per incoming flow message      {per_flow * 1e6:7.2f} us -> ceiling "
        f"{1 / per_flow:,.0f} flow msg/s in one process"
    )
    print(
        f"  pydantic validate+encode alone       {(t_val + t_enc) * 1e6:7.2f} us -> "
        f"{1 / (t_val + t_enc):,.0f} msg/s (the serialization ceiling)"
    )
    shares = {
        "validate": t_val,
        "core": t_core,
        "encode": t_enc * len(out) / m,
        "put": t_put * len(out) / m,
    }
    print(
        "  time shares: " + ", ".join(f"{k} {100 * v / per_flow:.0f} %" for k, v in shares.items())
    )


def over_bus(spec: LineSpec, n: int) -> None:
    sup = Supervisor(spec).start()
    got = [0]
    first_last = [0.0, 0.0]
    lock = threading.Lock()
    try:
        assert sup.wait_ready(120), sup.alive
        s = open_session(spec.client_bus())

        def cb(sample: zenoh.Sample) -> None:
            now = time.perf_counter()
            with lock:
                got[0] += 1
                first_last[1] = now

        sub = s.declare_subscriber(
            keys.predicted_concentration(spec.name, "outlet"),
            zenoh.handlers.Callback(cb, lambda: None),
        )
        plant = Service("plant", spec=spec, install_signal_handlers=False).open()
        pubs = {
            f.id: plant.publisher(keys.feeder_flow(spec.name, f.id), FeederFlow, history=True)
            for f in spec.feeders
        }
        msgs = [
            (
                f.id,
                FeederFlow(
                    t=float(i),
                    seq=i,
                    component=f.component,
                    mass_flow_kg_h=f.setpoint_kg_h,
                    screw_speed_rpm=100.0,
                    hopper_mass_kg=5.0,
                    feed_factor_g_rev=1.0,
                ).to_json_bytes(),
            )
            for i in range(n)
            for f in spec.feeders
        ]
        time.sleep(1.5)
        t0 = time.perf_counter()
        for fid, p in msgs:
            pubs[fid].put_raw(p)
        t_pub = time.perf_counter() - t0
        expected = 2 * n
        while got[0] < expected and time.perf_counter() - t0 < 120:
            time.sleep(0.01)
        t_all = first_last[1] - t0
        sub.undeclare()
        plant.close()
        s.close()
    finally:
        sup.stop()
    print(
        f"Part 2: {len(msgs)} flows published in {t_pub:.2f} s; {got[0]} of {2 * n} "
        f"predictions back after {t_all:.2f} s"
    )
    print(
        f"  blender service sustained {len(msgs) / t_all:,.0f} flow msg/s in "
        f"(+ {got[0] / t_all:,.0f} prediction msg/s out)"
    )


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--ticks", type=int, default=20000)
    ap.add_argument("--port", type=int, default=17920)
    a = ap.parse_args()
    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(
        bus={"mode": "router", "listen": [f"tcp/127.0.0.1:{a.port}"], "connect": []},
        services=["blender"],
        state_dir=tempfile.mkdtemp(prefix="twin-blend-"),
        express=False,
        history_samples=2 * a.ticks + 10,
    )
    spec = LineSpec.model_validate(data)
    stage_costs(spec, a.ticks)
    over_bus(spec, a.ticks)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
