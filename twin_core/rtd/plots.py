"""Figures of the RTD analyses (matplotlib ``Figure`` objects; the caller saves them): a measured
tracer profile with its preprocessing, the model fitted to the raw profile and its lack-of-fit
verdict, and the figures of the seed's chapter 6 reproduction (Fig. 6.10 / Table 6.1, Tables
6.2-6.3, Fig. 6.16, Fig. 6.17, the raw-data intervals of every run). No pyplot state is used."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from twin_core.rtd.pipeline import FitSummary, Processed

__all__ = [
    "plot_denoising",
    "plot_funnel_cases",
    "plot_intervals",
    "plot_oos_curve",
    "plot_profile",
    "plot_truncation",
]


def plot_denoising(
    run: Any, cleaned: np.ndarray, denoised: Mapping[str, np.ndarray], summary: pd.DataFrame
) -> Figure:
    """Fig. 6.10: one run, its truth and the seed's denoising methods (first 100 s); Table 6.1:
    RMSE to the truth by method and tracer amount."""
    fig = Figure(figsize=(12, 4.5), layout="tight")
    axs = fig.subplots(1, 2)
    axs[0].plot(run.t, run.c, ".", color="0.7", ms=3, label="measured")
    axs[0].plot(run.t, run.c_true + run.baseline_offset, "k", lw=1, label="truth")
    for name, y in denoised.items():
        axs[0].plot(run.t, y, lw=1, label=name)
    axs[0].set_xlim(0, 100)
    axs[0].set_xlabel("t (s)")
    axs[0].set_ylabel("C (% w/w)")
    axs[0].legend()
    axs[0].set_title(f"run {run.name} (Fig. 6.10)")
    piv = summary.pivot(index="method", columns="amount_g", values="rmse_truth")
    piv.plot.bar(ax=axs[1])
    axs[1].set_ylabel("RMSE to truth (% w/w)")
    axs[1].set_title("denoising error against the known truth")
    return fig


def plot_truncation(summary: pd.DataFrame) -> Figure:
    """Tables 6.2-6.3: the AD parameters of noisy fits (mean +- sd, Tukey groups) and of the
    truncated truth, by truncation level, against the true values."""
    fig = Figure(figsize=(13, 4), layout="tight")
    axs = fig.subplots(1, 3)
    sub = summary[summary.level != "PAT"]
    x = sub.level.astype(float) * 100
    for ax, par in zip(axs, ("tau_d", "tau", "pe")):
        ax.errorbar(
            x, sub[f"{par}_mean"], yerr=sub[f"{par}_std"], fmt="o-", label="noisy fits (n=3)"
        )
        ax.plot(x, sub[f"{par}_truthfit_mean"], "s--", label="fit of truncated truth")
        ax.axhline(sub[f"{par}_true_mean"].iloc[0], color="k", lw=0.8, label="true")
        for xi, yi, g in zip(x, sub[f"{par}_mean"], sub[f"{par}_group"]):
            ax.annotate(g, (xi, yi), textcoords="offset points", xytext=(4, 6), fontsize=8)
        ax.set_xlabel("truncation level (% of peak)")
        ax.set_title(par)
    axs[0].legend(fontsize=8)
    return fig


def plot_funnel_cases(cases: Mapping[str, Mapping[str, Any]]) -> Figure:
    """Fig. 6.16 A-D: feasible-region boundaries of the truncation cases."""
    fig = Figure(figsize=(11, 9), layout="tight")
    axs = fig.subplots(2, 2)
    for ax, (case, fs) in zip(axs.ravel(), list(cases.items())[:4]):
        for i, (label, f) in enumerate(fs.items()):
            ax.plot(
                f.durations, np.clip(f.h_crit, 0, f.intensities.max()), color=f"C{i}", label=label
            )
        ax.set_title(case.replace("_", " "))
        ax.set_xlabel("duration (s)")
        ax.set_ylabel("intensity (% of nominal)")
        ax.legend(fontsize=8, title="feasible below the line")
    return fig


def plot_oos_curve(summary: pd.DataFrame) -> Figure:
    """Fig. 6.17: % increase of OOS tablets against the relative truncation level (seed
    workflow, baseline-corrected, noise-free truth)."""
    fig = Figure(figsize=(6.5, 4.5), layout="tight")
    ax = fig.subplots()
    for col, lab in (
        ("oos_increase_pct", "seed workflow (measured)"),
        ("oos_increase_pct_baseline_corrected", "baseline-corrected"),
        ("oos_increase_pct_truth", "noise-free truth"),
    ):
        ax.errorbar(
            summary.level * 100,
            summary[f"{col}_mean"],
            yerr=summary[f"{col}_std"],
            fmt="o-",
            label=lab,
        )
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("truncation level (% of peak height)")
    ax.set_ylabel("increase of OOS tablets (percentage points)")
    ax.legend()
    return fig


def _noise_sd(summary: FitSummary) -> np.ndarray:
    """Pointwise sd of the estimated noise: sqrt(s_w^2 + s_p^2 + k^2 s^2), s = fitted - baseline."""
    f = summary.fit
    n = f.noise
    signal = f.fitted - f.params.get("baseline", 0.0)
    return np.sqrt(n.white_var + n.pink_var + n.prop_var * signal**2)


def plot_profile(processed: Processed, summary: FitSummary | None, warnings: list[str]) -> Figure:
    """Top: the measured profile, Hampel outliers, the processed profile and the model fitted
    to the raw profile (with its baseline); samples the fit left out are circled. Bottom: the
    residual of the fit with +/- 2 sd of the estimated noise and the lack-of-fit verdict. A
    warning (an inadequate fit) is written in red on the figure."""
    fig = Figure(figsize=(8, 7))
    ax = fig.subplots(2, 1, sharex=True, height_ratios=(3, 2))
    t, raw = processed.t, processed.profile.c
    ax[0].plot(t, raw, ".", ms=3, color="0.6", label="measured")
    if processed.outliers is not None and processed.outliers.count:
        idx = processed.outliers.indices
        ax[0].plot(t[idx], raw[idx], "rx", label="Hampel outliers")
    ax[0].plot(t, processed.y + processed.baseline, "C0", lw=1.2, label="processed (+ baseline)")
    if summary is not None:
        f = summary.fit
        verdict = "adequate" if f.adequate else "INADEQUATE"
        ax[0].plot(t, f.fitted, "C3--", lw=1.5, label=f"{f.model} fit ({verdict})")
        if f.excluded.size:
            ax[0].plot(
                t[f.excluded], raw[f.excluded], "o", mfc="none", mec="C3", label="left out of fit"
            )
        keep = np.ones(t.size, bool)
        keep[f.excluded] = False
        sd = _noise_sd(summary)
        ax[1].plot(t[keep], (raw - f.fitted)[keep], ".", ms=3, color="C3")
        ax[1].fill_between(t, -2 * sd, 2 * sd, color="0.85", label="+/- 2 sd of the noise")
        ax[1].axhline(0, color="k", lw=0.6)
        tests = ", ".join(f"{x.name} p={x.p_value:.2g}" for x in f.lack_of_fit.tests)
        ax[1].set_title(
            f"lack of fit: {verdict} (p = {f.lack_of_fit.p_value:.2g}; {tests})",
            fontsize=9,
            color="k" if f.adequate else "red",
        )
        ax[1].legend(fontsize=8)
    ax[0].set_ylabel(f"C ({processed.profile.conc_unit})")
    ax[0].legend(fontsize=8)
    ax[1].set_xlabel("t (s)")
    ax[1].set_ylabel("residual")
    for i, w in enumerate(warnings[:3]):
        fig.text(0.01, 0.995 - 0.025 * i, "WARNING: " + w[:150], color="red", fontsize=7, va="top")
    fig.tight_layout(rect=(0, 0, 1, 0.97 if warnings else 1))
    return fig


def plot_intervals(table: pd.DataFrame) -> Figure:
    """Raw-data 95 % intervals of each run (``quality.reproduce.interval_table``) against its
    truth: AD parameters, mean residence time and the upper lot boundary."""
    keys = ("tau_d", "tau", "pe", "mrt", "t_hi_s")
    fig = Figure(figsize=(15, 4), layout="tight")
    axs = fig.subplots(1, len(keys))
    y = np.arange(len(table))
    for ax, k in zip(axs, keys):
        v = table[k].to_numpy()
        err = [v - table[f"{k}_lo"].to_numpy(), table[f"{k}_hi"].to_numpy() - v]
        ax.errorbar(v, y, xerr=err, fmt="o", ms=3, label="estimate, 95 % CI")
        ax.plot(table[f"{k}_true"], y, "kx", label="truth")
        ax.set_title(k)
        ax.set_yticks(y, table.run, fontsize=7)
    axs[0].legend(fontsize=7)
    return fig
