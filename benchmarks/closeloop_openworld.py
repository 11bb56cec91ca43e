"""Open-world confusion benchmark of the close-loop: effects in and out of the candidate
library, data faults, product/probe look-alikes, and effect-free runs.

Each run simulates a case of ``twin_core.plant.openworld_cases`` (2 h at 1 Hz: API set-point
steps, a line-rate step, three API refills with the load cell frozen, the seed's NIR noise x1
or x2, with or without tracer pulses), turns it into the line's bus messages (data faults
applied there), and runs the current method on them: ``twin_core.closeloop.check.
check_recording`` (the message-to-array adapter, then ``twin_core.closeloop.close_loop``). The
report dict is scored against the known truth (``openworld_cases.score_report``): right /
wrong-confident / "don't know", claims on effect-free data with their upper 95 % bound, data
faults flagged, look-alikes (both sides listed, product at risk, a discriminating measurement
named), time per run.

One CSV row per run, appended as runs finish (process pool, ``--workers``), so an interrupted
benchmark resumes; the summary (markdown tables) is printed and written next to the CSV.

    OPENBLAS_NUM_THREADS=1 python benchmarks/closeloop_openworld.py --out benchmarks/out/closeloop_openworld.csv \
        --null-seeds 200 --seeds 3 --workers 2

``--timing`` puts a random timing fault in every run (``twin_core.plant.faults.
random_timing_fault``: a refill flag or screw speed 1-3 samples off the rest of its feeder's
messages, a source's clock 0.5-5 s off, stamp jitter up to half a period, irregular sampling,
1-5 % of the ticks lost or re-sent), drawn from the run's case, setting and seed; ``--paired``
with the CSV of the same runs without it gives the share of runs whose status and claims the
timing fault left unchanged.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import time
import zlib
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
from machine import describe
from results import read_rows, row_appender
from tqdm import tqdm

from twin_core.closeloop.check import check_recording
from twin_core.closeloop.identify import IdentifyOptions
from twin_core.closeloop.scenarios import EFFECT_MAGNITUDES, effect_spec
from twin_core.plant.faults import DataFault, random_timing_fault
from twin_core.plant.openworld_cases import (
    DURATION_S,
    FAULT_CASES,
    LOOKALIKE_PAIRS,
    OUT_OF_LIST,
    Case,
    Setting,
    clopper_pearson_upper,
    run_case,
    score_report,
)

FIELDS = [
    "family", "case", "truth", "side", "setting", "tracers", "noise", "seed", "blender",
    "status", "outcome", "claimed", "listed", "equivalents_field", "product_at_risk",
    "discriminating", "flagged", "status_data_quality", "both_listed", "lookalike_ok",
    "n_data_quality", "effect_rms", "product_rms", "product_mean", "noise_sd", "match_rms",
    "rmse_before_heldout", "rmse_after_heldout", "sim_s", "method_s", "error", "timing",
    "clock_offsets",
]  # fmt: skip

#: duration of the standard scenario the in-list magnitudes were sized for
STANDARD_S = 1500.0
FAMILY_SEED = {"none": 100000, "inlist": 200000, "outlist": 300000, "fault": 400000,
               "lookalike": 500000}  # fmt: skip


def inlist_spec(name: str, level: int, duration_s: float) -> dict:
    """The scenario magnitude of an in-list effect (``scenarios.effect_spec``; level -1: half
    of level 0, time constants kept, a sensor lag halved), its drift rates scaled so the drift
    reached at the end of the run equals the standard scenario's."""
    spec = effect_spec(name, max(level, 0))
    params = dict(spec["params"])
    if level < 0:
        null = {"gain": 1.0, "pe_factor": 1.0}
        keep = set() if name == "sensor_lag" else {"tau_s"}
        params = {
            k: (null[k] + (v - null[k]) / 2 if k in null else (v if k in keep else v / 2))
            for k, v in params.items()
        }
    params = {k: v * STANDARD_S / duration_s if k == "rate_per_h" else v for k, v in params.items()}
    return {**spec, "params": params}


def cases(args: argparse.Namespace) -> list[tuple[Case, int]]:
    """Every case with its number of seeds."""
    out: list[tuple[Case, int]] = [(Case("none", "none"), args.null_seeds)]
    for name in args.inlist.split(",") if args.inlist else []:
        for lv in (int(x) for x in args.levels.split(",")):
            spec = inlist_spec(name, lv, args.duration)
            out.append((Case("inlist", f"{name}@{lv:+d}", effects=(spec,)), args.seeds))
    for name in args.outlist.split(",") if args.outlist else []:
        out.append((Case("outlist", name, open_world=(OUT_OF_LIST[name],)), args.seeds))
    for name in args.faults.split(",") if args.faults else []:
        out.append((Case("fault", name, faults=FAULT_CASES[name]), args.fault_seeds))
    for pair in args.pairs.split(",") if args.pairs else []:
        for role in ("product", "probe"):
            out.append((Case.lookalike(pair, role), args.seeds))
    return out


def settings(spec: str) -> list[Setting]:
    """``"0:1,1:2"`` -> (no tracers, noise x1), (tracers, noise x2)."""
    out = []
    for item in spec.split(","):
        tr, nz = item.split(":")
        out.append(Setting(bool(int(tr)), float(nz)))
    return out


def job_key(row: dict) -> tuple[str, str, int]:
    return (str(row["case"]), str(row["setting"]), int(row["seed"]))


def timing_fault(case: Case, setting: Setting, seed: int) -> tuple[DataFault, ...]:
    """The random timing fault of a run (``--timing``): drawn from the run's seed, case and
    setting (``twin_core.plant.faults.random_timing_fault``), so a run keeps its fault."""
    key = zlib.crc32(f"{case.name}|{setting.label}|{seed}".encode())
    return random_timing_fault(key, ("api", "excipient"))


def one(job: tuple[Case, Setting, int, float, dict, bool]) -> dict:
    """Simulate one case, run the current method on its messages, score the report."""
    case, setting, seed, duration, options, timing = job
    t0 = time.perf_counter()
    fault = timing_fault(case, setting, seed) if timing else ()
    cr = run_case(case, setting, seed, duration, timing=fault)
    t1 = time.perf_counter()
    error = ""
    try:
        report = check_recording(
            cr.messages, cr.run.config, IdentifyOptions(**options), recording=case.name
        )
    except Exception as exc:  # the method failing on a record is a result, not a crash
        report = {"status": "error"}
        error = f"{type(exc).__name__}: {exc}"[:300]
    t2 = time.perf_counter()
    score = score_report(report, cr.truth)
    errs = report.get("errors") or {}
    row = {k: cr.truth.get(k, "") for k in FIELDS if k in cr.truth}
    row.update({k: score.get(k, "") for k in FIELDS if k in score})
    row.update(
        case=case.name,
        claimed="+".join(score["claimed"]),
        listed="+".join(score["listed"]),
        rmse_before_heldout=(errs.get("before") or {}).get("heldout", {}).get("rmse", ""),
        rmse_after_heldout=(errs.get("after") or {}).get("heldout", {}).get("rmse", ""),
        sim_s=round(t1 - t0, 3),
        method_s=round(t2 - t1, 3),
        error=error,
        timing=_timing_label(cr.truth.get("timing")),
        clock_offsets="; ".join(
            f"{c['series']} {c['offset_s']:+.2f} s [{c['low_s']:+.2f}, {c['high_s']:+.2f}]"
            for c in report.get("clock_offsets") or []
        ),
    )
    return {k: row.get(k, "") for k in FIELDS}


def _timing_label(truth: dict | None) -> str:
    """``kind stream size/share`` of a run's timing fault ('' without one)."""
    if not truth:
        return ""
    return f"{truth['kind']} {truth['stream']} {truth.get('size', 0.0):+g} n={truth['n_samples']}"


# ---------------------------------------------------------------------------------------------
# summary
# ---------------------------------------------------------------------------------------------
def _f(x: str) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def _b(x: str) -> bool:
    return str(x) == "True"


def _table(header: list[str], rows: list[list]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return out


OUTCOMES = ("right", "right_equivalent", "wrong_confident", "wrong_partial", "dont_know")


def _outcome_rows(rows: list[dict], key) -> list[list]:
    groups: dict[str, list[dict]] = defaultdict(list)
    for r in rows:
        groups[key(r)].append(r)
    table = []
    for k in sorted(groups):
        g = groups[k]
        c = Counter(r["outcome"] for r in g)
        table.append([k, len(g), *[c[o] for o in OUTCOMES], sum(1 for r in g if r["error"])])
    return table


def summarize(rows: list[dict]) -> str:
    """Markdown tables of the results (see the module docstring)."""
    by = defaultdict(list)
    for r in rows:
        by[r["family"]].append(r)
    lines: list[str] = []
    head = ["", "n", *OUTCOMES, "errors"]
    if by["none"]:
        lines.append("**Effect-free runs** (a claim: any effect named)")
        lines.append("")
        t = []
        for s in sorted({r["setting"] for r in by["none"]}):
            g = [r for r in by["none"] if r["setting"] == s]
            k = sum(r["outcome"] == "claim" for r in g)
            stat = Counter(r["status"] for r in g)
            fit = np.array([_f(r["effect_rms"]) for r in g])
            t.append([s, len(g), k, f"{k / len(g):.3f}", f"{clopper_pearson_upper(k, len(g)):.3f}",
                      ", ".join(f"{a} {b}" for a, b in sorted(stat.items())),
                      f"{np.nanmax(fit):.1e}"])  # fmt: skip
        lines += _table(
            [
                "setting",
                "runs",
                "claims",
                "rate",
                "upper 95 %",
                "status",
                "max RMS truth - declared",
            ],
            t,  # fmt: skip
        )
        lines.append("")
    for fam, title in (("inlist", "In-list effects"), ("outlist", "Out-of-list effects")):
        if not by[fam]:
            continue
        lines.append(f"**{title}** (per hidden effect, all settings)")
        lines.append("")
        lines += _table(head, _outcome_rows(by[fam], lambda r: r["case"]))
        lines.append("")
        lines += _table(head, _outcome_rows(by[fam], lambda r: r["setting"]))
        lines.append("")
        if fam == "inlist":
            big = [r for r in by[fam] if _f(r["effect_rms"]) >= 2 * _f(r["noise_sd"])]
            small = [r for r in by[fam] if _f(r["effect_rms"]) < 2 * _f(r["noise_sd"])]
            for name, g in (("RMS >= 2x noise SD", big), ("RMS < 2x noise SD", small)):
                if g:
                    c = Counter(r["outcome"] for r in g)
                    lines.append(
                        f"- {name}: {len(g)} runs, right {c['right'] / len(g):.3f}, right or "
                        f"equivalent {(c['right'] + c['right_equivalent']) / len(g):.3f}, wrong "
                        f"claims {(c['wrong_confident'] + c['wrong_partial']) / len(g):.3f}"
                    )
            lines.append("")
        else:
            prod = [r for r in by[fam] if r["side"] == "product"]
            expl = sum(r["outcome"] == "wrong_confident" for r in by[fam])
            lines.append(
                f"- `explained` with a mechanism neither true nor listed: {expl} of "
                f"{len(by[fam])} ({expl / len(by[fam]):.3f}); product-side effects with "
                f"product_at_risk true: {sum(r['product_at_risk'] == 'True' for r in prod)} of "
                f"{len(prod)}"
            )
            lines.append("")
    if by["fault"]:
        lines.append("**Data faults** (effect-free runs with the fault in the record)")
        lines.append("")
        t = []
        for k in sorted({r["case"] for r in by["fault"]}):
            g = [r for r in by["fault"] if r["case"] == k]
            stat = Counter(r["status"] for r in g)
            t.append([k, len(g), sum(_b(r["flagged"]) for r in g),
                      sum(_b(r["status_data_quality"]) for r in g),
                      sum(r["outcome"] == "claim" for r in g),
                      ", ".join(f"{a} {b}" for a, b in sorted(stat.items())),
                      "; ".join(sorted({r["claimed"] for r in g if r["claimed"]}))])  # fmt: skip
        lines += _table(
            [
                "fault",
                "runs",
                "flagged",
                "status data_quality",
                "effect claimed",
                "status",
                "claims",
            ],
            t,  # fmt: skip
        )
        lines.append("")
    if by["lookalike"]:
        lines.append("**Product/probe look-alikes** (success: both listed, product_at_risk, a "
                     "discriminating measurement)")  # fmt: skip
        lines.append("")
        t = []
        for k in sorted({r["case"] for r in by["lookalike"]}):
            g = [r for r in by["lookalike"] if r["case"] == k]
            t.append([k, len(g), sum(r["outcome"] == "right" for r in g),
                      sum(_b(r["both_listed"]) for r in g),
                      sum(r["product_at_risk"] == "True" for r in g),
                      sum(_b(r["discriminating"]) for r in g),
                      sum(_b(r["lookalike_ok"]) for r in g),
                      "; ".join(sorted({r["claimed"] or "-" for r in g})),
                      f"{np.nanmax([_f(r['match_rms']) for r in g]):.3f}"
                      if any(r["match_rms"] for r in g) else ""])  # fmt: skip
        lines += _table(
            [
                "case",
                "runs",
                "truth claimed",
                "both listed",
                "product_at_risk",
                "measurement",
                "success",
                "claimed",
                "match RMS",
            ],
            t,  # fmt: skip
        )
        lines.append("")
    m = np.array([_f(r["method_s"]) for r in rows])
    s = np.array([_f(r["sim_s"]) for r in rows])
    lines.append(
        f"Runs: {len(rows)}; method seconds per run: median {np.median(m):.2f}, p95 "
        f"{np.percentile(m, 95):.2f}, max {m.max():.2f} (total {m.sum() / 3600:.2f} h); "
        f"simulation: median {np.median(s):.2f} s."
    )
    return "\n".join(lines)


def paired_summary(rows: list[dict], aligned: list[dict]) -> str:
    """Runs whose outcome (status and claimed effects) is the one of the same run (case,
    setting, seed) without its timing fault, per family and timing-fault kind."""
    base = {job_key(r): r for r in aligned}
    pairs = [(r, base[job_key(r)]) for r in rows if job_key(r) in base]
    if not pairs:
        return "No paired runs."
    same = [r["status"] == b["status"] and r["claimed"] == b["claimed"] for r, b in pairs]
    t = []
    for label, key in (("family", lambda r: r["family"]),
                       ("timing fault", lambda r: (r["timing"] or "none").split(" ")[0])):  # fmt: skip
        for k in sorted({key(r) for r, _ in pairs}):
            g = [s for (r, _), s in zip(pairs, same) if key(r) == k]
            t.append([f"{label}: {k}", len(g), sum(g), f"{sum(g) / len(g):.3f}"])
    t.append(["all", len(same), sum(same), f"{sum(same) / len(same):.3f}"])
    changed = [
        f"{r['case']} seed {r['seed']} ({r['timing']}): {b['status']} {b['claimed'] or '-'} -> "
        f"{r['status']} {r['claimed'] or '-'}"
        for (r, b), s in zip(pairs, same)
        if not s
    ]
    lines = ["**Outcome unchanged by the timing fault** (status and claims as without it)", ""]
    lines += _table(["runs", "n", "unchanged", "share"], t)
    if changed:
        lines += ["", "Changed: " + "; ".join(changed)]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", default="benchmarks/out/closeloop_openworld.csv")
    ap.add_argument("--settings", default="0:1,0:2,1:1,1:2", help="tracers:noise, ...")
    ap.add_argument("--null-seeds", type=int, default=200, help="effect-free runs per setting")
    ap.add_argument("--seeds", type=int, default=3, help="runs per effect case and setting")
    ap.add_argument("--fault-seeds", type=int, default=2, help="runs per fault case and setting")
    ap.add_argument("--inlist", default=",".join(sorted(EFFECT_MAGNITUDES)))
    ap.add_argument("--levels", default="-1,0", help="in-list magnitudes (-1: half of 0)")
    ap.add_argument("--outlist", default=",".join(OUT_OF_LIST))
    ap.add_argument("--faults", default=",".join(FAULT_CASES))
    ap.add_argument("--pairs", default=",".join(LOOKALIKE_PAIRS))
    ap.add_argument("--duration", type=float, default=DURATION_S)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--options", default="{}", help="IdentifyOptions fields as JSON")
    ap.add_argument("--summary-only", action="store_true", help="re-print the tables of --out")
    ap.add_argument(
        "--timing",
        action="store_true",
        help="a random timing fault per run (twin_core.plant.faults.random_timing_fault)",
    )
    ap.add_argument(
        "--paired",
        default="",
        help="CSV of the same runs without timing faults: the share of runs whose outcome "
        "(status and claims) a timing fault left unchanged",
    )
    args = ap.parse_args()
    out = Path(args.out)
    done = read_rows(out)
    seen = {job_key(r) for r in done}
    options = json.loads(args.options)
    jobs = [
        (case, st, FAMILY_SEED[case.family] + i, args.duration, options, args.timing)
        for case, n in cases(args)
        for i in range(n)
        for st in settings(args.settings)
    ]
    # the cases of one seed run together (they share the feeders' simulation)
    jobs.sort(key=lambda j: (j[2], j[0].family, j[0].name))
    todo = [] if args.summary_only else [
        j for j in jobs if (j[0].name, j[1].label, j[2]) not in seen
    ]  # fmt: skip
    print(describe())
    t0 = time.perf_counter()
    if todo:
        with (
            row_appender(out, FIELDS, done) as append,
            mp.get_context("fork").Pool(args.workers) as pool,
        ):
            for row in tqdm(pool.imap_unordered(one, todo, chunksize=4), total=len(todo),
                            desc="open-world runs"):  # fmt: skip
                append(row)
    text = summarize(done)
    if args.paired:
        text += "\n\n" + paired_summary(done, read_rows(Path(args.paired)))
    text += f"\nWall time of this invocation: {(time.perf_counter() - t0) / 60:.1f} min, " \
            f"{len(todo)} runs, {args.workers} workers."  # fmt: skip
    print(text)
    out.with_suffix(".md").write_text(describe() + "\n\n" + text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
