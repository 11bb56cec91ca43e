"""Speed of the material tracking (issue 38): the streaming tracker with 20 live lots per tick,
and ``twin batch report`` of a 24 h, 1 Hz recording.

    python benchmarks/trace_speed.py [--hours 24] [--keep DIR]

1. ``MaterialTracker.push`` on two feeders with stirred hoppers (``mixed``: every lot of a
   feeder stays in its hopper, diluted), refilled until 10 lots each are fed at every tick: the
   cost of a tick with 20 lots entering the blender (E(t) of 300 samples), median over 20,000
   ticks.
2. A 24 h recording at 1 Hz (two feeders, their refills with lot ids every 69 and 111 min, an
   NIR sample per second: 259,200 messages) written with ``services.recording.write_messages``,
   then ``twin batch report`` (read, track, batches by product mass of 50 kg, JSON + HTML) and
   ``twin trace --lot`` on it, wall time each.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from twin_core.rtd.models import model_e


def tick_cost(n_ticks: int = 20000) -> dict[str, float]:
    from twin_core.tracking import MaterialTracker

    e = model_e(
        "axial_dispersion_open", {"tau_d": 11.92, "tau": 16.37, "pe": 7.67}, np.arange(300.0)
    )
    tr = MaterialTracker({"a": "api", "b": "excipient"}, 1.0, e, alpha=1.0)
    hop = {"a": 1.0, "b": 10.0}
    flows = {"a": 1.2, "b": 10.8}
    for i in range(9 * 60):  # a refill of each feeder every minute: 10 lots each
        if i % 60 == 59:
            for f in ("a", "b"):
                tr.refill_start(f)
                tr.refill_stop(f, 0.1 * hop[f])
        tr.push(float(i), flows, hop)
    live = sum(1 for v in tr.hopper_content() if v > 0)
    times = []
    for i in range(n_ticks):
        t0 = time.perf_counter()
        tr.push(float(540 + i), flows, hop)
        times.append(time.perf_counter() - t0)
    return {
        "live_lots": live,
        "median_us": statistics.median(times) * 1e6,
        "p99_us": float(np.quantile(times, 0.99) * 1e6),
    }


def day_recording(path: Path, hours: float) -> int:
    from schemas import keys
    from schemas.messages import Event, FeederFlow, MeasuredConcentration
    from services.recording import write_messages

    n = int(hours * 3600) + 1
    msgs = []
    spec = {"api": (1.2, 1.78, 0.4), "excipient": (10.8, 25.0, 5.0)}
    seqs = {"api": 0, "excipient": 0}
    mass = {f: v[1] for f, v in spec.items()}
    nir = keys.measured_concentration("line1", "nir1")
    for i in range(n):
        t = float(i)
        for f, (q, high, low) in spec.items():
            msgs.append(
                (
                    keys.feeder_flow("line1", f),
                    FeederFlow(
                        t=t,
                        seq=i,
                        component=f,
                        mass_flow_kg_h=q,
                        setpoint_kg_h=q,
                        screw_speed_rpm=100.0,
                        hopper_mass_kg=mass[f],
                        feed_factor_g_rev=1.0,
                    ),
                )
            )
            mass[f] -= q / 3600.0
            if mass[f] < low:
                seqs[f] += 1
                lot = f"{f}-L{seqs[f]:04d}"
                k = keys.event("line1", "feeder", f)
                for dt_, kind in ((0.4, "refill_start"), (0.6, "refill_stop")):
                    ev = Event(
                        t=t + dt_,
                        seq=2 * seqs[f] + (kind == "refill_stop"),
                        kind=kind,
                        source=f,
                        component=f,
                        lot_id=lot,
                    )
                    msgs.append((k, ev))
                mass[f] = high
        msgs.append(
            (
                nir,
                MeasuredConcentration(
                    t=t, seq=i, sensor="nir1", component="api", concentration_pct_w_w=10.0
                ),
            )
        )
    msgs.sort(key=lambda km: km[1].t)
    return write_messages(path, msgs)


CONFIG = """
name: line1
feeders:
  - {id: api, component: api, setpoint_kg_h: 1.2}
  - {id: excipient, component: excipient, setpoint_kg_h: 10.8}
blender: {kind: rtd}
sensor: {id: nir1, component: api}
spec: [{component: api, target_pct_w_w: 10.0, lower_pct_w_w: 8.5, upper_pct_w_w: 11.5}]
batch: {by: product_mass, size: 50.0}
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=24.0)
    ap.add_argument("--keep", help="keep the recording and the report in this directory")
    args = ap.parse_args()
    print("streaming tracker:", tick_cost())
    from services.cli.main import main as twin

    with tempfile.TemporaryDirectory() as tmp:
        d = Path(args.keep or tmp)
        d.mkdir(parents=True, exist_ok=True)
        rec, cfg = d / "day.mcap", d / "line.yaml"
        cfg.write_text(CONFIG)
        t0 = time.perf_counter()
        n = day_recording(rec, args.hours)
        print(
            f"recording: {n} messages, {args.hours:g} h, written in {time.perf_counter() - t0:.1f} s"
        )
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):
            rc = twin(
                ["batch", "report", str(rec), "--config", str(cfg), "--out", str(d / "report")]
            )
        print(
            f"twin batch report: rc {rc}, {time.perf_counter() - t0:.1f} s, "
            f"{len(list((d / 'report').glob('batch_*.json')))} batches"
        )
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):
            rc = twin(["trace", str(rec), "--config", str(cfg), "--lot", "api-L0005"])
        print(f"twin trace --lot: rc {rc}, {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
