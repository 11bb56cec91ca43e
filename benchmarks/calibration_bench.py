"""Calibration and feeder benchmarks: our code next to a peer in the same run, with ratios.

Peers: numpy.linalg.lstsq (bare OLS) for the response-surface fit; scipy.optimize.fsolve from
the same multi-start points for the inverse calibration; a plain serial loop for the campaign.
Machine timings are noisy on shared machines: compare the ratios, not the absolute numbers.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np
from scipy.optimize import fsolve
from scipy.stats import qmc

from twin_core.calibration import (
    SEED_BULK_RESPONSES,
    SEED_FACTORS,
    SEED_LEVELS,
    SEED_TABLE_3_4,
    InverseCalibration,
    ResponseSurface,
    TwoStepRSM,
    definitive_screening_design,
    load_seed_table,
)
from twin_core.calibration.campaign import run_campaign, surrogate_drawdown
from twin_core.feeder import LossInWeightFeeder


def timeit(fn, repeat: int = 5) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    bulk = load_seed_table("bulk")
    print("== definitive screening designs")
    for m in (8, 20, 30):
        t = timeit(lambda m=m: definitive_screening_design(m), 3)
        print(f"m={m:2d}: {definitive_screening_design(m).n_runs} runs in {t * 1e3:.1f} ms")

    print("== OLS fit of Eq. (10) (21 runs, 6 coefficients): ours (with ANOVA, SE, p) vs lstsq")
    terms = ["PP_SF", "PP_RF", "PW_SF", "PP_SF*PP_SF", "PW_SF*PW_SF"]
    x = np.column_stack(
        [
            np.ones(21),
            bulk.PP_SF,
            bulk.PP_RF,
            bulk.PW_SF,
            (bulk.PP_SF - 0.35) ** 2,
            (bulk.PW_SF - 0.35) ** 2,
        ]
    )
    y = bulk.shear_angle_deg.to_numpy()
    t_ours = timeit(lambda: ResponseSurface(terms=terms).fit(bulk, "shear_angle_deg"), 20)
    t_peer = timeit(lambda: np.linalg.lstsq(x, y, rcond=None), 20)
    b_ours = ResponseSurface(terms=terms).fit(bulk, "shear_angle_deg").coef_.to_numpy()
    b_peer = np.linalg.lstsq(x, y, rcond=None)[0]
    print(
        f"ours {t_ours * 1e3:.2f} ms, lstsq {t_peer * 1e3:.3f} ms, ratio {t_ours / t_peer:.0f}x; "
        f"max |coef diff| {np.max(np.abs(b_ours - b_peer)):.2e}"
    )

    print("== two-step stepwise (min AICc), 8 factors, 21 runs")
    for r in SEED_BULK_RESPONSES:
        t = timeit(lambda r=r: TwoStepRSM(SEED_FACTORS, criterion="aicc").fit(bulk, r), 2)
        m = TwoStepRSM(SEED_FACTORS, criterion="aicc").fit(bulk, r).model_
        print(
            f"{r:18s} {t:.2f} s  R2 {m.r2_:.3f}  terms {' + '.join('*'.join(t) for t in m.terms_)}"
        )

    print("== inverse calibration, Table 3.4 (seed-term surfaces refitted), 4 unknowns")
    seed_terms = {
        "AOR_deg": ["PP_SF", "PP_COR", "SM", "SM*SM"],
        "shear_angle_deg": terms,
        "mass_lower_kg": [
            "PP_SF",
            "PP_RF",
            "PP_COR",
            "PW_SF",
            "PW_RF",
            "PP_RF*PP_RF",
            "PP_RF*PP_COR",
            "PP_COR*PP_COR",
            "PP_SF*PW_SF",
            "PP_COR*PW_RF",
        ],
        "max_flowrate_kg_s": ["PP_SF", "PP_RF", "PW_SF", "PP_SF*PP_SF"],
    }
    models = {k: ResponseSurface(terms=v).fit(bulk, k) for k, v in seed_terms.items()}
    unknowns = {
        k: (SEED_LEVELS[k][0], SEED_LEVELS[k][2]) for k in ("PP_SF", "PP_RF", "PP_COR", "PW_SF")
    }
    ic = InverseCalibration(models, unknowns, fixed={"PW_RF": 0.01, "SM": 5428571.4286})
    targets = SEED_TABLE_3_4["targets"]
    for method in ("multistart", "de", "both"):
        t0 = time.perf_counter()
        res = ic.solve(targets, n_starts=64, method=method, seed=0)
        dt = time.perf_counter() - t0
        rec = res.recommended
        print(
            f"{method:10s} {dt:.2f} s, {len(res.solutions)} distinct solution(s), recommended "
            + ", ".join(f"{k}={v:.4f}" for k, v in rec.params.items())
            + f", cond {rec.condition_number:.1f}"
        )
    # peer: fsolve from the same Sobol starts, solutions inside the bounds counted
    keys = list(targets)
    lo = np.array([b[0] for b in unknowns.values()])
    hi = np.array([b[1] for b in unknowns.values()])
    names = list(unknowns)

    def f(theta):
        vals = {**{n: [v] for n, v in zip(names, theta)}, "PW_RF": [0.01], "SM": [5428571.4286]}
        return [(models[k].predict(vals)[0] - targets[k]) / models[k].rmse_ for k in keys]

    starts = lo + qmc.Sobol(4, scramble=True, seed=0).random(64) * (hi - lo)
    t0 = time.perf_counter()
    sols = []
    for s in starts:
        th, _, ier, _ = fsolve(f, s, full_output=True)
        if ier == 1 and np.all(th >= lo - 1e-9) and np.all(th <= hi + 1e-9):
            if not any(np.linalg.norm((th - q) / (hi - lo)) < 1e-3 for q in sols):
                sols.append(th)
    dt_peer = time.perf_counter() - t0
    print(f"fsolve (peer, 64 starts, no bounds) {dt_peer:.2f} s, {len(sols)} in-bound solution(s)")
    print("seed (GAMS/BARON):", SEED_TABLE_3_4["solution"])

    print("== loss-in-weight feeder, 1 h at dt = 0.1 s (36,001 steps)")
    feeder = LossInWeightFeeder()
    t = timeit(lambda: feeder.simulate(3600.0, 0.1, seed=0), 3)
    print(f"{t:.3f} s wall, {3600 / t:.0f}x real time, {36001 / t / 1e3:.0f} k steps/s")

    print("== campaign, 21 surrogate runs: serial loop (peer) vs run_campaign (2 threads)")
    design = definitive_screening_design(SEED_LEVELS).physical.reset_index()
    surrogate_drawdown(design.iloc[0].to_dict(), 0)
    t0 = time.perf_counter()
    for _, row in design.iterrows():
        surrogate_drawdown({k: float(row[k]) for k in SEED_FACTORS}, 0)
    t_loop = time.perf_counter() - t0
    with TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        run_campaign(
            design,
            surrogate_drawdown,
            Path(tmp) / "r.csv",
            executor=ThreadPoolExecutor(2),
            progress=False,
        )
        t_camp = time.perf_counter() - t0
    print(
        f"loop {t_loop * 1e3:.0f} ms, campaign {t_camp * 1e3:.0f} ms (bookkeeping + fsync per run), ratio {t_camp / t_loop:.1f}x"
    )


if __name__ == "__main__":
    main()
