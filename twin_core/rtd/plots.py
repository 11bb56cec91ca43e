"""Figures of the RTD analyses (matplotlib ``Figure`` objects; the caller saves them): a processed
tracer profile with its fits, funnel plots and their difference, and the figures of the seed's
chapter 6 reproduction (Fig. 6.10 / Table 6.1, Tables 6.2-6.3, Fig. 6.16, Fig. 6.17). No pyplot
state is used."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

__all__ = [
    "plot_denoising",
    "plot_funnel_cases",
    "plot_funnel_difference",
    "plot_funnels",
    "plot_oos_curve",
    "plot_profile",
    "plot_truncation",
]


def plot_profile(
    t: np.ndarray,
    measured: np.ndarray,
    processed: np.ndarray,
    e: np.ndarray,
    conc_unit: str,
    outliers: Sequence[int] = (),
    fits: Sequence[Any] = (),
) -> Figure:
    """Measured and processed profile (outliers marked), the processed E(t) and up to three
    fitted models (``twin_core.rtd.fitting`` results, with their AIC)."""
    fig = Figure(figsize=(8, 7), layout="tight")
    ax = fig.subplots(2, 1, sharex=True)
    ax[0].plot(t, measured, ".", ms=3, color="0.6", label="measured")
    if len(outliers):
        idx = np.asarray(outliers)
        ax[0].plot(t[idx], measured[idx], "rx", label="outliers")
    ax[0].plot(t, processed, "C0", lw=1.5, label="processed")
    ax[0].set_ylabel(f"C ({conc_unit})")
    ax[0].legend()
    ax[1].plot(t, e, "C0", label="E(t) processed")
    for f in list(fits)[:3]:
        ax[1].plot(t, f.fitted, "--", label=f"{f.model} (AIC {f.aic:.0f})")
    ax[1].set_xlabel("t (s)")
    ax[1].set_ylabel("E (1/s)")
    ax[1].legend()
    return fig


def plot_funnels(funnels: Mapping[str, Any], title: str) -> Figure:
    """Funnel plot (max % deviation over duration x intensity, one funnel) or the feasible-region
    boundaries of several (``twin_core.quality.funnel.FunnelResult``)."""
    fig = Figure(figsize=(6.5, 5), layout="tight")
    ax = fig.subplots()
    first = next(iter(funnels.values()))
    if len(funnels) == 1:
        cs = ax.contourf(
            first.durations, first.intensities, first.max_dev.T, levels=20, cmap="viridis"
        )
        fig.colorbar(cs, ax=ax, label="max deviation (%)")
    for i, (label, f) in enumerate(funnels.items()):
        ax.plot(
            f.durations,
            np.clip(f.h_crit, 0, f.intensities.max()),
            color=f"C{i + 1}",
            lw=2,
            label=f"{label}",
        )
    ax.set_xlabel("disturbance duration (s)")
    ax.set_ylabel("disturbance intensity (% of nominal)")
    ax.set_ylim(first.intensities.min(), first.intensities.max())
    ax.set_title(title)
    ax.legend(title=f"limit {first.limit:g} %", fontsize=8)
    return fig


def plot_funnel_difference(a: Any, b: Any) -> Figure:
    """Max deviation of the second funnel minus the first, on their common grid."""
    fig = Figure(figsize=(6.5, 5), layout="tight")
    ax = fig.subplots()
    diff = (b.max_dev - a.max_dev).T
    lim = float(np.max(np.abs(diff))) or 1.0
    cs = ax.pcolormesh(a.durations, a.intensities, diff, cmap="RdBu_r", vmin=-lim, vmax=lim)
    fig.colorbar(cs, ax=ax, label="max deviation, second - first (%)")
    ax.set_xlabel("disturbance duration (s)")
    ax.set_ylabel("disturbance intensity (% of nominal)")
    ax.set_title("funnel difference")
    return fig


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
