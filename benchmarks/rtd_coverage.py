"""Coverage, adequacy and model-selection campaign of the RTD fits (docs/rtd.md).

Run: python benchmarks/rtd_coverage.py [--profiles 100] [--selection 25] [--out DIR]
[--jobs 2] [--adequacy-only]. Resumable: every simulated profile is one line of DIR/coverage.jsonl or
DIR/selection.jsonl; a rerun skips the lines already there and prints the tables.

Truths come from code paths independent of ``rtd.models`` (``rtd.virtual``): axial
dispersion from the PDE, tanks in series from ``scipy.stats.gamma``, an exponentially tailed
peak from a numerical convolution, a stagnant zone from the two-zone PDE. Each truth is
measured with the seed's PAT noise (white 0.10, 1/f 0.07 % w/w, 3 % proportional, offset,
1 % outliers of 1-3 % w/w) and with twice the white, 1/f and proportional parts; pulses of
10 / 7.5 / 6 / 5 g (seed 6.1.2).

Per profile and noise setting:
- coverage: the generating family is fitted by ``quality.analysis.analyze`` (default
  preprocessing, raw-data GLS fit); each nominal 95 % interval (parameters, mean residence
  time, variance, lot boundaries, feasible fraction and h_crit at 10 s) covers the truth or not;
  the documented pipeline before (outliers, auto denoise, PAT truncation, ``fitting.fit`` on E)
  is scored on the same profile for comparison;
- adequacy: AD (``ad_open``) fitted to every profile; share flagged inadequate, by each
  test; ``--adequacy-only`` runs only this on the same profiles (DIR/adequacy.jsonl) and
  prints the noncentrality that bounds any test's power on each stagnant zone;
- selection (``--selection`` profiles of some truths): every registered model ranked by BIC;
  the selected model's family and parameter count, the time of the slowest candidate.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from multiprocessing import Pool
from pathlib import Path

import numpy as np
from machine import describe
from scipy import stats
from tqdm import tqdm

from twin_core.quality.analysis import analyze
from twin_core.quality.funnel import funnel, max_window_fraction
from twin_core.quality.lots import quantile_time
from twin_core.rtd import virtual as V
from twin_core.rtd.denoise import denoise
from twin_core.rtd.fitting import fit
from twin_core.rtd.likelihood import (
    LACK_OF_FIT_ALPHA,
    NoiseModel,
    fit_candidates,
    fit_raw,
    lack_of_fit_levels,
    weighted_bonferroni,
)
from twin_core.rtd.models import MODELS, get_model
from twin_core.rtd.outliers import hampel
from twin_core.rtd.pipeline import Preprocessing, fit_profile
from twin_core.rtd.profiles import e_curve, from_arrays
from twin_core.rtd.repeats import combine_repeat_tests, pool
from twin_core.rtd.truncation import truncate_pat

T = np.arange(0.0, 251.0)
FINE = np.linspace(0.0, 1000.0, 40001)
DURATIONS = np.linspace(0.0, 60.0, 200)
INTENSITIES = np.linspace(0.0, 50.0, 200)
NOISE = {"seed": V.SEED_NOISE, "2x": V.SEED_NOISE.scaled(2.0)}


@dataclass(frozen=True)
class Truth:
    """A virtual system: how its E is computed, its parameters in the fitted family's terms,
    the tracer amount and the family fitted for coverage (None: adequacy only)."""

    name: str
    kind: str
    args: tuple[float, ...]
    amount_g: float
    family: str | None
    params: dict[str, float]

    def e(self, t: np.ndarray) -> np.ndarray:
        if self.kind == "pde":
            return V.dispersion_pde(t, *self.args)
        if self.kind == "gamma":
            return V.tanks_gamma(t, *self.args)
        return V.emg_convolution(t, *self.args)


AD = (11.92, 16.37, 7.67)
TRUTHS = [
    *[
        Truth(f"ad_{g:g}g", "pde", AD, g, "ad_open", dict(zip(("tau_d", "tau", "pe"), AD)))
        for g in (10.0, 7.5, 6.0, 5.0)
    ],
    Truth(
        "ad_pe25", "pde", (10.0, 18.0, 25.0), 10.0, "ad_open", {"tau_d": 10, "tau": 18, "pe": 25}
    ),
    Truth("ad_pe3", "pde", (8.0, 20.0, 3.0), 7.5, "ad_open", {"tau_d": 8, "tau": 20, "pe": 3}),
    Truth("tis_n4", "gamma", (8.0, 24.0, 4.0), 10.0, "tis", {"tau_d": 8, "tau": 24, "n": 4}),
    Truth("emg", "emg", (22.0, 4.0, 12.0), 7.5, "emg", {"mu": 22, "sigma": 4, "tau_e": 12}),
    Truth("stagnant", "pde", (10.0, 14.0, 10.0, 0.3, 25.0), 10.0, None, {}),
    Truth("stagnant_5g", "pde", (10.0, 14.0, 10.0, 0.3, 25.0), 5.0, None, {}),
    Truth("stagnant_weak", "pde", (10.0, 14.0, 10.0, 0.2, 50.0), 10.0, None, {}),
]
SELECTION = ("ad_10g", "ad_5g", "tis_n4", "emg", "stagnant")


def truth_quantities(truth: Truth) -> dict[str, float]:
    """Derived quantities of the truth on a fine, long grid (same definitions as the fit's)."""
    e = truth.e(FINE)
    area = np.trapezoid(e, FINE)
    mean = float(np.trapezoid(FINE * e, FINE) / area)
    var = float(np.trapezoid((FINE - mean) ** 2 * e, FINE) / area)
    grid = FINE[::10]
    eg = e[::10]
    d10 = DURATIONS[int(np.argmin(np.abs(DURATIONS - 10.0)))]
    return {
        "mean_residence_time_s": mean,
        "variance_s2": var,
        "t_lo_s": quantile_time(FINE, e, 0.005),
        "t_hi_s": quantile_time(FINE, e, 0.995),
        "feasible_fraction": funnel(grid, eg, DURATIONS, INTENSITIES, 5.0).feasible_fraction,
        "h_crit_10s": float(5.0 / max_window_fraction(grid, eg, [d10])[0]),
    }


_CACHE: dict[str, tuple[np.ndarray, dict]] = {}


def _compute_truth(name: str) -> tuple[str, list[float], dict]:
    truth = next(x for x in TRUTHS if x.name == name)
    c = V.pulse_concentration(truth.e(T), truth.amount_g)
    return name, c.tolist(), truth_quantities(truth)


def prepare_truths(path: Path, jobs: int, names: list[str] | None = None) -> None:
    """Every truth's measured-grid concentration and derived quantities, computed once (the
    PDE on the long fine grid is the slow part) in parallel, kept in ``path`` for reruns and
    inherited by the workers of the campaign."""
    stored = json.loads(path.read_text()) if path.exists() else {}
    todo = [t.name for t in TRUTHS if t.name not in stored and (names is None or t.name in names)]
    if todo:
        with Pool(jobs) as pool:
            for name, c, q in tqdm(
                pool.imap_unordered(_compute_truth, todo),
                total=len(todo),
                desc="truths",
                file=sys.stderr,
            ):
                stored[name] = {"c": c, "q": q}
                path.write_text(json.dumps(stored))
    for name, v in stored.items():
        _CACHE[name] = (np.asarray(v["c"]), v["q"])


def _truth_data(truth: Truth) -> tuple[np.ndarray, dict]:
    if truth.name not in _CACHE:
        _, c, q = _compute_truth(truth.name)
        _CACHE[truth.name] = (np.asarray(c), q)
    return _CACHE[truth.name]


def _rng(truth: str, noise: str, i: int) -> np.random.Generator:
    key = [ord(ch) for ch in f"{truth}|{noise}"]
    return np.random.default_rng([*key, i])


def _inside(ci: list[float] | tuple[float, float], value: float) -> bool:
    return bool(ci[0] <= value <= ci[1])


def _old_pipeline(y: np.ndarray, truth: Truth) -> dict[str, bool] | None:
    """The documented pipeline before: Hampel, auto denoise, PAT truncation, fit of E."""
    try:
        d = denoise(hampel(y, t=T).y, "auto").y
        tr = truncate_pat(T, d, t_baseline=120.0)
        r = fit(T, e_curve(T, tr), truth.family, scale="free")
    except (ValueError, np.linalg.LinAlgError):
        return None
    return {k: _inside(r.ci[k], v) for k, v in truth.params.items()}


def coverage_task(task: tuple[str, str, int]) -> dict:
    """One profile: coverage of the generating family, the old pipeline, AD adequacy."""
    name, noise, i = task
    truth = next(x for x in TRUTHS if x.name == name)
    c, q = _truth_data(truth)
    y, _ = V.measure(c, NOISE[noise], _rng(name, noise, i))
    prof = from_arrays(T, y, name=f"{name}_{noise}_{i}")
    row: dict = {"truth": name, "noise": noise, "i": i}
    t0 = time.perf_counter()
    a = None
    if truth.family is not None:
        try:
            a = analyze(prof, Preprocessing(), truth.family, durations=DURATIONS)
        except ValueError as exc:
            row["error"] = str(exc)
            return row
        row["seconds"] = time.perf_counter() - t0
        f = a.summary.fit
        ci = f.ci
        cov = {k: _inside(ci[k], v) for k, v in truth.params.items()}
        m = a.summary.moments
        band = a.funnel.at(10.0)
        cov["mean_residence_time_s"] = _inside(
            m["mean_residence_time_s"].ci, q["mean_residence_time_s"]
        )
        cov["variance_s2"] = _inside(m["variance_s2"].ci, q["variance_s2"])
        cov["t_lo_s"] = _inside(a.lots_model["t_lo_s"].ci, q["t_lo_s"])
        cov["t_hi_s"] = _inside(a.lots_model["t_hi_s"].ci, q["t_hi_s"])
        cov["feasible_fraction"] = _inside(a.funnel.feasible_fraction.ci, q["feasible_fraction"])
        cov["h_crit_10s"] = _inside(band["ci"], q["h_crit_10s"])
        row["covered"] = cov
        row["mrt_error_pct"] = 100 * (
            m["mean_residence_time_s"].value / q["mean_residence_time_s"] - 1
        )
        row["adequate_own"] = f.adequate
        row["old"] = _old_pipeline(y, truth)
    t1 = time.perf_counter()
    ad = a.summary if truth.family == "ad_open" else fit_profile(prof, "ad_open")
    row["ad_seconds"] = time.perf_counter() - t1
    row["ad_adequate"] = ad.fit.adequate
    row["ad_p"] = ad.fit.lack_of_fit.p_value
    row["ad_mrt_error_pct"] = 100 * (
        ad.moments["mean_residence_time_s"].value / q["mean_residence_time_s"] - 1
    )
    return row


def adequacy_task(task: tuple[str, str, int]) -> dict:
    """One profile (the same as :func:`coverage_task`'s): AD fitted, its lack-of-fit tests."""
    name, noise, i = task
    truth = next(x for x in TRUTHS if x.name == name)
    c, q = _truth_data(truth)
    y, _ = V.measure(c, NOISE[noise], _rng(name, noise, i))
    t0 = time.perf_counter()
    try:
        ad = fit_profile(from_arrays(T, y, name=f"{name}_{noise}_{i}"), "ad_open")
    except ValueError as exc:  # e.g. a fit past its time limit: counted, not scored
        return {"truth": name, "noise": noise, "i": i, "error": str(exc)}
    lof = ad.fit.lack_of_fit
    return {
        "truth": name,
        "noise": noise,
        "i": i,
        "ad_seconds": time.perf_counter() - t0,
        "ad_adequate": ad.fit.adequate,
        "ad_p": lof.p_value,
        "ad_tests": {x.name: [x.statistic, x.p_value] for x in lof.tests},
        "ad_mrt_error_pct": 100
        * (ad.moments["mean_residence_time_s"].value / q["mean_residence_time_s"] - 1),
        "ad_mrt": [
            ad.moments["mean_residence_time_s"].value,
            ad.moments["mean_residence_time_s"].stderr,
        ],
        "truth_mrt": q["mean_residence_time_s"],
    }


def exchange_noncentrality(truth: Truth, noise: str) -> float:
    """delta = min over AD of |L^-1 (c - mu_AD)|^2: the whitened misfit of the best AD fit to
    the noise-free truth c (with the offset) under its true noise covariance (white, 1/f,
    proportional of ``NOISE[noise]``; the model's 1/f correlation). It is the noncentrality of
    the likelihood ratio of AD against the truth's own family, so no test of AD at one-sided
    level a has a power above Phi(sqrt(delta) - z_a) on profiles of this truth."""
    c, _ = _truth_data(truth)
    spec = NOISE[noise]
    nm = NoiseModel(spec.white**2, spec.pink**2, spec.proportional**2)
    ad = fit_raw(T, c + spec.offset_mean, "ad_open", noise=nm, screen=False, extension=False)
    return ad.chi2


def noncentrality_table() -> str:
    """Markdown table: the stagnant-zone truths' noncentrality and the power it allows."""
    level = lack_of_fit_levels(["shape", "exchange"])["exchange"]
    z = float(stats.norm.isf(level))
    lines = [
        "| truth | noise | delta | sqrt(delta) | power bound at one-sided "
        f"{100 * level:g} % | at 5 % |",
        "|---|---|---|---|---|---|",
    ]
    for truth in TRUTHS:
        if truth.family is not None:
            continue
        for noise in NOISE:
            d = exchange_noncentrality(truth, noise)
            bound = [stats.norm.cdf(np.sqrt(d) - x) for x in (z, stats.norm.isf(0.05))]
            lines.append(
                f"| {truth.name} | {noise} | {d:.1f} | {np.sqrt(d):.2f} | "
                f"{100 * bound[0]:.0f} | {100 * bound[1]:.0f} |"
            )
    return "\n".join(lines)


def selection_task(task: tuple[str, str, int]) -> dict:
    """One profile: every registered model ranked by BIC."""
    name, noise, i = task
    truth = next(x for x in TRUTHS if x.name == name)
    c, _ = _truth_data(truth)
    y, _ = V.measure(c, NOISE[noise], _rng(name, noise, 10_000 + i))
    t0, c0 = time.perf_counter(), time.process_time()
    r = fit_candidates(T, y, list(MODELS))
    best = r.best
    return {
        "truth": name,
        "noise": noise,
        "i": i,
        "selected": best.model,
        "selected_k": len(get_model(best.model).params),
        "family": truth.family or "ad_open_dead",
        "family_weight": sum(
            w for f, w in zip(r.fits, r.weights) if f.model == (truth.family or "ad_open_dead")
        ),
        "max_candidate_s": max(f.seconds for f in r.fits),
        "candidate_s": {f.model: f.seconds for f in r.fits},
        "cpu_seconds": time.process_time() - c0,
        "failed": r.failed,
        "seconds": time.perf_counter() - t0,
    }


def _run(path: Path, tasks: list, fn, jobs: int, desc: str) -> list[dict]:
    done = []
    if path.exists():
        done = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    have = {(r["truth"], r["noise"], r["i"]) for r in done}
    todo = [t for t in tasks if t not in have]
    with path.open("a") as fh, Pool(jobs) as pool:
        bar = tqdm(total=len(tasks), initial=len(tasks) - len(todo), desc=desc, file=sys.stderr)
        for row in pool.imap_unordered(fn, todo):
            fh.write(json.dumps(row) + "\n")
            fh.flush()
            done.append(row)
            bar.update()
        bar.close()
    return done


def _pct(x: list[bool]) -> str:
    return f"{100 * np.mean(x):.1f}" if x else "-"


def _pct_sd(x: list[bool]) -> str:
    """Share in % with its binomial sd, 100 sqrt(p (1 - p) / n)."""
    if not x:
        return "-"
    p = float(np.mean(x))
    return f"{100 * p:.1f} ({100 * np.sqrt(p * (1 - p) / len(x)):.1f})"


def coverage_tables(rows: list[dict]) -> str:
    """Markdown tables: coverage per truth and noise, old pipeline, adequacy."""
    keys = ["mean_residence_time_s", "variance_s2", "t_lo_s", "t_hi_s"]
    keys += ["feasible_fraction", "h_crit_10s"]
    lines = [
        "| truth | noise | n | parameters (each) | MRT | variance | t_lo | t_hi | feasible frac. | "
        "h_crit(10 s) | old pipeline (each) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for truth in TRUTHS:
        for noise in NOISE:
            sub = [r for r in rows if r["truth"] == truth.name and r["noise"] == noise]
            ok = [r for r in sub if "covered" in r]
            if ok:
                pars = " / ".join(_pct([r["covered"][k] for r in ok]) for k in truth.params)
                old = [r["old"] for r in ok if r.get("old")]
                olds = " / ".join(_pct([o[k] for o in old]) for k in truth.params)
                cells = " | ".join(_pct([r["covered"][k] for r in ok]) for k in keys)
                lines.append(f"| {truth.name} | {noise} | {len(ok)} | {pars} | {cells} | {olds} |")
    lines += [
        "",
        "Pooled over the truths:",
        "",
        "| noise | profiles | parameters | MRT | variance | t_lo | t_hi | feasible frac. | "
        "h_crit(10 s) | old pipeline, parameters |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for noise in NOISE:
        ok = [r for r in rows if r["noise"] == noise and "covered" in r]
        if ok:
            pars = [v for r in ok for k, v in r["covered"].items() if k not in keys]
            cells = " | ".join(_pct_sd([r["covered"][k] for r in ok]) for k in keys)
            old = [v for r in ok if r.get("old") for v in r["old"].values()]
            lines.append(f"| {noise} | {len(ok)} | {_pct_sd(pars)} | {cells} | {_pct_sd(old)} |")
    errors = [r for r in rows if "error" in r]
    tail = [f"\nprofiles refused: {len(errors)}"] + [
        f"  {r['truth']} {r['error']}" for r in errors[:5]
    ]
    secs = [r["seconds"] for r in rows if "seconds" in r]
    tail.append(
        f"analyze wall time per profile: median {np.median(secs):.2f} s, 95th percentile "
        f"{np.percentile(secs, 95):.2f} s"
    )
    return "\n".join(lines + tail)


def _ad_flagged(row: dict) -> bool:
    """AD flagged inadequate: a test's p-value below its current level (rows keep the
    p-values, so a rerun scores them at the levels of the code), else the stored verdict."""
    tests = row.get("ad_tests")
    if not tests:
        return not row["ad_adequate"]
    return weighted_bonferroni({k: v[1] for k, v in tests.items()})[0] < LACK_OF_FIT_ALPHA


def adequacy_tables(rows: list[dict]) -> str:
    """Markdown table: share of profiles whose AD fit is flagged inadequate (binomial sd),
    by each test, and the AD mean residence time error; pure AD pooled per noise setting."""
    lines = [
        "| truth | noise | n | AD flagged inadequate % (sd) | shape test % | exchange / tail "
        "test % | exchange p < 5 % | AD MRT error % (median) | AD fit + tests, s (median) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    groups = [(t.name, [t.name]) for t in TRUTHS]
    groups.append(("pure AD", [t.name for t in TRUTHS if t.name.startswith("ad_")]))
    for label, names in groups:
        for noise in NOISE:
            sub = [
                r for r in rows if r["truth"] in names and r["noise"] == noise and "error" not in r
            ]
            if not sub:
                continue
            tests = [r.get("ad_tests", {}) for r in sub]
            by_test = {
                k: _pct([x[k][1] < lack_of_fit_levels(list(x))[k] for x in tests if k in x])
                for k in ("shape", "exchange", "tail")
            }
            lines.append(
                f"| {label} | {noise} | {len(sub)} | "
                f"{_pct_sd([_ad_flagged(r) for r in sub])} | {by_test['shape']} | "
                f"{by_test['exchange'] if by_test['exchange'] != '-' else by_test['tail']} | "
                f"{_pct([x['exchange'][1] < 0.05 for x in tests if 'exchange' in x])} | "
                f"{np.median([r['ad_mrt_error_pct'] for r in sub]):+.1f} | "
                f"{np.median([r['ad_seconds'] for r in sub]):.1f} |"
            )
    failed = [r for r in rows if "error" in r and "ad_tests" not in r]
    lines.append(f"\nAD fits that failed (not scored): {len(failed)}")
    lines += [f"  {r['truth']} {r['noise']} {r['i']}: {r['error']}" for r in failed[:5]]
    return "\n".join(lines)


def _tail_flag(j) -> bool:
    """The joint stagnant-tail test (exchange, or tail where most repeats kept it) flags."""
    name = "exchange" if "exchange" in j.combined else "tail"
    return bool(j.combined.get(name, 1.0) < j.levels.get(name, 0.0))


def repeats_tables(rows: list[dict], k: int) -> str:
    """Markdown table: profiles of one truth and noise taken k at a time (disjoint, by index)
    as repeat pulses of one system (``twin_core.rtd.repeats``): share of the k-tuples whose
    joint AD lack of fit is flagged, by each combined test, and the coverage of the pooled
    mean residence time's 95 % interval (the pure AD truths)."""
    lines = [
        f"| truth | noise | {k}-tuples | AD flagged jointly % (sd) | shape % | exchange % | "
        "one profile flagged % | pooled MRT interval covers % (sd) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    groups = [(t.name, [t.name]) for t in TRUTHS]
    groups.append(("pure AD", [t.name for t in TRUTHS if t.name.startswith("ad_")]))
    for label, names in groups:
        for noise in NOISE:
            tuples = []
            for name in names:
                sub = sorted(
                    (
                        r
                        for r in rows
                        if r["truth"] == name and r["noise"] == noise and "ad_mrt" in r
                    ),
                    key=lambda r: r["i"],
                )
                tuples += [sub[j : j + k] for j in range(0, len(sub) - k + 1, k)]
            if not tuples:
                continue
            joint = [
                combine_repeat_tests([{n: v[1] for n, v in r["ad_tests"].items()} for r in tup])
                for tup in tuples
            ]
            covers = []
            if label.startswith("ad") or label == "pure AD":
                for tup in tuples:
                    pl = pool([r["ad_mrt"][0] for r in tup], [r["ad_mrt"][1] for r in tup])
                    covers.append(pl.ci[0] <= tup[0]["truth_mrt"] <= pl.ci[1])
            single = [_ad_flagged(r) for tup in tuples for r in tup]
            lines.append(
                f"| {label} | {noise} | {len(tuples)} | {_pct_sd([not j.adequate for j in joint])} | "
                f"{_pct([j.combined['shape'] < j.levels['shape'] for j in joint])} | "
                f"{_pct([_tail_flag(j) for j in joint])} | "
                f"{_pct(single)} | {_pct_sd(covers)} |"
            )
    return "\n".join(lines)


def selection_tables(rows: list[dict]) -> str:
    """Markdown table: what BIC selects per truth and noise; the wall time of a candidate
    (median over candidates and profiles, and the slowest) and the failed candidates."""
    lines = [
        "| truth | noise | n | generating family selected % | an AD model (ad_open / ad_closed) "
        "% | more parameters than the truth % | median weight of the family | candidate wall "
        "s, median / max | failed candidates |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    true_k = {"ad_open": 3, "tis": 3, "emg": 3, "ad_open_dead": 5}
    for name in SELECTION:
        for noise in NOISE:
            sub = [r for r in rows if r["truth"] == name and r["noise"] == noise]
            if not sub:
                continue
            fam = sub[0]["family"]
            fails = sum(len(r["failed"]) for r in sub)
            each = [s for r in sub for s in r.get("candidate_s", {}).values()]
            med = f"{np.median(each):.1f}" if each else "-"
            lines.append(
                f"| {name} | {noise} | {len(sub)} | {_pct([r['selected'] == fam for r in sub])} | "
                f"{_pct([r['selected'] in ('ad_open', 'ad_closed') for r in sub])} | "
                f"{_pct([r['selected_k'] > true_k[fam] for r in sub])} | "
                f"{np.median([r['family_weight'] for r in sub]):.2f} | "
                f"{med} / {max(r['max_candidate_s'] for r in sub):.1f} | {fails} |"
            )
    cpu = [r["cpu_seconds"] for r in rows if "cpu_seconds" in r]
    if cpu:
        lines.append(
            f"\nCPU time per profile (all candidates): median {np.median(cpu):.1f} s, max "
            f"{max(cpu):.1f} s ({len(cpu)} profiles)"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profiles", type=int, default=100, help="profiles per truth and noise")
    ap.add_argument("--selection", type=int, default=25, help="profiles for model selection")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("out/rtd_coverage"))
    ap.add_argument(
        "--adequacy-only",
        action="store_true",
        help="only the AD fit and its lack-of-fit tests on the same profiles (adequacy.jsonl)",
    )
    ap.add_argument(
        "--repeats",
        type=int,
        default=0,
        help="with --adequacy-only: also score the profiles k at a time as repeat pulses",
    )
    ap.add_argument(
        "--zone-profiles",
        type=int,
        default=None,
        help="with --adequacy-only: profiles per stagnant-zone truth and noise (default --profiles)",
    )
    ap.add_argument("--truths", nargs="+", default=None, help="only these truths")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    print(describe())
    # profile index outermost: a campaign stopped early is balanced across truths and noises
    zone = args.profiles if args.zone_profiles is None else args.zone_profiles
    wanted = [t for t in TRUTHS if args.truths is None or t.name in args.truths]
    prepare_truths(args.out / "truths.json", args.jobs, [t.name for t in wanted])
    tasks = [
        (t.name, n, i)
        for i in range(max(args.profiles, zone if args.adequacy_only else 0))
        for t in wanted
        for n in NOISE
        if i < (zone if (args.adequacy_only and t.family is None) else args.profiles)
    ]
    if args.adequacy_only:
        # the AD and stagnant-zone truths (size and power of the test) before the others
        tasks.sort(key=lambda x: x[0] in ("tis_n4", "emg"))
        rows = _run(args.out / "adequacy.jsonl", tasks, adequacy_task, args.jobs, "adequacy")
        print(adequacy_tables(rows))
        if args.repeats > 1:
            print(repeats_tables(rows, args.repeats))
        print(noncentrality_table())
        return
    if tasks:  # --profiles 0: the selection table alone
        rows = _run(args.out / "coverage.jsonl", tasks, coverage_task, args.jobs, "coverage")
        print(coverage_tables(rows))
        print(adequacy_tables(rows))
    sel = [(t, n, i) for i in range(args.selection) for t in SELECTION for n in NOISE]
    srows = _run(args.out / "selection.jsonl", sel, selection_task, args.jobs, "selection")
    print(selection_tables(srows))


if __name__ == "__main__":
    main()
