"""Rates of the structure searches (``twin_core.closeloop.structure``) on independent cases.

Per seed, the 2-hour scenario of ``twin_core.closeloop.structure_cases`` is simulated twice
(constant throughput, and the throughput levels 100 / 125 / 85 / 110 %), and at every noise
scale (``--noise``: multiples of the seed NIR noise, declared the same) these records are made
from them:

- ``none`` on both (the declared model is the truth): any finding is a false one;
- ``throughput_tau`` (tau proportional to 1 / Q^k, k = 1 and 0.5; piecewise simulation);
- ``pulsation_screw`` (API flow pulsation at the API screw's rotation frequency, 20 % and 10 %)
  and ``pulsation_cycle`` (75 s API limit cycle carried by the reported screw speed, 2 % and
  1 %);
- ``two_zone`` (two-zone exchange blender integrated as an ODE; stagnant hold-up 0.04 and
  0.02 kg, exchange 3.6 kg/h).

The declared model is searched with the default options (first 60 % trains, last 40 % held
out). Verdicts: ``right`` (a finding of the true kind that says the truth: the frequency within
the multitaper bandwidth; tau against the throughput or a covariate moving with it; a kernel),
``wrong`` (findings, none of them right), ``dont_know`` (no finding). Interval coverage: the
true value inside the finding's 95 % interval (frequency and amplitude; the slope of tau and the
window levels when the covariate is the throughput; mean residence time and standard deviation
of the kernel on its window). One CSV row per record (appended, so a run resumes), then the
summary is printed and written next to the CSV.

    python benchmarks/closeloop_structure.py --seeds 50 --workers 2
    python benchmarks/closeloop_structure.py --seeds 60 --first-seed 50 --only none \\
        --out benchmarks/out/closeloop_structure_null.csv
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from results import read_rows, row_appender
from scipy import stats

from twin_core.closeloop import make_split
from twin_core.closeloop import structure_cases as sc
from twin_core.closeloop.structure import StructureFinding, find_structure
from twin_core.closeloop.structure_kernel import kernel_shape

FIELDS = [
    "case",
    "level",
    "noise",
    "seed",
    "verdict",
    "kinds",
    "detail",
    "covered",
    "n_intervals",
    "cpu_s",
    "wall_s",
]


def _coverage_periodic(f: StructureFinding, truth: dict) -> list[bool]:
    out = []
    for key in ("frequency_hz", "amplitude_pct_w_w"):
        _, lo, hi = f.estimates[key]
        out.append(lo <= truth[key] <= hi)
    return out


def _true_tau(truth: dict, q: float) -> float:
    return truth["tau_ref"] * (truth["q_ref"] / q) ** truth["exponent"]


def _coverage_tau(f: StructureFinding, truth: dict) -> list[bool]:
    c = f.curves
    if c["param"] != "blender.tau" or c["covariate"] != "throughput":
        return []
    x, lev, se = np.asarray(c["x"]), np.asarray(c["levels"]), np.asarray(c["se"])
    true_lev = np.array([_true_tau(truth, q) for q in x])
    out = [bool(abs(a - b) <= 1.96 * s) for a, b, s in zip(lev, true_lev, se)]
    slope_true = float(np.polyfit(x, true_lev, 1)[0])
    _, lo, hi = next(v for k, v in f.estimates.items() if ":slope_per_" in k)
    out.append(lo <= slope_true <= hi)
    return out


def _coverage_kernel(f: StructureFinding, truth: dict) -> list[bool]:
    lag = np.asarray(f.curves["lag_s"])
    rtd = np.interp(lag, truth["rtd_lag_s"], truth["rtd"])
    t_tail = float(f.evidence.get("tail_time_s", lag[-1]))
    shape = kernel_shape(lag, rtd, t_tail)
    out = []
    for key, val in (("mean_residence_time_s", shape.mean_s), ("sd_s", shape.sd_s)):
        _, lo, hi = f.estimates[key]
        out.append(lo <= val <= hi)
    return out


def verdict(case: sc.StructureCase, found: list[StructureFinding]) -> tuple[str, str, list[bool]]:
    """(right | wrong | dont_know | none_ok | false, detail, coverage flags)."""
    truth = case.truth
    kind = truth.get("kind")
    if not found:
        return ("none_ok" if kind is None else "dont_know"), "", []
    detail = " | ".join(f.summary for f in found)
    if kind is None:
        return "false", detail, []
    for f in found:
        if f.kind != kind:
            continue
        if kind == "periodic":
            bw = float(f.evidence.get("bandwidth_hz", 0.0))
            if abs(f.estimates["frequency_hz"][0] - truth["frequency_hz"]) <= bw:
                return "right", detail, _coverage_periodic(f, truth)
        elif kind == "parameter_dependence":
            c = f.curves
            names = [f"{c['param']} vs {c['covariate']}", *f.alternatives]
            ok = any(
                n.startswith(f"blender.tau vs {cov}")
                for n in names
                for cov in ("throughput", "excipient:screw_speed")
            )
            if ok:
                return "right", detail, _coverage_tau(f, truth)
        else:
            return "right", detail, _coverage_kernel(f, truth)
    return "wrong", detail, []


def _cases(run_v, run_c, seed: int) -> list[tuple[str, int, Callable[[], sc.StructureCase]]]:
    return [
        ("none_vary", 0, lambda: sc.none_case(run_v, seed)),
        ("none_const", 0, lambda: sc.none_case(run_c, seed + 1)),
        ("throughput_tau", 1, lambda: sc.throughput_tau_case(run_v, seed + 2, exponent=1.0)),
        ("throughput_tau", 0, lambda: sc.throughput_tau_case(run_v, seed + 3, exponent=0.5)),
        ("pulsation_screw", 1, lambda: sc.pulsation_case(run_c, seed + 4, 0.2)),
        ("pulsation_screw", 0, lambda: sc.pulsation_case(run_c, seed + 5, 0.1)),
        ("pulsation_cycle", 1, lambda: sc.pulsation_case(run_c, seed + 6, 0.02, 75.0, True)),
        ("pulsation_cycle", 0, lambda: sc.pulsation_case(run_c, seed + 7, 0.01, 75.0, True)),
        ("two_zone", 1, lambda: sc.two_zone_case(run_c, seed + 8, stagnant_kg=0.04)),
        ("two_zone", 0, lambda: sc.two_zone_case(run_c, seed + 9, stagnant_kg=0.02)),
    ]


def seed_rows(
    seed: int, duration: float, noises: list[float], tracer: bool, only: tuple[str, ...] = ()
) -> list[dict]:
    """All records of one seed (see module); ``only``: case-name prefixes to run (all if
    empty)."""
    base_v = sc.base_run(duration, 1000 + seed, vary_throughput=True, tracer_pulses=tracer)
    base_c = sc.base_run(duration, 2000 + seed, vary_throughput=False, tracer_pulses=tracer)
    rows = []
    for nz in noises:
        run_v, run_c = sc.with_noise_scale(base_v, nz), sc.with_noise_scale(base_c, nz)
        for name, level, make in _cases(run_v, run_c, 100 * seed + int(10 * nz)):
            if only and not name.startswith(only):
                continue
            case = make()
            sp = make_split(case.data.t_s)
            t0, c0 = time.perf_counter(), time.process_time()
            found = find_structure(case.data, case.model, train=sp.train, heldout=sp.heldout)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            v, detail, cov = verdict(case, found)
            rows.append(
                {
                    "case": name,
                    "level": level,
                    "noise": nz,
                    "seed": seed,
                    "verdict": v,
                    "kinds": "+".join(f.kind for f in found) or "none",
                    "detail": detail,
                    "covered": sum(cov),
                    "n_intervals": len(cov),
                    "cpu_s": round(cpu, 4),
                    "wall_s": round(wall, 4),
                }
            )
    return rows


def _upper95(k: int, n: int) -> float:
    """Clopper-Pearson upper 95 % bound of a rate k / n."""
    return 1.0 if k >= n else float(stats.beta.ppf(0.975, k + 1, n - k))


def summarize(rows: list[dict]) -> str:
    lines = []
    null = [r for r in rows if r["case"].startswith("none")]
    by_noise = defaultdict(list)
    for r in null:
        by_noise[float(r["noise"])].append(r["verdict"] == "false")
    lines.append("effect-free records (any structure finding is false):")
    for nz in sorted(by_noise):
        v = by_noise[nz]
        lines.append(
            f"  noise x{nz:g}: {sum(v)} / {len(v)} = {np.mean(v):.3f} "
            f"(upper 95 % {_upper95(sum(v), len(v)):.3f})"
        )
    groups = defaultdict(list)
    for r in rows:
        if not r["case"].startswith("none"):
            groups[(r["case"], int(r["level"]), float(r["noise"]))].append(r)
    lines.append(
        f"{'case':<17}{'level':>6}{'noise':>6}{'n':>5}{'right':>7}{'wrong':>7}"
        f"{'dont_know':>10}{'coverage':>10}"
    )
    for key in sorted(groups):
        rs = groups[key]
        n = len(rs)
        cnt = {v: sum(r["verdict"] == v for r in rs) for v in ("right", "wrong", "dont_know")}
        cov = sum(int(r["covered"]) for r in rs)
        ncov = sum(int(r["n_intervals"]) for r in rs)
        lines.append(
            f"{key[0]:<17}{key[1]:>6d}{key[2]:>6g}{n:>5d}{cnt['right'] / n:>7.2f}"
            f"{cnt['wrong'] / n:>7.2f}{cnt['dont_know'] / n:>10.2f}"
            f"{(cov / ncov if ncov else math.nan):>10.2f}"
        )
    cpu = np.array([float(r["cpu_s"]) for r in rows])
    wall = np.array([float(r["wall_s"]) for r in rows])
    lines.append(
        f"search time per 2-hour record: CPU median {np.median(cpu):.3f} s, p95 "
        f"{np.percentile(cpu, 95):.3f} s, max {cpu.max():.3f} s; wall median "
        f"{np.median(wall):.3f} s ({len(rows)} records)"
    )
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", default="benchmarks/out/closeloop_structure.csv")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--noise", default="1,2")
    ap.add_argument("--duration", type=float, default=7200.0)
    ap.add_argument("--tracer", action="store_true", help="API tracer pulses every 15 min")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--only", default="", help="comma-separated case-name prefixes (e.g. none)")
    ap.add_argument("--summary-only", action="store_true", help="re-print the table of --out")
    args = ap.parse_args()
    out = Path(args.out)
    done = read_rows(out)
    seen = {int(r["seed"]) for r in done}
    noises = [float(x) for x in args.noise.split(",")]
    only = tuple(x for x in args.only.split(",") if x)
    todo = [s for s in range(args.first_seed, args.first_seed + args.seeds) if s not in seen]
    if args.summary_only:
        if not done:
            print(f"error: no rows in {out} to summarise, --out={str(out)!r}", file=sys.stderr)
            return 2
        todo = []
    with (
        row_appender(out, FIELDS, done) as append,
        ProcessPoolExecutor(max(1, args.workers)) as pool,
    ):
        futures = [
            pool.submit(seed_rows, s, args.duration, noises, args.tracer, only) for s in todo
        ]
        for i, fut in enumerate(futures):
            for row in fut.result():
                append(row)
            print(f"seed {todo[i]} done ({i + 1}/{len(todo)})", flush=True)
    text = summarize(done)
    print(text)
    out.with_suffix(".txt").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
