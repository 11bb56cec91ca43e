"""Benchmark: latency from an NIR sample to its OOS decision, at real-time rate on loopback,
at start-up, in steady state, and after a restart of the diverter.

The benchmark process plays the plant at real time (10 Hz flows and NIR, ideal feeders) with
short NIR excursions out of the specification every second (3 samples out: an episode opens,
then closes after 3 samples back in); blender and oos run as supervised processes. For every
decision of the diverter (the ``.open`` divert command when an episode opens, the alert when it
closes) the latency is the wall time from publishing the NIR sample that completed the decision
(its plant time is the decision's ``t``) to receiving the decision. The path includes the router
hop to the diverter, validation, the event-time merge (which waits for the blender's prediction
of the same tick: a second hop) and the hop back.

Phases, reported apart: *start-up* (the first ``--startup-s`` of plant time, fed as soon as the
services' liveliness tokens are up), *steady* (the rest before the restart), *restart* (the
oos service is killed with SIGKILL at ``--kill-at`` s of plant time; the supervisor restarts it;
decisions on samples published from the moment its health says ``running`` again, the first
``--startup-s`` of them) and *after restart* (the rest). Decisions on samples published while
the diverter was down or catching up are counted apart (*outage*): they wait for it by design.

``--floor``: then the same decision path with nothing but zenoh in it
(``benchmarks/bus_floor.py``: the same processes and hops, no validation, no computation), in
the same run, for the part of the latency the transport takes on this machine.

Run: ``python benchmarks/services_latency.py [--seconds 60] [--kill-at 30] [--floor]``
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bus_floor  # noqa: E402
from machine import describe  # noqa: E402

from schemas import keys  # noqa: E402
from schemas.line import LineSpec  # noqa: E402
from schemas.messages import (  # noqa: E402
    DivertCommand,
    FeederFlow,
    MeasuredConcentration,
    OosAlert,
    PredictedConcentration,
    ServiceHealth,
)
from services.bus import free_port, open_session  # noqa: E402
from services.service import Service  # noqa: E402
from services.supervisor import Supervisor  # noqa: E402

CONFIG = Path(__file__).resolve().parent.parent / "services" / "configs" / "line1.yaml"
DT = 0.1


def line_spec(port: int, services: list[str], express: bool, state: Path) -> LineSpec:
    """line1 at 10 Hz (150 s kernel), a router on ``port``."""
    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(
        dt_s=DT,
        sensor={"id": "nir1", "component": "api", "sample_period_s": DT},
        bus={"mode": "router", "listen": [f"tcp/127.0.0.1:{port}"], "connect": []},
        services=services,
        express=express,
        state_dir=str(state),
    )
    data["blender"]["kernel_s"] = 150.0
    return LineSpec.model_validate(data)


class Decisions:
    """Wall time each decision (kind, plant time) was first received; oos health by pid."""

    def __init__(self, session: zenoh.Session, line: str) -> None:
        self.recv: dict[tuple[str, float], float] = {}
        #: wall time the blender's prediction of each tick was first received
        self.pred: dict[float, float] = {}
        self.running_since: dict[int, float] = {}
        self.lock = threading.Lock()
        self.subs = [
            session.declare_subscriber(keys.oos_alert(line), self._on(OosAlert)),
            session.declare_subscriber(keys.divert_command(line), self._on(DivertCommand)),
            session.declare_subscriber(
                keys.predicted_concentration(line, "outlet"),
                zenoh.handlers.Callback(self._on_pred, lambda: None),
            ),
            session.declare_subscriber(
                keys.service_health(line, "oos"),
                zenoh.handlers.Callback(self._on_health, lambda: None),
            ),
        ]

    def _on(self, model):
        def cb(sample: zenoh.Sample) -> None:
            now = time.perf_counter()
            m = model.model_validate_json(sample.payload.to_bytes())
            kind = "alert" if model is OosAlert else m.command_id.rsplit(".", 1)[-1]
            with self.lock:
                self.recv.setdefault((kind, round(m.t, 6)), now)

        return zenoh.handlers.Callback(cb, lambda: None)

    def _on_pred(self, sample: zenoh.Sample) -> None:
        now = time.perf_counter()
        p = PredictedConcentration.model_validate_json(sample.payload.to_bytes())
        with self.lock:
            self.pred.setdefault(round(p.t, 6), now)

    def _on_health(self, sample: zenoh.Sample) -> None:
        h = ServiceHealth.model_validate_json(sample.payload.to_bytes())
        if h.state == "running":
            with self.lock:
                self.running_since.setdefault(h.pid, time.perf_counter())

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()


def play(plant: Service, spec: LineSpec, seconds: float, on_tick) -> dict[float, float]:
    """Publish flows and NIR at real time; ``on_tick(t)`` after each tick; returns the wall
    time each NIR sample was sent."""
    flow_pubs = {
        f.id: plant.publisher(keys.feeder_flow(spec.name, f.id), FeederFlow, history=True)
        for f in spec.feeders
    }
    nir = plant.publisher(
        keys.measured_concentration(spec.name, "nir1"), MeasuredConcentration, history=True
    )
    sent: dict[float, float] = {}
    t_wall0 = time.perf_counter()
    for i in range(int(seconds / DT)):
        t = round(i * DT, 6)
        pause = t_wall0 + i * DT - time.perf_counter()
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
        on_tick(t)
    return sent


def phases(
    lat: dict[tuple[str, float], float],
    sent: dict[float, float],
    startup_s: float,
    kill_t: float | None,
    back_wall: float | None,
) -> dict[str, list[tuple[float, str, float]]]:
    """Latencies (ms, decision kind, plant time) by phase (module docstring)."""
    out: dict[str, list[tuple[float, str, float]]] = {}
    t_back = None
    if back_wall is not None:
        t_back = min((t for t, w in sent.items() if w >= back_wall), default=None)
    for (kind, t), v in lat.items():
        if kill_t is None or t < kill_t:
            phase = "start-up" if t < startup_s else "steady"
        elif t_back is None or t < t_back:
            phase = "outage"
        else:
            phase = "restart" if t < t_back + startup_s else "after restart"
        out.setdefault(phase, []).append((v * 1e3, kind, t))
    return out


def stages(
    lat: dict[tuple[str, float], float], pred: dict[float, float], sent: dict[float, float]
) -> dict[str, list[float]]:
    """Each decision's latency split at the arrival of the blender's prediction of its tick at
    the benchmark (a peer of the diverter on the same router): NIR sample -> prediction seen
    (the flows' hop to the blender, its computation, the hop out), and prediction seen ->
    decision seen (the diverter's merge and decision, the hop back), ms."""
    a, b = [], []
    for (_, t), v in lat.items():
        if t in pred and t in sent:
            p = pred[t] - sent[t]
            a.append(p * 1e3)
            b.append((v - p) * 1e3)
    if not a:
        return {}
    return {"NIR sample -> prediction seen": a, "prediction seen -> decision seen": b}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--kill-at", type=float, default=30.0, help="plant s; <= 0: no restart")
    ap.add_argument("--startup-s", type=float, default=10.0)
    ap.add_argument("--services", default="blender,oos", help="supervised services")
    ap.add_argument(
        "--express",
        choices=["on", "off"],
        default="on",
        help="zenoh express publishers (on: the real-time setting of line1.yaml)",
    )
    ap.add_argument(
        "--floor", action="store_true", help="also time the bare-zenoh path (bus_floor.py)"
    )
    a = ap.parse_args()
    state = Path(tempfile.mkdtemp(prefix="twin-lat-"))
    spec = line_spec(free_port(), a.services.split(","), a.express == "on", state)
    sup = Supervisor(spec, backoff_s=0.2).start()
    kill_t = a.kill_at if a.kill_at > 0 else None
    killed: dict[str, float] = {}
    try:
        assert sup.wait_ready(120), sup.alive
        s = open_session(sup.client_config("operator"))
        dec = Decisions(s, spec.name)
        plant = Service(
            "plant", sup.client_config("plant"), spec=spec, install_signal_handlers=False
        ).open()

        def on_tick(t: float) -> None:
            if kill_t is not None and not killed and t >= kill_t:
                pid = sup.pids()["oos"]
                os.kill(pid, signal.SIGKILL)
                killed["pid"] = pid

        sent = play(plant, spec, a.seconds, on_tick)
        time.sleep(2.0)
        dec.close()
        plant.close()
        s.close()
    finally:
        sup.stop()
    back_wall = None
    if killed:
        back_wall = min(
            (w for pid, w in dec.running_since.items() if pid != killed["pid"]), default=None
        )
    lat = {k: v - sent[k[1]] for k, v in dec.recv.items() if k[1] in sent}
    by_phase = phases(lat, sent, a.startup_s, kill_t, back_wall)
    load = os.getloadavg()
    print(describe())
    print(f"load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}")
    print(f"zenoh express: {spec.express}; services: {', '.join(spec.services)}")
    print(
        f"{len(lat)} decisions from {len(sent)} NIR samples at 10 Hz over {a.seconds:.0f} s "
        f"(real time); oos killed at {kill_t} s of plant time"
    )
    for phase in ("start-up", "steady", "outage", "restart", "after restart"):
        rows = sorted(by_phase.get(phase, []), reverse=True)
        v = np.array([r[0] for r in rows])
        if v.size == 0:
            print(f"  {phase:<14} n=   0")
            continue
        slow = ", ".join(f"{k} t={t:.1f} s {ms:.1f} ms" for ms, k, t in rows[:3])
        print(
            f"  {phase:<14} n={v.size:4d}  median {np.median(v):.2f} ms  p99 "
            f"{np.percentile(v, 99):.2f} ms  max {v.max():.2f} ms  (slowest: {slow})"
        )
    print("  target: p99 < 5 ms at start-up, steady, restart and after restart")
    calm = {(k, t) for ph in ("steady", "after restart") for _, k, t in by_phase.get(ph, [])}
    split = stages({k: v for k, v in lat.items() if k in calm}, dec.pred, sent)
    if split:
        print("  where the time goes (steady and after restart; decisions with a prediction):")
        for name, v in split.items():
            print(f"    {name:<34} median {np.median(v):.2f} ms  p99 {np.percentile(v, 99):.2f} ms")
    if a.floor:
        floor = bus_floor.measure(a.seconds)
        print("  the same path with nothing but zenoh in it (bus_floor.py, right after):")
        print("    " + bus_floor.summary(floor, int(a.seconds / DT)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
