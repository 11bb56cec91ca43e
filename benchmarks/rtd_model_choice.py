"""Model choice over mixed truths: `twin rtd analyze --fit all` on systems of several kinds
(docs/rtd.md, "Model choice that cannot run away").

Run: python benchmarks/rtd_model_choice.py [--profiles 50] [--jobs 2] [--out DIR]
[--truths NAME ...]. Resumable: every profile is one line of DIR/model_choice.jsonl; a rerun
skips the lines already there and prints the table.

Every registered model is fitted to the raw profile and ranked (``rtd.pipeline.fit_profile``
with ``all``: record-bounded parameters, candidates on a bound or with a degenerate interval
or a mean residence time outside the record not selected, the mean residence time averaged
over the candidates that fit). Scored per truth and noise: the share of profiles whose 95 %
interval of the mean residence time covers the truth, the selected models, the share with a
selected mean residence time outside the record, the share where the averaged interval was
used, and the share of profiles on which the AD candidate (``ad_open``) was flagged
inadequate.

Truths, each from a code path apart from ``rtd.models`` (a 250 s record at 1 s, pulses of
10 g as the seed's 6.1.2, ``rtd.virtual.pulse_concentration``):

- ``ad``: axial dispersion at Table 6.2 (11.92 s, 16.37 s, Pe 7.67), the method-of-lines PDE
  (``rtd.virtual.dispersion_pde``);
- ``tis``: tanks in series (8 s, 24 s, n = 4), ``scipy.stats.gamma`` (``rtd.virtual``);
- ``cstr_pfr``: a plug-flow delay of 10.3 s before a CSTR of 20 s, the closed form written
  here (Levenspiel 1999 ch. 12);
- ``emg``: a skewed peak, a Gaussian (22 s, 4 s) convolved numerically with an exponential
  decay of 12 s (``rtd.virtual.emg_convolution``);
- ``dead_zone``: AD (10 s, 14 s, Pe 10) exchanging with a stagnant zone (r = 0.3,
  tau_x = 25 s), the two-zone PDE (``rtd.virtual.dispersion_pde``);
- ``bypass``: 15 % of the flow through a CSTR of 5 s after the delay, the rest through the AD
  PDE of ``ad``, mixed here;
- ``drift``: ``ad`` with a baseline rising by 0.4 % w/w with a 60 s time constant (the NIR
  warming up; the record still passes the profile checks).

Noise: the seed's NIR noise (``rtd.virtual.SEED_NOISE``: white 0.10, 1/f 0.07 % w/w, 3 %
proportional, offset, 1 % outliers of 1-3 % w/w) and twice its white, 1/f and proportional
parts. The truth's mean residence time is that of its E on 0-1000 s at 0.1 s.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from functools import lru_cache
from multiprocessing import Pool
from pathlib import Path

import numpy as np
from machine import describe
from scipy import stats
from tqdm import tqdm

from twin_core.rtd import virtual as V
from twin_core.rtd.pipeline import fit_profile
from twin_core.rtd.profiles import from_arrays

T = np.arange(0.0, 251.0)
FINE = np.arange(0.0, 1000.0 + 0.05, 0.1)
NOISE = {"seed": V.SEED_NOISE, "2x": V.SEED_NOISE.scaled(2.0)}
AD = (11.92, 16.37, 7.67)
TRUTHS = ("ad", "tis", "cstr_pfr", "emg", "dead_zone", "bypass", "drift")
#: the truth's own family among the candidates (the drift's is AD's)
FAMILY = {
    "ad": "ad_open",
    "tis": "tis",
    "cstr_pfr": "cstr_pfr",
    "emg": "emg",
    "dead_zone": "ad_open_dead",
    "bypass": "ad_open_bypass",
    "drift": "ad_open",
}


def cstr_after_plug_flow(t: np.ndarray, delay: float, tau: float) -> np.ndarray:
    """E of a plug-flow delay before a CSTR: exp(-(t - delay) / tau) / tau after the delay."""
    s = t - delay
    return np.where(s >= 0.0, np.exp(-np.clip(s, 0.0, None) / tau) / tau, 0.0)


@lru_cache(maxsize=2)
def _ad_pde(t: tuple[float, ...]) -> np.ndarray:
    return V.dispersion_pde(np.asarray(t), *AD)


def truth_e(name: str, t: np.ndarray) -> np.ndarray:
    """E(t) (1/s) of a truth (module docstring)."""
    if name in ("ad", "drift"):
        return _ad_pde(tuple(t))
    if name == "tis":
        return V.tanks_gamma(t, 8.0, 24.0, 4.0)
    if name == "cstr_pfr":
        return cstr_after_plug_flow(t, 10.3, 20.0)
    if name == "emg":
        return V.emg_convolution(t, 22.0, 4.0, 12.0)
    if name == "dead_zone":
        return V.dispersion_pde(t, 10.0, 14.0, 10.0, 0.3, 25.0)
    if name == "bypass":
        return 0.15 * cstr_after_plug_flow(t, AD[0], 5.0) + 0.85 * _ad_pde(tuple(t))
    raise ValueError(f"truth must be one of {TRUTHS}, got {name!r}")


def drift(name: str, t: np.ndarray) -> np.ndarray:
    """The baseline added to the measured profile (0 but for ``drift``)."""
    return 0.4 * (1.0 - np.exp(-t / 60.0)) if name == "drift" else np.zeros_like(t)


_CACHE: dict[str, tuple[np.ndarray, float]] = {}


def truth(name: str) -> tuple[np.ndarray, float]:
    """(noise-free concentration on T, true mean residence time)."""
    if name not in _CACHE:
        e = truth_e(name, FINE)
        mrt = float(np.trapezoid(FINE * e, FINE) / np.trapezoid(e, FINE))
        c = V.pulse_concentration(np.interp(T, FINE, e), 10.0)
        _CACHE[name] = (c, mrt)
    return _CACHE[name]


def _rng(name: str, noise: str, i: int) -> np.random.Generator:
    return np.random.default_rng([*(ord(ch) for ch in f"choice|{name}|{noise}"), i])


def task(job: tuple[str, str, int]) -> dict:
    """One profile: every model ranked, the selection and the mean residence time scored."""
    name, noise, i = job
    c, mrt = truth(name)
    y, _ = V.measure(c, NOISE[noise], _rng(name, noise, i))
    y = y + drift(name, T)
    row: dict = {"truth": name, "noise": noise, "i": i, "truth_mrt": mrt}
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        s = fit_profile(from_arrays(T, y, name=f"{name}_{noise}_{i}"), "all")
    except ValueError as exc:
        row["error"] = str(exc)
        return row
    m = s.moments["mean_residence_time_s"]
    own = s.averaging["selected_model_mean_residence_time_s"] if s.averaging else m.as_dict()
    ad = next((f for f in s.ranking.fits if f.model == "ad_open"), None)
    row |= {
        "selected": s.fit.model,
        "selected_adequate": s.fit.adequate,
        "mrt": [m.value, m.ci[0], m.ci[1]],
        "covered": bool(m.ci[0] <= mrt <= m.ci[1]),
        "selected_mrt": [own["value"], *own["ci"]],
        "selected_covered": bool(own["ci"][0] <= mrt <= own["ci"][1]),
        "selected_mrt_in_record": bool(T[0] < own["value"] < T[-1]),
        "averaged": [x["model"] for x in s.averaging["models"]] if s.averaging else [],
        "excluded": s.ranking.excluded,
        "candidates": {
            f.model: [
                w,
                f.adequate,
                *([m.value, *m.ci] if (m := s.ranking.mrt.get(f.model)) else []),
            ]
            for f, w in zip(s.ranking.fits, s.ranking.weights)
        },
        "failed": s.ranking.failed,
        "ad_adequate": None if ad is None else bool(ad.adequate),
        "seconds": time.perf_counter() - t0,
        "cpu_seconds": time.process_time() - c0,
    }
    return row


def _run(path: Path, jobs: list, n_jobs: int) -> list[dict]:
    done = []
    if path.exists():
        done = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
    have = {(r["truth"], r["noise"], r["i"]) for r in done}
    todo = [j for j in jobs if j not in have]
    with path.open("a") as fh, Pool(n_jobs) as pool:
        bar = tqdm(total=len(jobs), initial=len(jobs) - len(todo), file=sys.stderr)
        for row in pool.imap_unordered(task, todo):
            fh.write(json.dumps(row) + "\n")
            fh.flush()
            done.append(row)
            bar.update()
        bar.close()
    return done


def _pct_sd(x: list[bool]) -> str:
    """Share in % with its binomial sd, and a 95 % Clopper-Pearson interval."""
    if not x:
        return "-"
    k, n = int(np.sum(x)), len(x)
    p = k / n
    lo = stats.beta.ppf(0.025, k, n - k + 1) if k > 0 else 0.0
    hi = stats.beta.ppf(0.975, k + 1, n - k) if k < n else 1.0
    return f"{100 * p:.1f} ({100 * np.sqrt(p * (1 - p) / n):.1f}; {100 * lo:.0f}-{100 * hi:.0f})"


def table(rows: list[dict]) -> str:
    """Markdown table per truth and noise, and pooled."""
    lines = [
        "| truth | noise | n | MRT interval covers % (sd; 95 % CI) | selected model's own "
        "covers % | averaged % | selected MRT outside the record | own family selected % | "
        "selected (count) | AD flagged inadequate % | median MRT error % | CPU s (median) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    groups = [(name, [name]) for name in TRUTHS] + [("pooled", list(TRUTHS))]
    for label, names in groups:
        for noise in NOISE:
            sub = [r for r in rows if r["truth"] in names and r["noise"] == noise]
            ok = [r for r in sub if "error" not in r]
            if not sub:
                continue
            sel: dict[str, int] = {}
            for r in ok:
                sel[r["selected"]] = sel.get(r["selected"], 0) + 1
            top = ", ".join(f"{k} {v}" for k, v in sorted(sel.items(), key=lambda x: -x[1]))
            ad = [not r["ad_adequate"] for r in ok if r["ad_adequate"] is not None]
            own = [r["selected"] == FAMILY[r["truth"]] for r in ok]
            err = [100 * (r["mrt"][0] / r["truth_mrt"] - 1) for r in ok]
            cpu = [r["cpu_seconds"] for r in ok]
            lines.append(
                f"| {label} | {noise} | {len(ok)}"
                f"{f' (+{len(sub) - len(ok)} refused)' if len(sub) > len(ok) else ''} | "
                f"{_pct_sd([r['covered'] for r in ok])} | "
                f"{100 * np.mean([r['selected_covered'] for r in ok]):.1f} | "
                f"{100 * np.mean([bool(r['averaged']) for r in ok]):.0f} | "
                f"{sum(not r['selected_mrt_in_record'] for r in ok)} | "
                f"{100 * np.mean(own):.0f} | {top if label != 'pooled' else '-'} | "
                f"{100 * np.mean(ad):.0f} | {np.median(err):+.1f} | {np.median(cpu):.0f} |"
                if ok
                else f"| {label} | {noise} | 0 (+{len(sub)} refused) | - | - | - | - | - | - | "
                "- | - | - |"
            )
    errors = [r for r in rows if "error" in r]
    tail = [f"\nprofiles refused: {len(errors)}"] + [
        f"  {r['truth']} {r['noise']} {r['i']}: {r['error'][:200]}" for r in errors[:5]
    ]
    return "\n".join(lines + tail)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profiles", type=int, default=50, help="profiles per truth and noise")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("out/rtd_model_choice"))
    ap.add_argument("--truths", nargs="+", default=list(TRUTHS), choices=TRUTHS)
    ap.add_argument("--table-only", action="store_true", help="print the table of the rows there")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "model_choice.jsonl"
    if args.table_only:
        rows = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
        print(table(rows))
        return
    print(describe())
    for name in args.truths:  # the PDE truths once, inherited by the workers
        truth(name)
    # profile index outermost: a campaign stopped early is balanced across truths and noises
    jobs = [(name, n, i) for i in range(args.profiles) for name in args.truths for n in NOISE]
    print(table(_run(path, jobs, args.jobs)))


if __name__ == "__main__":
    main()
