"""Size and power of the periodic and residual-spectrum tests on records of the plant simulator.

Records: ``twin_core.closeloop.structure_cases.openworld_case``, the open-world benchmark's
scenario (API and line-rate set-point steps, refills; ``--duration`` s of it) simulated by the
plant with the finite-volume blender, the seed's NIR noise x1 or x2 (declared the same), a code
path independent of the searches' model.

``--mode size``: effect-free records, ``--seeds`` per noise level (the record of seed i at
the k-th noise level is simulated with seed i + 100000 k, so no two share a noise draw). Per
record:

- ``finding``: ``find_structure(kinds=("periodic",))`` gives any finding (a false one);
- ``p_line``: the line search's smallest Bonferroni p over its band, ``p_screw``: the
  screw-locked search's smallest Bonferroni p over feeders x orders (each search runs at half of
  ``search_alpha`` = 1 %: the search stage fires when either is below 0.005);
- ``p_wald_api1``: the Wald p-value of one fixed try (API screw, one pulse per revolution):
  uniform under the null;
- ``p_cumper``: the residual-spectrum test, the cumulative periodogram (Bartlett's
  Kolmogorov-Smirnov test, ``diagnostics.innovation_tests``) of the declared model's innovations
  (``NoiseWhitener``) on the training and held-out windows; ``p_ljung_box`` with it.

``--mode power``: the plant's ``screw_pulsation`` of the API feeder at relative amplitudes
``--amplitudes`` and ``--orders`` pulses per revolution (random phase), ``--seeds`` per cell.
``right``: a periodic finding locked to the API screw whose order interval holds the true
order; ``wrong``: a finding, none right; ``dont_know``: none. Coverage of the order (equivalently
the period at the reported screw speed) and the relative amplitude intervals among the right
ones; ``peak_ratio``: the residual periodogram's largest ordinate (above 0.01 Hz) over its
median on the training window, for scale.

    OPENBLAS_NUM_THREADS=1 python benchmarks/closeloop_periodic.py --mode size --seeds 200 \\
        --duration 1200 --workers 2 --out benchmarks/out/closeloop_periodic_size.csv
    OPENBLAS_NUM_THREADS=1 python benchmarks/closeloop_periodic.py --mode power --seeds 6 \\
        --duration 1800 --amplitudes 0.1,0.2,0.35,0.7 \\
        --out benchmarks/out/closeloop_periodic_power.csv
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from results import read_rows, row_appender
from scipy import stats

from twin_core.closeloop import make_split
from twin_core.closeloop import structure_cases as sc
from twin_core.closeloop.diagnostics import innovation_tests
from twin_core.closeloop.structure import StructureOptions, find_structure
from twin_core.closeloop.structure_base import contiguous_span, residual_context
from twin_core.closeloop.structure_periodic import _fit_screw_locked, _fit_sinusoid, _ScrewSearch
from twin_core.plant.openworld_cases import clopper_pearson_upper

FIELDS = [
    "mode", "amplitude", "order", "noise", "seed", "verdict", "finding", "summary",
    "q", "q_lo", "q_hi", "amp", "amp_lo", "amp_hi", "q_covered", "amp_covered", "peak_ratio",
    "p_line", "p_screw", "p_wald_api1", "p_cumper", "p_ljung_box", "sim_s", "cpu_s",
]  # fmt: skip

OPT = StructureOptions(kinds=("periodic",))


def one(job: tuple[str, float, float, float, int, float]) -> dict:
    """Simulate one record and run the tests on it (see module)."""
    mode, amplitude, order, noise, seed, duration = job
    t0 = time.perf_counter()
    case = sc.openworld_case(duration, seed, noise=noise, amplitude=amplitude, pulses_per_rev=order)
    t1 = time.perf_counter()
    c0 = time.process_time()
    sp = make_split(case.data.t_s)
    found = find_structure(case.data, case.model, train=sp.train, heldout=sp.heldout, options=OPT)
    cpu = time.process_time() - c0
    ctx = residual_context(case.data, case.model, sp.train, sp.heldout, None)
    span = contiguous_span(ctx.train)
    s, lines, _ = _fit_sinusoid(ctx, ctx.resid, span, OPT, 1.0 - 1e-12)
    search = _ScrewSearch(ctx, OPT)
    sl = _fit_screw_locked(search, ctx.resid, 1.0 - 1e-12)
    w_api1 = search.wald(ctx.resid, "api", 1.0)[0] if ("api", 1) in search.tries else np.nan
    both = ctx.train | ctx.held
    e = ctx.whiten(np.where(ctx.finite, ctx.resid / ctx.sigma, 0.0))[both]
    nt = innovation_tests(e)
    x = ctx.resid[ctx.train] - ctx.resid[ctx.train].mean()
    per = np.abs(np.fft.rfft(x)) ** 2
    f = np.fft.rfftfreq(x.size, ctx.dt)
    row = dict(
        mode=mode,
        amplitude=amplitude,
        order=order,
        noise=noise,
        seed=seed,
        finding=len(found),
        summary=found[0].summary[:160] if found else "",
        peak_ratio=round(float(per[f > 0.01].max() / np.median(per[1:])), 2),
        p_line=s.p_search if s is not None else 1.0,
        p_screw=sl.p_search if sl is not None else 1.0,
        p_wald_api1=float(stats.chi2.sf(w_api1, 2)),
        p_cumper=nt["p"]["cumulative_periodogram"],
        p_ljung_box=nt["p"]["ljung_box"],
        sim_s=round(t1 - t0, 2),
        cpu_s=round(cpu, 3),
    )
    verdict = "dont_know"
    for fd in found:
        est = fd.estimates
        if "pulses_per_rev" not in est or "screw of api" not in fd.summary:
            continue
        q, qlo, qhi = est["pulses_per_rev"]
        if amplitude > 0 and qlo - 0.02 <= order <= qhi + 0.02:
            a, alo, ahi = est["relative_amplitude"]
            verdict = "right"
            row.update(q=q, q_lo=qlo, q_hi=qhi, amp=a, amp_lo=alo, amp_hi=ahi)
            row.update(q_covered=qlo <= order <= qhi, amp_covered=alo <= amplitude <= ahi)
            break
    if found and verdict != "right":
        verdict = "wrong"
    row["verdict"] = verdict
    return {k: row.get(k, "") for k in FIELDS}


def _f(x: str) -> float:
    try:
        return float(x)
    except ValueError:
        return float("nan")


def _rate(k: int, n: int) -> str:
    return f"{k} / {n} = {k / max(n, 1):.3f} (upper 95 % {clopper_pearson_upper(k, n):.3f})"


def summarize(rows: list[dict]) -> str:
    out = []
    size = [r for r in rows if r["mode"] == "size"]
    if size:
        out.append("effect-free records (rate, one-sided Clopper-Pearson upper 95 % bound):")
        out.append(
            "noise  n  periodic finding | search stage (either p < 0.005) | Wald API 1/rev "
            "p < 0.05 | cumulative periodogram p < 0.01 | p < 0.0025 | Ljung-Box p < 0.0025"
        )
        by = defaultdict(list)
        for r in size:
            by[_f(r["noise"])].append(r)
        for noise in sorted(by):
            rs = by[noise]
            n = len(rs)
            fin = sum(int(_f(r["finding"]) > 0) for r in rs)
            stage = sum(min(_f(r["p_line"]), _f(r["p_screw"])) < 0.005 for r in rs)
            wald = sum(_f(r["p_wald_api1"]) < 0.05 for r in rs)
            cp1 = sum(_f(r["p_cumper"]) < 0.01 for r in rs)
            cp = sum(_f(r["p_cumper"]) < 0.0025 for r in rs)
            lb = sum(_f(r["p_ljung_box"]) < 0.0025 for r in rs)
            out.append(f"x{noise:g}: n = {n}")
            for name, k in (
                ("periodic finding (nominal <= 1 %)", fin),
                ("search stage fired (nominal 1 %)", stage),
                ("Wald, API 1/rev, p < 0.05 (nominal 5 %)", wald),
                ("cumulative periodogram p < 0.01 (nominal 1 %)", cp1),
                ("cumulative periodogram p < 0.0025 (nominal 0.25 %)", cp),
                ("Ljung-Box p < 0.0025 (nominal 0.25 %)", lb),
            ):
                out.append(f"  {name}: {_rate(k, n)}")
            ks = stats.kstest([_f(r["p_wald_api1"]) for r in rs], "uniform").pvalue
            out.append(f"  Wald API 1/rev p-values vs uniform: KS p {ks:.3f}")
        cpu = np.array([_f(r["cpu_s"]) for r in size])
        out.append(
            f"periodic search CPU per record: median {np.median(cpu):.2f} s, max {cpu.max():.2f} s"
        )
    power = [r for r in rows if r["mode"] == "power"]
    if power:
        out.append("")
        out.append(
            "amplitude order noise  n  right  wrong dont_know  order covered  amplitude covered"
            "  peak/median (median)"
        )
        cells = defaultdict(list)
        for r in power:
            cells[(_f(r["amplitude"]), _f(r["order"]), _f(r["noise"]))].append(r)
        for key in sorted(cells):
            rs = cells[key]
            n = len(rs)
            right = [r for r in rs if r["verdict"] == "right"]
            wrong = sum(r["verdict"] == "wrong" for r in rs)
            dk = sum(r["verdict"] == "dont_know" for r in rs)
            qc = sum(r["q_covered"] == "True" for r in right)
            ac = sum(r["amp_covered"] == "True" for r in right)
            pr = np.median([_f(r["peak_ratio"]) for r in rs])
            out.append(
                f"{key[0]:9.2f} {key[1]:5g} {key[2]:5g} {n:3d} {len(right):5d} {wrong:6d} "
                f"{dk:9d} {qc:6d} / {len(right):<3d} {ac:10d} / {len(right):<3d} {pr:12.0f}"
            )
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mode", choices=("size", "power"), required=True)
    ap.add_argument("--out", default="benchmarks/out/closeloop_periodic.csv")
    ap.add_argument("--seeds", type=int, default=200)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--noise", default="1,2", help="multiples of the seed NIR noise")
    ap.add_argument("--duration", type=float, default=1500.0)
    ap.add_argument("--amplitudes", default="0.05,0.1,0.2,0.35")
    ap.add_argument("--orders", default="1,2")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--summary-only", action="store_true", help="re-print the table of --out")
    args = ap.parse_args()
    out = Path(args.out)
    done = read_rows(out)
    seen = {
        (r["mode"], _f(r["amplitude"]), _f(r["order"]), _f(r["noise"]), int(r["seed"]))
        for r in done
    }
    noises = [float(x) for x in args.noise.split(",")]
    if args.mode == "size":
        cells = [(0.0, 1.0, nz, 100000 * i) for i, nz in enumerate(noises)]
    else:
        cells = [
            (float(a), float(o), nz, 200000 + 100000 * i)
            for i, nz in enumerate(noises)
            for a in args.amplitudes.split(",")
            for o in args.orders.split(",")
        ]
    jobs = [
        (args.mode, a, o, nz, off + s, args.duration)
        for a, o, nz, off in cells
        for s in range(args.first_seed, args.first_seed + args.seeds)
        if (args.mode, a, o, nz, off + s) not in seen
    ]
    if args.summary_only:
        if not done:
            print(f"error: no rows in {out} to summarise, --out={str(out)!r}", file=sys.stderr)
            return 2
        jobs = []
    with (
        row_appender(out, FIELDS, done) as append,
        ProcessPoolExecutor(max(1, args.workers)) as pool,
    ):
        for i, row in enumerate(pool.map(one, jobs)):
            append(row)
            if (i + 1) % 10 == 0:
                print(f"{i + 1}/{len(jobs)} records", flush=True)
    text = summarize(done)
    print(text)
    out.with_suffix(".txt").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
