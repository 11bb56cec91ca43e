"""The live twin's decisions end to end, scored against the plant's truth.

Each record is simulated by the plant (``twin_core.plant``: LIW feeders with refills, the
open-world scenario's finite-volume blender where it applies, the seed's NIR noise), written to
MCAP, and fed to the twin **as users start it**: ``twin up --config LINE`` (the shipped
``line1.yaml``: secured bus, every service, the live close-loop) in its own directory, then
``twin replay REC --config LINE --speed S``. The twin's own recording (``twin-live.mcap``) gives
its divert commands, alerts and close-loop findings, which are scored against the truth the
simulator kept (the true outlet concentration of the API, the true mass flow):

- **false-divert mass**: product diverted while its true API content was inside the
  specification (kg, and % of the production);
- **missed OOS mass**: product accepted while its true API content was outside (kg, and % of
  the OOS mass);
- **stray diverts**: divert seconds outside every disturbance's RTD window (inlet stretch of
  the disturbance shifted by the E(t)'s 0.5 % and 99.5 % quantiles, the seed's lot
  boundaries) and outside the truly OOS stretches: a record is clean when it has none;
- **alert latency**: plant seconds from the start of a truly OOS stretch to the first divert
  command covering it (negative: decided before the product left, from the feeder flows);
- **close-loop**: the findings the live twin adopted (``explained``) and the offline
  ``twin close-loop`` analysis of the same record (its whole data).

Families: ``ordinary`` (effect-free line1 at 10 % API, 12 kg/h, with refills, a line-rate change
12 -> 14 -> 12 kg/h at constant composition, and flow disturbances of both feeders, some of
which take the product out of specification), ``inlist`` / ``outlist`` (a hidden effect of
the candidate library / outside it, ``twin_core.plant.openworld_cases``), ``fault`` (data
faults on an effect-free run). Timing faults between sources are not simulated yet.

Run: ``python benchmarks/live_decisions.py --out out/live_decisions [--families ordinary]
[--records 8] [--hours 3] [--speed 100]``; results in ``results.json`` and ``results.md``.
The records of one family run one after the other (one twin at a time).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe as machine_line  # noqa: E402
from schemas.line import LineSpec  # noqa: E402
from services.recording import read_recording, write_messages  # noqa: E402
from twin_core.closeloop.quality import true_runs  # noqa: E402
from twin_core.plant.model import rtd_kernel  # noqa: E402

LINE = ROOT / "services" / "configs" / "line1.yaml"
TWIN = [sys.executable, "-m", "services.cli.main"]
#: quantiles of E(t) that bound a disturbance's outlet window (the seed's lot boundaries)
LOT_Q = (0.005, 0.995)


# ------------------------------------------------------------------------------ records
def ordinary_record(seed: int, hours: float) -> tuple[Any, list, dict[str, Any]]:
    """An effect-free record of line1 with ordinary disturbances (module docstring)."""
    from twin_core.plant import FlowDisturbance, simulate_line
    from twin_core.plant.messages import run_messages

    spec = LineSpec.from_file(LINE)
    dur = hours * 3600.0
    rng = np.random.default_rng(1000 + seed)
    # a line-rate change at constant composition: both set points x 14/12 for the middle third
    up, down = dur / 3.0, 2.0 * dur / 3.0
    feeders = []
    for f in spec.feeders:
        sched = [(up, f.setpoint_kg_h * 14.0 / 12.0), (down, f.setpoint_kg_h)]
        feeders.append(f.model_copy(update={"liw": {**f.liw, "setpoint_schedule": sched}}))
    cfg = spec.model_copy(update={"feeders": feeders})
    dists = []
    n = max(2, int(round(2 * hours)))
    times = np.sort(rng.uniform(600.0, dur - 600.0, n))
    for t in times:
        if rng.random() < 0.75:
            delta = float(rng.choice([-1, 1]) * rng.choice([0.15, 0.3, 0.6]))
            dists.append(FlowDisturbance("api", float(t), delta, float(rng.uniform(20.0, 90.0))))
        else:
            delta = float(rng.choice([-1, 1]) * rng.choice([1.5, 3.0]))
            dists.append(
                FlowDisturbance("excipient", float(t), delta, float(rng.uniform(30.0, 120.0)))
            )
    run = simulate_line(cfg, dur, dt_s=spec.dt_s, seed=seed, disturbances=dists)
    msgs = run_messages(run, cfg)
    windows = [(d.t_s, d.t_s + d.duration_s) for d in dists]
    return run, msgs, {"family": "ordinary", "case": "ordinary", "disturbances": windows}


def case_record(family: str, name: str, seed: int) -> tuple[Any, list, dict[str, Any]]:
    """An open-world benchmark case (``twin_core.plant.openworld_cases``), no tracers, the
    seed's noise; its set-point steps count as disturbances."""
    from twin_core.plant.effects import EFFECTS
    from twin_core.plant.openworld_cases import (
        API_SCHEDULE,
        EXCIPIENT_SCHEDULE,
        FAULT_CASES,
        OUT_OF_LIST,
        Case,
        Setting,
        run_case,
    )

    if family == "inlist":
        params = {"sensor_offset": {"offset": 0.4}, "dead_zone": {"fraction": 0.3, "tau_s": 40.0}}
        case = Case("inlist", name, effects=({"name": name, "params": params[name]},))
        assert name in EFFECTS
    elif family == "outlist":
        case = Case("outlist", name, open_world=(OUT_OF_LIST[name],))
    else:
        case = Case("fault", name, faults=FAULT_CASES[name])
    cr = run_case(case, Setting(tracers=False, noise=1.0), seed)
    steps = [t for t, _ in (*API_SCHEDULE, *EXCIPIENT_SCHEDULE)]
    return (
        cr.run,
        cr.messages,
        {"family": family, "case": name, "disturbances": [(t, t) for t in steps]},
    )


# ------------------------------------------------------------------------------ the twin
def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def live_run(rec: Path, workdir: Path, speed: float) -> tuple[Path, dict[str, float]]:
    """``twin up`` with line1.yaml (its port and state folder moved into ``workdir``) and
    ``twin replay`` of ``rec`` into it; returns the twin's own recording and wall times."""
    raw = yaml.safe_load(LINE.read_text())
    port = free_port()
    raw["bus"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    raw["state_dir"] = str(workdir / "state")
    raw["record_path"] = "twin-live.mcap"
    cfg = workdir / "line.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t0 = time.perf_counter()
    up = subprocess.Popen(
        [*TWIN, "up", "--config", str(cfg)],
        cwd=workdir,
        env=env,
        stdout=subprocess.PIPE,
        stderr=open(workdir / "up.err", "w"),
        text=True,
    )
    try:
        for line in up.stdout:  # type: ignore[union-attr]
            if "ready" in line:
                break
        t_ready = time.perf_counter() - t0
        subprocess.run(
            [*TWIN, "replay", str(rec), "--config", str(cfg), "--speed", str(speed)],
            cwd=workdir,
            env=env,
            check=True,
            capture_output=True,
        )
        t_replay = time.perf_counter() - t0 - t_ready
        _wait_quiet(workdir / "state")
    finally:
        up.send_signal(signal.SIGINT)
        try:
            up.wait(timeout=60)
        except subprocess.TimeoutExpired:
            up.kill()
    live = next((workdir / "state").glob("run-*/twin-live.mcap"))
    return live, {"ready_s": t_ready, "replay_s": t_replay, "total_s": time.perf_counter() - t0}


def _wait_quiet(state: Path, quiet_s: float = 15.0, limit_s: float = 600.0) -> None:
    """Wait until the twin's recording has not grown for ``quiet_s`` (the services caught up)."""
    t_end = time.monotonic() + limit_s
    last, since = -1, time.monotonic()
    while time.monotonic() < t_end:
        files = list(state.glob("run-*/twin-live.mcap"))
        size = files[0].stat().st_size if files else 0
        if size != last:
            last, since = size, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            return
        time.sleep(1.0)


# ------------------------------------------------------------------------------ scoring
def union_mask(windows: list[tuple[float, float]], t: np.ndarray) -> np.ndarray:
    """The samples of ``t`` inside any of the windows [a, b]."""
    m = np.zeros(t.size, dtype=bool)
    for a, b in windows:
        m |= (t >= a) & (t <= b)
    return m


def gate_windows(
    commands: dict[str, list[tuple[float, float, float, str]]],
) -> dict[str, list[tuple[float, float]]]:
    """What the gate diverted or the twin rejected, per alert: each ``divert`` command's
    window (decided at t: (t, start, end, action)) until the alert's next command replaces
    it (a window decided after its product passed the gate rejects that product all the same)."""
    out = {}
    for aid, cmds in commands.items():
        cmds = sorted(cmds)
        own = [
            (a, min(b, cmds[i + 1][0] if i + 1 < len(cmds) else math.inf))
            for i, (_, a, b, action) in enumerate(cmds)
            if action == "divert"
        ]
        if own:
            out[aid] = own
    return out


def truth(run: Any, spec: LineSpec) -> tuple[np.ndarray, np.ndarray]:
    """(product mass per tick, kg; truly out-of-specification ticks) of a simulated run: the
    true outlet content of the sensor's component against its limits."""
    t = run.t_s
    comp = spec.sensor.component
    lim = next(s for s in spec.spec if s.component == comp)
    c_true = run.outlet_true_pct_w_w[comp]
    mass = sum(f.delivered_kg_h for f in run.feeders.values()) / 3600.0 * float(t[1] - t[0])
    return mass, (c_true < lim.lower_pct_w_w) | (c_true > lim.upper_pct_w_w)


def lot_window_s(spec: LineSpec) -> tuple[float, float]:
    """(t_lo, t_hi): E(t)'s 0.5 % and 99.5 % quantiles, s (the declared blender)."""
    from twin_core.plant.model import rtd_blender_config

    blender = rtd_blender_config(spec).blender
    tk = np.arange(0.0, 2000.0, 0.1)
    e = rtd_kernel(blender, tk)
    f = np.cumsum(e) / np.sum(e)
    return float(tk[np.searchsorted(f, LOT_Q[0])]), float(tk[np.searchsorted(f, LOT_Q[1])])


def score(run: Any, info: dict[str, Any], live: Path, spec: LineSpec) -> dict[str, Any]:
    """The record's decisions against its truth (module docstring)."""
    t = run.t_s
    dt = float(t[1] - t[0])
    mass, oos = truth(run, spec)
    rec = read_recording(live)
    commands: dict[str, list[tuple[float, float, float, str]]] = {}
    alerts, findings = [], []
    for m in rec.messages:
        if m.key.endswith("/divert/command"):
            d = json.loads(m.payload)
            commands.setdefault(d["alert_id"], []).append(
                (d["t"], d["t_start_s"], d["t_end_s"], d["action"])
            )
        elif m.key.endswith("/oos/alert"):
            alerts.append(json.loads(m.payload))
        elif m.key.endswith("/closeloop/finding"):
            findings.append(json.loads(m.payload))
    per_alert = gate_windows(commands)
    windows = [w for own in per_alert.values() for w in own]
    diverts = {
        aid: (min(w[0] for w in own), max(w[1] for w in own), min(c[0] for c in commands[aid]))
        for aid, own in per_alert.items()
    }
    diverted = union_mask(windows, t)
    t_lo, t_hi = lot_window_s(spec)
    allowed = union_mask([(a + t_lo, b + t_hi) for a, b in info["disturbances"]], t)
    for a, b in true_runs(oos):
        allowed[max(0, a - 5) : b + 5] = True
    lat = []
    for a, _ in true_runs(oos):
        ts = t[a]
        hits = [td for wa, wb, td in diverts.values() if wa <= ts + dt and wb >= ts - dt]
        lat.append(min(hits) - ts if hits else math.inf)
    adopted = [f for f in findings if f["status"] == "explained"]
    return {
        **{k: info[k] for k in ("family", "case")},
        "seed": int(run.seed) if run.seed is not None else None,
        "hours": float(t[-1] - t[0] + dt) / 3600.0,
        "production_kg": float(mass.sum()),
        "oos_kg": float(mass[oos].sum()),
        "false_divert_kg": float(mass[diverted & ~oos].sum()),
        "missed_oos_kg": float(mass[oos & ~diverted].sum()),
        "diverted_kg": float(mass[diverted].sum()),
        "stray_divert_s": float(np.sum(diverted & ~allowed) * dt),
        "alerts": len(alerts),
        "oos_episodes": len(lat),
        "latency_s": [x if math.isfinite(x) else None for x in lat],
        "findings": len(findings),
        "adopted": [[e["label"] for e in f["effects"]] for f in adopted],
        "product_at_risk": sum(bool(f.get("product_at_risk")) for f in findings),
        "statuses": {
            s: sum(f["status"] == s for f in findings) for s in {f["status"] for f in findings}
        },
    }


def offline_close_loop(rec: Path, spec: LineSpec) -> dict[str, Any]:
    """``twin close-loop`` on the whole record (offline, default options): status, effects."""
    from twin_core.closeloop import IdentifyOptions
    from twin_core.closeloop.check import check_recording

    r = read_recording(rec)
    report = check_recording(((m.key, m.decode()) for m in r.messages), spec, IdentifyOptions())
    return {"status": report["status"], "effects": [e["label"] for e in report["effects"]]}


# ------------------------------------------------------------------------------ summary
def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for fam in sorted({r["family"] for r in rows}):
        rs = [r for r in rows if r["family"] == fam]
        prod = sum(r["production_kg"] for r in rs)
        hours = sum(r["hours"] for r in rs)
        oos = sum(r["oos_kg"] for r in rs)
        fd = sum(r["false_divert_kg"] for r in rs)
        lat = [x for r in rs for x in r["latency_s"] if x is not None]
        out[fam] = {
            "records": len(rs),
            "hours": hours,
            "production_kg": prod,
            "false_divert_kg": fd,
            "false_divert_pct": 100.0 * fd / prod if prod else 0.0,
            "false_divert_kg_per_day": fd * 24.0 / hours if hours else 0.0,
            "oos_kg": oos,
            "missed_oos_kg": sum(r["missed_oos_kg"] for r in rs),
            "missed_oos_pct": 100.0 * sum(r["missed_oos_kg"] for r in rs) / oos if oos else 0.0,
            "clean_records": sum(r["stray_divert_s"] == 0 for r in rs),
            "oos_episodes": sum(r["oos_episodes"] for r in rs),
            "missed_episodes": sum(x is None for r in rs for x in r["latency_s"]),
            "latency_median_s": float(np.median(lat)) if lat else None,
            "latency_max_s": float(np.max(lat)) if lat else None,
            "adopted_findings": sum(len(r["adopted"]) for r in rs),
            "adopted_offline_nothing": sum(
                len(r["adopted"]) for r in rs if r.get("offline", {}).get("effects") == []
            ),
        }
    return out


def markdown(summary: dict[str, Any], cmd: str, machine: str) -> str:
    head = (
        "| family | records | plant h | false-divert kg (% of production) | false divert kg/day | "
        "missed OOS kg (% of OOS) | records with no stray divert | OOS episodes (missed) | "
        "latency median / max s | findings adopted (offline finds nothing) |\n"
        "|---|---|---|---|---|---|---|---|---|---|\n"
    )
    rows = []
    for fam, s in summary.items():
        lat = (
            f"{s['latency_median_s']:.0f} / {s['latency_max_s']:.0f}"
            if s["latency_median_s"] is not None
            else "-"
        )
        rows.append(
            f"| {fam} | {s['records']} | {s['hours']:.1f} | {s['false_divert_kg']:.3f} "
            f"({s['false_divert_pct']:.3f} %) | {s['false_divert_kg_per_day']:.3f} | "
            f"{s['missed_oos_kg']:.3f} ({s['missed_oos_pct']:.2f} %) | "
            f"{s['clean_records']} / {s['records']} | {s['oos_episodes']} "
            f"({s['missed_episodes']}) | {lat} | {s['adopted_findings']} "
            f"({s['adopted_offline_nothing']}) |"
        )
    return f"`{cmd}` ({machine})\n\n" + head + "\n".join(rows) + "\n"


CASES = {
    "inlist": ["sensor_offset", "dead_zone"],
    "outlist": ["humidity_step", "api_wall_loss"],
    "fault": ["nir_stuck"],
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="out/live_decisions")
    ap.add_argument("--families", default="ordinary,inlist,outlist,fault")
    ap.add_argument("--records", type=int, default=8, help="ordinary records")
    ap.add_argument("--hours", type=float, default=3.0, help="plant hours of an ordinary record")
    ap.add_argument("--speed", type=float, default=100.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--offline", action="store_true", help="also run twin close-loop offline")
    args = ap.parse_args(argv)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    spec = LineSpec.from_file(LINE)
    jobs: list[tuple[str, str, int]] = []
    for fam in args.families.split(","):
        if fam == "ordinary":
            jobs += [("ordinary", "ordinary", args.seed + i) for i in range(args.records)]
        else:
            jobs += [(fam, name, args.seed) for name in CASES[fam]]
    done = out / "records.jsonl"
    rows = [json.loads(x) for x in done.read_text().splitlines()] if done.exists() else []
    seen = {(r["family"], r["case"], r["seed"]) for r in rows}
    for fam, name, seed in jobs:
        if (fam, name, seed) in seen:
            continue
        t0 = time.perf_counter()
        if fam == "ordinary":
            run, msgs, info = ordinary_record(seed, args.hours)
        else:
            run, msgs, info = case_record(fam, name, seed)
        work = out / f"{fam}-{name}-{seed}"
        work.mkdir(exist_ok=True)
        rec = work / "plant.mcap"
        write_messages(rec, msgs)
        live, wall = live_run(rec, work, args.speed)
        row = score(run, info, live, spec)
        row["seed"] = seed
        row["wall_s"] = wall
        if args.offline:
            row["offline"] = offline_close_loop(rec, spec)
        with done.open("a") as fh:
            fh.write(json.dumps(row) + "\n")
        rows.append(row)
        print(
            f"{fam:9s} {name:14s} seed {seed}: false divert {row['false_divert_kg']:.3f} kg, "
            f"missed OOS {row['missed_oos_kg']:.3f} of {row['oos_kg']:.3f} kg, stray "
            f"{row['stray_divert_s']:.0f} s, adopted {row['adopted']} "
            f"({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
    summary = summarize(rows)
    cmd = "python benchmarks/live_decisions.py " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )
    (out / "results.json").write_text(json.dumps({"summary": summary, "records": rows}, indent=2))
    (out / "results.md").write_text(markdown(summary, cmd, machine_line()))
    print(markdown(summary, cmd, machine_line()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
