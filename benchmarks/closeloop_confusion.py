"""Confusion table of the close-loop identification on plant runs with a hidden effect.

For every effect of the registry, magnitudes (``--levels``: indices into
``twin_core.closeloop.scenarios.EFFECT_MAGNITUDES`` plus level ``-1`` = half of the smallest),
noise scales (``--noise``: multipliers of the seed NIR noise) and seeds, the plant simulator
runs the standard scenario (1500 s, tracer pulses, refills, flow dips) with that effect hidden;
runs without an effect measure the false-claim rate. One CSV row per run (appended, so an
interrupted benchmark resumes), then the confusion table (truth x first effect claimed) and
the rates are printed and written next to the CSV.

    python benchmarks/closeloop_confusion.py --out benchmarks/out/closeloop_confusion.csv \
        --seeds 5 --null-seeds 40
"""

from __future__ import annotations

import argparse
import time
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
from results import read_rows, row_appender
from tqdm import tqdm

from schemas.line import NIRNoise
from twin_core.closeloop import IdentifyOptions, RunData, close_loop
from twin_core.closeloop.scenarios import EFFECT_MAGNITUDES, effect_spec, standard_scenario
from twin_core.plant import LineModel, simulate_line

FIELDS = [
    "truth",
    "level",
    "noise",
    "seed",
    "params",
    "status",
    "found",
    "correct_first",
    "found_all",
    "alternatives",
    "rmse_before_heldout",
    "rmse_after_heldout",
    "rmse_true_heldout",
    "best_rel_improvement",
    "seconds",
]


def _spec(name: str, level: int) -> dict:
    if level >= 0:
        return effect_spec(name, level)
    s = effect_spec(name, 0)
    null = {"gain": 1.0, "pe_factor": 1.0}
    keep = set() if name == "sensor_lag" else {"tau_s"}  # time constants of surges/zones stay
    s["params"] = {
        k: (null[k] + (v - null[k]) / 2 if k in null else (v if k in keep else v / 2))
        for k, v in s["params"].items()
    }
    return s


def one(
    truth: str, level: int, noise: float, seed: int, duration: float, opts: IdentifyOptions
) -> dict:
    cfg, dist = standard_scenario(duration)
    n = cfg.sensor.noise
    cfg.sensor.noise = NIRNoise(
        white_sd=n.white_sd * noise,
        pink_sd=n.pink_sd * noise,
        proportional_rel=n.proportional_rel * noise,
        outlier_prob=n.outlier_prob,
        outlier_sd=n.outlier_sd,
        baseline_offset=n.baseline_offset,
    )
    effs = [] if truth == "none" else [_spec(x, level) for x in truth.split("+")]
    t0 = time.perf_counter()
    run = simulate_line(cfg, duration, seed=seed, effects=effs, disturbances=dist)
    res = close_loop(RunData.from_line_run(run), LineModel(cfg), opts)
    dt = time.perf_counter() - t0
    found = [lab.split("[")[0] for lab in res.effects_found]
    sp = res.ident.split
    true_rmse = float(
        np.sqrt(
            np.nanmean(
                (run.measured_pct_w_w - run.sensor_true_pct_w_w)[sp.heldout & ~run.outliers] ** 2
            )
        )
    )
    e = res.errors()
    best = (
        max((f.rel_improvement for f in res.ident.steps[0]), default=float("nan"))
        if res.ident.steps
        else float("nan")
    )
    return {
        "truth": truth,
        "level": level,
        "noise": noise,
        "seed": seed,
        "params": ";".join(f"{k}={v:g}" for s in effs for k, v in s["params"].items()),
        "status": res.status,
        "found": "+".join(found) or "none",
        "correct_first": int((found[:1] == [truth]) if truth != "none" else (not found)),
        "alternatives": "+".join(a for f in res.ident.accepted for a in f.alternatives) or "",
        "found_all": int(
            sorted(found) == sorted(truth.split("+")) if truth != "none" else not found
        ),
        "rmse_before_heldout": e["before"]["heldout"]["rmse"],
        "rmse_after_heldout": e["after"]["heldout"]["rmse"],
        "rmse_true_heldout": true_rmse,
        "best_rel_improvement": best,
        "seconds": dt,
    }


def summarize(rows: list[dict]) -> str:
    lines = []
    pairs = [r for r in rows if "+" in r["truth"]]
    rows = [r for r in rows if "+" not in r["truth"]]
    truths = sorted({r["truth"] for r in rows})
    found_names = sorted({r["found"].split("+")[0] for r in rows})
    conf: dict[str, Counter] = defaultdict(Counter)
    for r in rows:
        conf[r["truth"]][r["found"].split("+")[0]] += 1
    w = max(len(x) for x in truths + found_names) + 1
    lines.append("confusion (rows: hidden effect, columns: first effect claimed)")
    lines.append(" " * w + "".join(f"{c[:9]:>10}" for c in found_names) + f"{'n':>6}{'right':>8}")
    for tname in truths:
        n = sum(conf[tname].values())
        right = conf[tname]["none" if tname == "none" else tname]
        lines.append(
            f"{tname:<{w}}"
            + "".join(f"{conf[tname][c]:>10d}" for c in found_names)
            + f"{n:>6d}{right / n:>8.2f}"
        )
    eff = [r for r in rows if r["truth"] != "none"]
    null = [r for r in rows if r["truth"] == "none"]
    if eff:
        acc = np.mean([int(r["correct_first"]) for r in eff])
        acc_alt = np.mean(
            [
                int(r["correct_first"])
                or r["truth"] in [a.split("[")[0] for a in r.get("alternatives", "").split("+")]
                for r in eff
            ]
        )
        drop = np.mean(
            [float(r["rmse_after_heldout"]) < float(r["rmse_before_heldout"]) for r in eff]
        )
        lines.append(
            f"effect runs: {len(eff)}, right effect first: {acc:.3f} (right or reported as an "
            f"indistinguishable alternative: {acc_alt:.3f}), held-out RMSE dropped: {drop:.3f}"
        )
        by_level = defaultdict(list)
        for r in eff:
            by_level[(int(r["level"]), float(r["noise"]))].append(int(r["correct_first"]))
        for k in sorted(by_level):
            lines.append(
                f"  level {k[0]:+d} noise x{k[1]:g}: {np.mean(by_level[k]):.3f} ({len(by_level[k])} runs)"
            )
    if null:
        fp = np.mean([r["found"] != "none" for r in null])
        lines.append(f"no-effect runs: {len(null)}, effect claimed in: {fp:.3f}")
        best = np.array([float(r["best_rel_improvement"]) for r in null])
        lines.append(
            "no-effect runs, best candidate's held-out relative MSE drop (the margin must exceed "
            f"it): p50 {np.percentile(best, 50):.4f}, p95 {np.percentile(best, 95):.4f}, "
            f"max {best.max():.4f}"
        )
        stat = Counter(r["status"] for r in null)
        lines.append(f"no-effect runs status: {dict(stat)}")
    if pairs:
        lines.append("two-effect runs (both found, nothing else):")
        by = defaultdict(list)
        for r in pairs:
            by[r["truth"]].append(r)
        for k, rs in sorted(by.items()):
            ok = np.mean([int(r["found_all"]) for r in rs])
            lines.append(
                f"  {k}: {ok:.2f} ({len(rs)} runs; found: {', '.join(r['found'] for r in rs)})"
            )
    secs = [float(r["seconds"]) for r in rows + pairs]
    lines.append(f"seconds per run: median {np.median(secs):.2f}, total {np.sum(secs):.0f}")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", default="benchmarks/out/closeloop_confusion.csv")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--null-seeds", type=int, default=20)
    ap.add_argument("--levels", default="-1,0,1")
    ap.add_argument("--noise", default="1,2")
    ap.add_argument("--effects", default=",".join(sorted(EFFECT_MAGNITUDES)))
    ap.add_argument("--duration", type=float, default=1500.0)
    ap.add_argument(
        "--pairs",
        default="dead_zone+sensor_offset,bypass+sensor_gain,refill_surge+sensor_lag,"
        "back_mixing+sensor_drift,extra_delay+feed_factor_drift",
        help="two-effect cases (both at level 0), empty for none",
    )
    ap.add_argument("--pair-seeds", type=int, default=3)
    ap.add_argument("--summary-only", action="store_true", help="re-print the table of --out")
    ap.add_argument("--select", default="bic_all", choices=("bic_all", "heldout"))
    args = ap.parse_args()
    out = Path(args.out)
    done = read_rows(out)
    seen = {(r["truth"], int(r["level"]), float(r["noise"]), int(r["seed"])) for r in done}
    levels = [int(x) for x in args.levels.split(",")]
    noises = [float(x) for x in args.noise.split(",")]
    jobs = [
        (name, lv, nz, 1000 * (lv + 2) + s)
        for name in args.effects.split(",")
        for lv in levels
        for nz in noises
        for s in range(args.seeds)
    ]
    jobs += [("none", 0, nz, 90000 + s) for nz in noises for s in range(args.null_seeds)]
    jobs += [
        (pair, 0, 1.0, 70000 + s)
        for pair in (args.pairs.split(",") if args.pairs else [])
        for s in range(args.pair_seeds)
    ]
    todo = [j for j in jobs if (j[0], j[1], j[2], j[3]) not in seen]
    if args.summary_only:
        todo = []
    opts = IdentifyOptions(select=args.select)
    with row_appender(out, FIELDS, done) as append:
        for j in tqdm(todo, desc="close-loop runs"):
            append(one(*j, duration=args.duration, opts=opts))
    text = summarize(done)
    print(text)
    out.with_suffix(".txt").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
