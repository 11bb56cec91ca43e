"""Size of the joint lack-of-fit test of repeat pulses (``twin_core.rtd.repeats``, docs/rtd.md).

Run: python benchmarks/rtd_repeat_size.py [--sets 200] [--repeats 3] [--noise 1 2] [--jobs 2]
[--out out/rtd_repeat_size]. Resumable: every record is one line of DIR/records.jsonl (its
AD fit's lack-of-fit tests: statistic, df, p-value); a rerun skips the records already there
and prints the table.

Pure repeats: every set is ``--repeats`` records of one axial-dispersion system with
independent noise. The truth is the open-open PDE of ``rtd.virtual.dispersion_pde`` at the
Table 6.2 parameters (11.92 s, 16.37 s, Pe 7.67), a 10 / 7.5 / 6 / 5 g pulse (by set, in
turn), 251 samples at 1 s; the noise is the plant's NIR probe (``plant.nir.add_nir_noise``:
white 0.10, 1/f 0.07 % w/w, 2 % proportional, 0.3 % Laplace outliers of sd 1.5 %, offset
-0.05) at the seed's level and twice it (``plant.nir.scaled_noise``). Neither path is the
fitted model function nor the likelihood's noise model. Each record is fitted by ``ad_open``
(``rtd.likelihood.fit_raw``, baseline fitted: what ``quality.analysis.analyze_repeats`` calls
for each repeat) and the tests of a set are joined by ``rtd.repeats.combine_repeat_tests``.
The table: share of sets flagged inadequate (false flags: every set is pure AD), its
one-sided 95 % Clopper-Pearson upper bound, the share of single records flagged, and each
test's share of combined p-values below its level.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from functools import cache
from multiprocessing import Pool
from pathlib import Path

import numpy as np
from machine import describe

from schemas.line import NIRNoise
from twin_core.plant.nir import add_nir_noise, scaled_noise
from twin_core.plant.openworld_cases import clopper_pearson_upper
from twin_core.rtd import virtual as V
from twin_core.rtd.likelihood import LACK_OF_FIT_ALPHA, fit_raw
from twin_core.rtd.repeats import combine_repeat_tests

T = np.arange(0.0, 251.0)
AMOUNTS_G = (10.0, 7.5, 6.0, 5.0)
TABLE_6_2 = (11.92, 16.37, 7.67)
SEED = 20_261_208


@cache
def truth(amount_g: float) -> np.ndarray:
    """Noise-free outlet concentration (% w/w) of a pulse of ``amount_g`` (PDE truth)."""
    return V.pulse_concentration(V.dispersion_pde(T, *TABLE_6_2), amount_g)


def record(scale: float, set_index: int, repeat: int) -> np.ndarray:
    """One measured record of a set: the set's truth with the NIR probe's noise times
    ``scale``, seeded by (scale, set, repeat)."""
    amount = AMOUNTS_G[set_index % len(AMOUNTS_G)]
    rng = np.random.default_rng([SEED, int(round(10 * scale)), set_index, repeat])
    y, _ = add_nir_noise(truth(amount), scaled_noise(NIRNoise(), scale), rng)
    return y


def task(key: tuple[float, int, int]) -> dict:
    scale, s, r = key
    t0 = time.perf_counter()
    fit = fit_raw(T, record(scale, s, r), "ad_open")
    return {
        "noise": scale,
        "set": s,
        "repeat": r,
        "amount_g": AMOUNTS_G[s % len(AMOUNTS_G)],
        "tests": {
            x.name: {"statistic": x.statistic, "df": list(x.df), "p": x.p_value}
            for x in fit.lack_of_fit.tests
        },
        "noise_fit": fit.lack_of_fit.noise.as_dict(),
        "excluded": int(fit.excluded.size),
        "seconds": time.perf_counter() - t0,
    }


def run(path: Path, keys: list, jobs: int) -> list[dict]:
    done = []
    if path.exists():
        done = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    have = {(d["noise"], d["set"], d["repeat"]) for d in done}
    todo = [k for k in keys if k not in have]
    with path.open("a") as fh, Pool(jobs) as pool:
        for i, row in enumerate(pool.imap_unordered(task, todo), 1):
            fh.write(json.dumps(row) + "\n")
            fh.flush()
            done.append(row)
            print(f"\r{i}/{len(todo)} records", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    return done


def table(rows: list[dict], repeats: int) -> list[str]:
    """Markdown rows: per noise level, complete sets only."""
    out = [
        "| noise | sets | flagged | rate % | 95 % upper bound % | single records flagged % (n) "
        "| shape combined < level % | exchange combined < level % | median s per fit |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for scale in sorted({r["noise"] for r in rows}):
        sets: dict[int, list[dict]] = {}
        for r in rows:
            if r["noise"] == scale:
                sets.setdefault(r["set"], []).append(r)
        full = [sorted(v, key=lambda r: r["repeat"]) for v in sets.values() if len(v) == repeats]
        joints = [combine_repeat_tests([{k: v["p"] for k, v in r["tests"].items()} for r in s])
                  for s in full]  # fmt: skip
        k = sum(not j.adequate for j in joints)
        n = len(joints)
        single = [combine_repeat_tests([{k: v["p"] for k, v in r["tests"].items()}]) for s in full
                  for r in s]  # fmt: skip
        by_test = {}
        for name in ("shape", "exchange"):
            hits = [j.combined[name] < j.levels[name] for j in joints if name in j.combined]
            by_test[name] = f"{100 * np.mean(hits):.1f}" if hits else "-"
        sec = np.median([r["seconds"] for s in full for r in s]) if full else float("nan")
        out.append(
            f"| {scale:g}x | {n} | {k} | {100 * k / max(n, 1):.1f} | "
            f"{100 * clopper_pearson_upper(k, n):.1f} | "
            f"{100 * np.mean([not j.adequate for j in single]):.1f} ({len(single)}) | "
            f"{by_test['shape']} | {by_test['exchange']} | {sec:.1f} |"
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sets", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--noise", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("out/rtd_repeat_size"))
    ap.add_argument("--table-only", action="store_true", help="no new fits: the table of DIR")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    keys = [
        (float(scale), s, r)
        for s in range(args.sets)
        for scale in args.noise
        for r in range(args.repeats)
    ]
    path = args.out / "records.jsonl"
    if args.table_only:
        rows = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
    else:
        rows = run(path, keys, args.jobs)
    print(describe())
    print(f"joint lack-of-fit alpha {LACK_OF_FIT_ALPHA:g}, {args.repeats} repeats per set")
    print("\n".join(table(rows, args.repeats)))


if __name__ == "__main__":
    main()
