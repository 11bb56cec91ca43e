"""Reproduction of the seed's chapter 6 analyses on the synthetic campaign.

Every table function returns pandas DataFrames; ``twin_core.quality.reproduce.reproduce_chapter6``
runs them with the quality analyses on a seeded campaign (``twin rtd reproduce``).

- :func:`denoise_table` - Table 6.1: the seed's metrics per denoising method, averaged over
  the three repeats of each tracer amount, with errors against the known truth;
- :func:`truncation_table` - Table 6.2 (+ the PAT row of Table 6.3): AD fits of the 10 g runs
  truncated at 0-10 % of the peak, ANOVA and Tukey letters, next to noise-free fits of the
  truncated truth;
- :func:`noise_table` - 6.1.3.2: noise components estimated from the residual to an AD fit.

The analyses that go on to quality decisions (funnels, OOS increase, lot boundaries: Fig. 6.16,
6.17, 6.1.4.3.1) build on these and live in ``twin_core.quality.reproduce``.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import pandas as pd

from twin_core.rtd import denoise as D
from twin_core.rtd.fitting import fit
from twin_core.rtd.metrics import denoise_metrics, truth_metrics
from twin_core.rtd.noise import characterize
from twin_core.rtd.outliers import hampel
from twin_core.rtd.profiles import e_curve
from twin_core.rtd.stats import compare_groups
from twin_core.rtd.synthetic import SyntheticRun
from twin_core.rtd.truncation import (
    SEED_PAT_BASELINE_S,
    pat_level,
    truncate_level,
    truncate_relative,
)

__all__ = [
    "SEED_METHODS",
    "REL_LEVELS",
    "clean",
    "apply_method",
    "denoise_table",
    "truncation_table",
    "noise_table",
]

#: the seed's four methods with its settings, plus our automatic choices
SEED_METHODS: dict[str, dict] = {
    "SA": {"method": "sa", "window": 5},
    "WT": {"method": "wavelet"},
    "SV": {"method": "sg", "window": 11, "order": 3},
    "FFT": {"method": "fft"},
    "SA-centred-auto": {"method": "auto_sa"},
    "SV-auto": {"method": "auto_sg"},
    "FFT-auto": {"method": "auto_fft"},
    "WT-SURE-auto": {"method": "auto_wavelet"},
}
REL_LEVELS = (0.0, 0.0125, 0.025, 0.0375, 0.05, 0.075, 0.1)


def clean(run: SyntheticRun) -> np.ndarray:
    """Outlier removal (Hampel) of a run's measured profile."""
    return hampel(run.c, t=run.t).y


def apply_method(y: np.ndarray, spec: dict) -> np.ndarray:
    """Denoise y with one entry of :data:`SEED_METHODS`."""
    m = spec["method"]
    if m.startswith("auto_"):
        fn = {
            "auto_sa": D.auto_sliding_average,
            "auto_sg": D.auto_savitzky_golay,
            "auto_fft": D.auto_fft,
            "auto_wavelet": D.auto_wavelet,
        }[m]
        return fn(y).y
    return D.denoise(y, m, **{k: v for k, v in spec.items() if k != "method"}).y


def denoise_table(runs: Iterable[SyntheticRun]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per-run metrics (long) and the Table 6.1-like summary (mean over repeats per amount).

    Metrics are computed against the outlier-cleaned measured profile (the seed's "original");
    truth columns against the noise-free measured signal c_true + baseline offset.
    """
    rows = []
    for run in runs:
        y = clean(run)
        truth = run.c_true + run.baseline_offset
        variants = {"Original": y} | {k: apply_method(y, v) for k, v in SEED_METHODS.items()}
        for name, yh in variants.items():
            m = denoise_metrics(run.t, y, yh)
            m.update(truth_metrics(run.t, yh, truth))
            rows.append({"run": run.name, "amount_g": run.amount_g, "method": name, **m})
    long = pd.DataFrame(rows)
    metrics = [c for c in long.columns if c not in ("run", "amount_g", "method")]
    summary = (
        long.groupby(["amount_g", "method"], sort=False)[metrics]
        .mean()
        .reset_index()
        .sort_values(["amount_g", "method"], ascending=[False, True])
    )
    return long, summary


def _fit_params(t: np.ndarray, y: np.ndarray) -> dict[str, float]:
    r = fit(t, e_curve(t, y), "ad_open", scale="fixed")
    return r.params


def truncation_table(
    runs: Iterable[SyntheticRun], levels: tuple[float, ...] = REL_LEVELS, pat_k: float = 3.0
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per-run AD fits of WT-denoised profiles truncated at `levels` of the peak (and the PAT
    level mu + k sigma of t >= 120 s), plus the summary with ANOVA and Tukey letters.

    Each run also gets the fit of its truncated noise-free profile ("truth" columns): the
    part of the parameter shift due to truncation alone.
    """
    rows = []
    for run in runs:
        y = D.denoise(clean(run), "wavelet").y
        truth = run.c_true
        lvl_pat, mu, sd = pat_level(run.t, clean(run), pat_k, SEED_PAT_BASELINE_S)
        cases = [
            (f"{lv:g}", truncate_relative(y, lv), truncate_relative(truth, lv)) for lv in levels
        ]
        cases.append(
            (
                "PAT",
                truncate_level(y, max(lvl_pat, 0.0)),
                truncate_level(truth, max(lvl_pat, 0.0)),
            )
        )
        for label, yt, tt in cases:
            p = _fit_params(run.t, yt)
            q = _fit_params(run.t, tt)
            rows.append(
                {
                    "run": run.name,
                    "level": label,
                    **p,
                    **{f"{k}_truthfit": v for k, v in q.items()},
                    **{f"{k}_true": v for k, v in run.params.items()},
                    "pat_level": lvl_pat,
                    "pat_level_rel": lvl_pat / float(np.max(y)),
                    "baseline_mu": mu,
                    "baseline_sigma": sd,
                }
            )
    long = pd.DataFrame(rows)
    out = []
    labels = [f"{lv:g}" for lv in levels]
    letters = {}
    for par in ("tau_d", "tau", "pe"):
        groups = {lb: long.loc[long.level == lb, par].to_numpy() for lb in labels}
        cmp = compare_groups(groups)
        letters[par] = dict(zip(labels, cmp.letters))
        letters[par + "_p"] = cmp.p_anova
    for lb in labels + ["PAT"]:
        sub = long[long.level == lb]
        row = {"level": lb, "n": len(sub)}
        for par in ("tau_d", "tau", "pe"):
            row[f"{par}_mean"] = sub[par].mean()
            row[f"{par}_std"] = sub[par].std(ddof=1)
            row[f"{par}_group"] = letters[par].get(lb, "")
            row[f"{par}_truthfit_mean"] = sub[f"{par}_truthfit"].mean()
            row[f"{par}_true_mean"] = sub[f"{par}_true"].mean()
            row[f"{par}_error_mean"] = (sub[par] - sub[f"{par}_true"]).mean()
        if lb == "PAT":
            row["pat_level_rel_mean"] = sub["pat_level_rel"].mean()
        out.append(row)
    summary = pd.DataFrame(out)
    summary.attrs["anova_p"] = {p: letters[p + "_p"] for p in ("tau_d", "tau", "pe")}
    return long, summary


def noise_table(runs: Iterable[SyntheticRun]) -> pd.DataFrame:
    """Noise components from the residual to an AD fit (free scale) of each cleaned run."""
    rows = []
    for run in runs:
        y = clean(run)
        r = fit(run.t, y, "ad_open", scale="free")
        rep = characterize(run.t, y, r.fitted)
        rows.append(
            {"run": run.name, **rep.as_dict(), **{f"{k}_true": v for k, v in run.noise.items()}}
        )
    return pd.DataFrame(rows)
