"""Reproduction of the seed's chapter 6 quality analyses on the synthetic campaign.

Built on ``twin_core.rtd.reproduce`` (outlier cleaning, the seed's denoising and truncation,
the RTD tables 6.1-6.3); every table function returns pandas DataFrames / dicts, and
:func:`reproduce_chapter6` runs all of them on a seeded campaign and writes the CSV tables,
figures and a summary to the directory it is given (``twin rtd reproduce``).

- :func:`funnel_cases` - Fig. 6.16 A-D: funnel overlays for tail, time and level truncation;
- :func:`funnel_summary` - feasible area of each funnel against its case's first;
- :func:`oos_curve` - Fig. 6.17: % increase of OOS tablets vs relative truncation level;
- :func:`lot_table` - 6.1.4.3.1: lot boundaries of original, denoised and true profiles;
- :func:`interval_table` - the raw-data AD fit of every run with its intervals against the
  run's truth, and the truncated fits of Table 6.2 against those intervals.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from twin_core.quality.funnel import FunnelResult, compare_funnels, funnel, oos_increase_curve
from twin_core.quality.lots import lot_boundaries
from twin_core.rtd import denoise as D
from twin_core.rtd.profiles import e_curve
from twin_core.rtd.reproduce import REL_LEVELS, clean
from twin_core.rtd.synthetic import SyntheticRun
from twin_core.rtd.truncation import (
    baseline_correct,
    truncate_level,
    truncate_pat,
    truncate_time,
    two_peak_profiles,
)

__all__ = [
    "DURATIONS",
    "INTENSITIES",
    "funnel_cases",
    "funnel_summary",
    "oos_curve",
    "lot_table",
    "interval_table",
    "reproduce_chapter6",
]

#: funnel grid of the seed's Fig. 6.16: disturbance durations (s) and intensities (% of nominal)
DURATIONS = np.linspace(0.0, 60.0, 200)
INTENSITIES = np.linspace(0.0, 50.0, 200)


def _funnel(t: np.ndarray, y: np.ndarray) -> FunnelResult:
    return funnel(t, e_curve(t, y), DURATIONS, INTENSITIES)


def funnel_cases(run: SyntheticRun) -> dict[str, dict[str, FunnelResult]]:
    """Fig. 6.16: funnels for (A) two tails, (B) time truncation at 50 s, (C) low and (D) high
    absolute truncation levels (% w/w), on the WT-denoised run; plus the true profile."""
    t = run.t
    y = D.denoise(clean(run), "wavelet").y
    c1, c2 = two_peak_profiles(t)
    out: dict[str, dict[str, FunnelResult]] = {
        "A_tails": {"C1": _funnel(t, c1), "C2": _funnel(t, c2)},
        "B_time": {
            "original": _funnel(t, y),
            "truncated 50 s": _funnel(t, truncate_time(t, y, 50.0)),
        },
        "C_low_levels": {
            f"{lv:g} % w/w": _funnel(t, truncate_level(y, lv)) for lv in (0.125, 0.25, 0.375, 0.5)
        },
        "D_high_levels": {
            f"{lv:g} % w/w": _funnel(t, truncate_level(y, lv)) for lv in (0.5, 1.0, 1.5, 2.0)
        },
        "truth": {
            "true": _funnel(t, run.c_true),
            "denoised": _funnel(t, y),
            "raw": _funnel(t, clean(run)),
        },
    }
    return out


def funnel_summary(cases: dict[str, dict[str, FunnelResult]]) -> pd.DataFrame:
    """Feasible area of each funnel and its change against the case's first funnel."""
    rows = []
    for case, fs in cases.items():
        ref = next(iter(fs.values()))
        for label, f in fs.items():
            c = compare_funnels(ref, f)
            rows.append(
                {
                    "case": case,
                    "label": label,
                    "feasible_area": f.feasible_area,
                    "feasible_fraction": f.feasible_fraction,
                    "oos_increase_pct_vs_first": c["oos_increase_pct"],
                    "feasible_iou_vs_first": c["feasible_iou"],
                    "max_abs_dev_diff_vs_first": c["max_abs_deviation_difference"],
                }
            )
    return pd.DataFrame(rows)


def oos_curve(
    runs: Iterable[SyntheticRun], levels: tuple[float, ...] = REL_LEVELS[1:]
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Fig. 6.17: truncate at a fraction of the peak -> WT-denoise -> funnel -> % increase of
    OOS tablets against the untruncated denoised profile. Three variants: the seed's workflow
    on the measured profile, the same after baseline-offset correction, and the noise-free
    truth."""
    rows = []
    wt = lambda v: D.denoise(v, "wavelet").y  # noqa: E731 - the seed smooths with WT
    kw = {"durations": DURATIONS, "intensities": INTENSITIES}
    for run in runs:
        y = clean(run)
        a = oos_increase_curve(run.t, y, levels, wt, **kw)
        b = oos_increase_curve(run.t, baseline_correct(run.t, y), levels, wt, **kw)
        c = oos_increase_curve(run.t, run.c_true, levels, None, **kw)
        for i, lv in enumerate(levels):
            rows.append(
                {
                    "run": run.name,
                    "level": lv,
                    "oos_increase_pct": a[i],
                    "oos_increase_pct_baseline_corrected": b[i],
                    "oos_increase_pct_truth": c[i],
                }
            )
    long = pd.DataFrame(rows)
    cols = ["oos_increase_pct", "oos_increase_pct_baseline_corrected", "oos_increase_pct_truth"]
    summary = long.groupby("level")[cols].agg(["mean", "std"])
    summary.columns = ["_".join(c) for c in summary.columns]
    return long, summary.reset_index()


def lot_table(runs: Iterable[SyntheticRun]) -> pd.DataFrame:
    """0.5 % / 99.5 % lot boundaries of raw (cleaned), WT-denoised, WT-denoised and PAT-truncated
    (mu + 3 sigma) and true profiles (negative values clipped to 0 for F to be monotone)."""
    rows = []
    for run in runs:
        y = clean(run)
        yd = D.denoise(y, "wavelet").y
        row = {"run": run.name}
        variants = (
            ("raw", np.clip(y, 0, None)),
            ("denoised", np.clip(yd, 0, None)),
            ("denoised_pat", truncate_pat(run.t, yd)),
            ("true", run.c_true),
        )
        for name, c in variants:
            lo, hi = lot_boundaries(run.t, c)
            row[f"t_lo_{name}"], row[f"t_hi_{name}"] = lo, hi
        rows.append(row)
    return pd.DataFrame(rows)


def interval_table(runs: Iterable[SyntheticRun], truncation: pd.DataFrame) -> pd.DataFrame:
    """Chapter 6 with the raw-data intervals: per run, the AD fit of the raw profile
    (``rtd.pipeline.fit_profile``: GLS with white + 1/f + proportional noise) with its 95 %
    intervals, whether they cover the run's true parameters, mean residence time and lot
    boundaries, its lack-of-fit p-value, and, for the runs in ``truncation`` (the output of
    :func:`truncation_table`), whether the fit of the 5 %, 10 % and PAT-truncated profile lies
    outside the raw-data interval (truncation moved the estimate by more than its
    uncertainty)."""
    from twin_core.quality.analysis import lot_estimates
    from twin_core.rtd.models import axial_dispersion_open
    from twin_core.rtd.pipeline import fit_profile
    from twin_core.rtd.profiles import from_arrays

    rows = []
    for run in runs:
        s = fit_profile(from_arrays(run.t, run.c, name=run.name), "ad_open")
        f = s.fit
        ci = f.ci
        p = run.params
        grid = np.linspace(0.0, 4000.0, 80001)
        e = axial_dispersion_open(grid, p["tau_d"], p["tau"], p["pe"])
        true_lots = lot_boundaries(grid, e)
        lots = lot_estimates(s)
        mrt = s.moments["mean_residence_time_s"]
        true_mrt = p["tau_d"] + p["tau"] * (1 + 2 / p["pe"])
        row = {"run": run.name, "adequate": f.adequate, "lack_of_fit_p": f.lack_of_fit.p_value}
        for k in ("tau_d", "tau", "pe"):
            row |= {
                k: f.params[k],
                f"{k}_lo": ci[k][0],
                f"{k}_hi": ci[k][1],
                f"{k}_true": p[k],
                f"{k}_covered": bool(ci[k][0] <= p[k] <= ci[k][1]),
            }
        row |= {
            "mrt": mrt.value,
            "mrt_lo": mrt.ci[0],
            "mrt_hi": mrt.ci[1],
            "mrt_true": true_mrt,
            "mrt_covered": bool(mrt.ci[0] <= true_mrt <= mrt.ci[1]),
        }
        for k, true in zip(("t_lo_s", "t_hi_s"), true_lots):
            est = lots[k]
            row |= {
                k: est.value,
                f"{k}_lo": est.ci[0],
                f"{k}_hi": est.ci[1],
                f"{k}_true": true,
                f"{k}_covered": bool(est.ci[0] <= true <= est.ci[1]),
            }
        trunc = truncation[truncation.run == run.name]
        for level in ("0.05", "0.1", "PAT"):
            sub = trunc[trunc.level == level]
            if sub.empty:
                continue
            for k in ("tau_d", "tau", "pe"):
                v = float(sub[k].iloc[0])
                row[f"{k}_trunc_{level}_outside_ci"] = bool(not ci[k][0] <= v <= ci[k][1])
        rows.append(row)
    return pd.DataFrame(rows)


def _write_result(
    out: Path, name: str, runs: pd.DataFrame, summary: pd.DataFrame, fig: Any
) -> None:
    """One result of the reproduction: per-run rows ``<name>_runs.csv``, the summary
    ``<name>.csv`` and its figure ``<name>.png``."""
    runs.to_csv(out / f"{name}_runs.csv", index=False)
    summary.to_csv(out / f"{name}.csv", index=False)
    fig.savefig(out / f"{name}.png", dpi=120)


def reproduce_chapter6(
    out_dir: str | Path, seed: int = 0, repeats: int = 3, progress: bool = False
) -> dict[str, object]:
    """The seed's chapter 6 on a synthetic campaign (``twin_core.rtd.synthetic``, ``repeats``
    runs per tracer amount, seeded), written to ``out_dir``: the RTD tables of
    ``twin_core.rtd.reproduce`` and the quality analyses above as CSV, their figures
    (``twin_core.rtd.plots``) and ``reproduce.json`` (runs, ANOVA p-values, files); returns that
    summary."""
    import json

    from tqdm import tqdm

    from twin_core.quality.analysis import json_default
    from twin_core.rtd import plots
    from twin_core.rtd.reproduce import (
        SEED_METHODS,
        apply_method,
        denoise_table,
        noise_table,
        truncation_table,
    )
    from twin_core.rtd.synthetic import CampaignConfig, generate_campaign

    if repeats < 2:
        raise ValueError(f"repeats must be >= 2, got {repeats}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    runs = generate_campaign(seed, CampaignConfig(repeats=repeats))
    ten = [r for r in runs if r.amount_g == 10.0]  # the seed's truncation runs
    steps = tqdm(total=6, desc="reproduce", disable=not progress)

    long, summ = denoise_table(runs)
    y = clean(runs[0])
    shown = {name: apply_method(y, SEED_METHODS[name]) for name in ("SA", "WT", "SV", "FFT")}
    _write_result(out, "table_6_1", long, summ, plots.plot_denoising(runs[0], y, shown, summ))
    steps.update()

    l2, s2 = truncation_table(ten)
    _write_result(out, "table_6_2", l2, s2, plots.plot_truncation(s2))
    steps.update()

    cases = funnel_cases(ten[0])
    funnel_summary(cases).to_csv(out / "fig_6_16_funnels.csv", index=False)
    rows: dict[str, object] = {"duration_s": DURATIONS}
    for case, fs in cases.items():
        for label, f in fs.items():
            rows[f"{case}:{label}"] = f.h_crit
    pd.DataFrame(rows).to_csv(out / "fig_6_16_boundaries.csv", index=False)
    plots.plot_funnel_cases(cases).savefig(out / "fig_6_16.png", dpi=120)
    steps.update()

    l3, s3 = oos_curve(ten)
    _write_result(out, "fig_6_17", l3, s3, plots.plot_oos_curve(s3))
    steps.update()

    lot_table(runs).to_csv(out / "lots.csv", index=False)
    noise_table(runs).to_csv(out / "noise.csv", index=False)
    steps.update()

    intervals = interval_table(runs, l2)
    intervals.to_csv(out / "intervals.csv", index=False)
    plots.plot_intervals(intervals).savefig(out / "intervals.png", dpi=120)
    steps.update()
    steps.close()
    meta = {
        "seed": seed,
        "runs": [r.name for r in runs],
        "anova_p": s2.attrs.get("anova_p", {}),
        "interval_coverage": {
            k: float(intervals[f"{k}_covered"].mean())
            for k in ("tau_d", "tau", "pe", "mrt", "t_lo_s", "t_hi_s")
        },
        "files": sorted(p.name for p in out.iterdir()),
    }
    (out / "reproduce.json").write_text(json.dumps(meta, indent=2, default=json_default))
    return meta
