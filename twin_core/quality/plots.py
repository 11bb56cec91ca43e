"""Figures of the quality analyses (matplotlib ``Figure`` objects; the caller saves them): funnel
plots with the fitted model's band, the difference of two funnels, lot boundaries on F(t). No
pyplot state is used."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from twin_core.quality.analysis import FunnelAnalysis, LotsAnalysis, RepeatsAnalysis

__all__ = ["plot_funnel", "plot_funnel_difference", "plot_lots", "plot_repeats"]


def _warn(fig: Figure, warnings: list[str]) -> None:
    if warnings:
        fig.text(0.01, 0.005, "WARNING: " + warnings[0][:140], color="red", fontsize=7, va="bottom")


def plot_funnel(result: FunnelAnalysis) -> Figure:
    """Feasible boundaries h_crit(d) of each profile (and the fitted model's interval band);
    with one profile the max-deviation contours underneath."""
    fig = Figure(figsize=(6.5, 5))
    ax = fig.subplots()
    first = result.funnels[0]
    top = first.intensities.max()
    if len(result.funnels) == 1:
        cs = ax.contourf(
            first.durations, first.intensities, first.max_dev.T, levels=20, cmap="viridis"
        )
        fig.colorbar(cs, ax=ax, label="max deviation (%)")
    for i, (label, f, band) in enumerate(zip(result.labels, result.funnels, result.bands)):
        ax.plot(f.durations, np.clip(f.h_crit, 0, top), color=f"C{i + 1}", lw=2, label=label)
        if band is not None:
            ax.fill_between(
                band.durations,
                np.clip(band.lower, 0, top),
                np.clip(band.upper, 0, top),
                color=f"C{i + 1}",
                alpha=0.3,
                label=f"{label}: model, 95 % band",
            )
    ax.set_xlabel("disturbance duration (s)")
    ax.set_ylabel("disturbance intensity (% of nominal)")
    ax.set_ylim(first.intensities.min(), top)
    ax.set_title("funnel plot" if len(result.funnels) == 1 else "funnel overlay")
    ax.legend(title=f"limit {first.limit:g} %", fontsize=8)
    _warn(fig, result.warnings)
    fig.tight_layout()
    return fig


def plot_funnel_difference(result: FunnelAnalysis) -> Figure:
    """Max deviation of the second funnel minus the first."""
    a, b = result.funnels
    fig = Figure(figsize=(6.5, 5))
    ax = fig.subplots()
    diff = (b.max_dev - a.max_dev).T
    lim = float(np.max(np.abs(diff))) or 1.0
    cs = ax.pcolormesh(a.durations, a.intensities, diff, cmap="RdBu_r", vmin=-lim, vmax=lim)
    fig.colorbar(cs, ax=ax, label="max deviation, second - first (%)")
    ax.set_xlabel("disturbance duration (s)")
    ax.set_ylabel("disturbance intensity (% of nominal)")
    ax.set_title("funnel difference")
    fig.tight_layout()
    return fig


def plot_lots(result: LotsAnalysis) -> Figure:
    """F(t) of the processed profile (and of the fitted model) with the lot boundaries and
    their intervals."""
    a = result.analysis
    curves = result.curves()
    fig = Figure(figsize=(7, 4.5))
    ax = fig.subplots()
    ax.plot(curves["t_s"], curves["F_processed"], "C0", label="processed profile")
    for v in a.lots_empirical:
        ax.axvline(v, color="C0", ls=":", lw=1)
    if a.lots_model is not None:
        ax.plot(curves["t_s"], curves["F_model"], "C1--", label=f"model {a.summary.fit.model}")
        for k in ("t_lo_s", "t_hi_s"):
            est = a.lots_model[k]
            ax.axvspan(*est.ci, color="C1", alpha=0.25)
            ax.axvline(est.value, color="C1", lw=1)
    ax.axhline(result.lower, color="0.6", lw=0.6)
    ax.axhline(result.upper, color="0.6", lw=0.6)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("F(t)")
    ax.set_title(f"lot boundaries ({result.lower:.1%} / {result.upper:.1%} of F)")
    ax.legend(fontsize=8)
    _warn(fig, a.warnings)
    fig.tight_layout()
    return fig


def plot_repeats(result: RepeatsAnalysis) -> Figure:
    """Repeat pulses: each processed profile with its fit, and the mean residence time of each
    repeat with its interval beside the pooled one (a forest plot), with the joint verdict."""
    fig = Figure(figsize=(10, 4.5))
    ax, fx = fig.subplots(1, 2, gridspec_kw={"width_ratios": [3, 2]})
    for i, a in enumerate(result.repeats):
        p = a.processed
        ax.plot(p.t, p.y, color=f"C{i}", lw=0.8, alpha=0.6, label=p.profile.name)
        if a.summary is not None:
            ax.plot(p.t, a.summary.fit.fitted, color=f"C{i}", lw=1.5, ls="--")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("concentration (% w/w), processed; dashed: fit")
    ax.legend(fontsize=7)
    key = "mean_residence_time_s"
    est = result.pooled.get(key)
    if est is not None:
        for i, a in enumerate(result.repeats):
            m = a.summary.moments[key]
            fx.errorbar(m.value, i, xerr=[[m.value - m.ci[0]], [m.ci[1] - m.value]], fmt="o",
                        color=f"C{i}")  # fmt: skip
        k = len(est.values)
        fx.errorbar(est.value, k, xerr=[[est.value - est.ci[0]], [est.ci[1] - est.value]],
                    fmt="D", color="k")  # fmt: skip
        fx.set_yticks(range(k + 1), [f"repeat {i + 1}" for i in range(k)] + ["pooled"])
        fx.set_xlabel("mean residence time (s), 95 % interval")
    j = result.joint
    verdict = "adequate" if j.adequate else "INADEQUATE"
    fx.set_title(f"joint lack of fit: {verdict} (p = {j.p_value:.2g})", fontsize=9)
    _warn(fig, result.warnings)
    fig.tight_layout()
    return fig
