"""Figures of the calibration and feeder results (matplotlib ``Figure`` objects; the caller
saves them). No pyplot state is used, so these are safe in servers and threads."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

__all__ = [
    "plot_correlation_map",
    "plot_parity",
    "plot_contours",
    "plot_profiles",
    "plot_feeder_trace",
    "plot_prediction_profiles",
    "plot_feed_factor_fit",
]


def plot_correlation_map(
    corr: pd.DataFrame, title: str = "DSD colour map on correlations"
) -> Figure:
    """|r| between main effects, two-factor interactions and quadratics (seed Fig. 3.4)."""
    n = len(corr)
    fig = Figure(figsize=(max(6, 0.18 * n + 2), max(5, 0.18 * n + 1.5)), layout="constrained")
    ax = fig.subplots()
    im = ax.imshow(corr.to_numpy(), cmap="coolwarm", vmin=0, vmax=1, interpolation="nearest")
    ax.set_xticks(range(n), corr.columns, rotation=90, fontsize=6)
    ax.set_yticks(range(n), corr.index, fontsize=6)
    ax.set_title(title)
    fig.colorbar(im, ax=ax, label="|r|", shrink=0.8)
    return fig


def plot_parity(
    models: Mapping[str, object], extra: Mapping[str, pd.DataFrame] | None = None
) -> Figure:
    """Actual vs predicted for each fitted surface (seed Figs. 3.5-3.6, 8.6-8.8, 3.14-3.16).

    ``models``: name -> ResponseSurface (or TwoStepRSM). ``extra``: name -> DataFrame with
    ``actual`` and ``predicted`` of additional (verification) points, drawn as triangles.
    """
    k = len(models)
    cols = min(k, 2)
    rows = int(np.ceil(k / cols))
    fig = Figure(figsize=(5 * cols, 4.5 * rows), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    for ax, (name, m) in zip(axes, models.items()):
        mm = getattr(m, "model_", m)
        a, p = mm.actual_, mm.fitted_
        ax.scatter(p, a, s=22, label="design runs")
        lo, hi = float(min(a.min(), p.min())), float(max(a.max(), p.max()))
        if extra and name in extra:
            e = extra[name]
            ax.scatter(e["predicted"], e["actual"], marker="^", s=50, label="verification")
            lo, hi = (
                min(lo, e[["actual", "predicted"]].min().min()),
                max(hi, e[["actual", "predicted"]].max().max()),
            )
        pad = 0.05 * (hi - lo or 1.0)
        ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], "k--", lw=1)
        ax.set_xlabel(f"{name} predicted")
        ax.set_ylabel(f"{name} actual")
        ax.set_title(f"{name}: R$^2$ = {mm.r2_:.3f}, RMSE = {mm.rmse_:.3g}")
        ax.legend(fontsize=8)
    for ax in axes[k:]:
        ax.set_visible(False)
    return fig


def plot_contours(
    calibration: object,
    x: str,
    y: str,
    at: Mapping[str, float],
    targets: Mapping[str, float] | None = None,
    solutions: list[Mapping[str, float]] | None = None,
    n: int = 121,
) -> Figure:
    """Contours of each response over unknowns ``x`` and ``y`` (seed Fig. 3.13), the target
    level of each drawn bold, and a last panel overlaying the target lines with the solutions."""
    xx, yy, z = calibration.contour_grid(x, y, at, n=n)  # type: ignore[attr-defined]
    k = len(z) + (1 if targets else 0)
    cols = min(k, 3)
    rows = int(np.ceil(k / cols))
    fig = Figure(figsize=(4.6 * cols, 4.0 * rows), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    colors = ["C0", "C1", "C2", "C3", "C4", "C5"]
    for ax, (name, zz) in zip(axes, z.items()):
        cs = ax.contourf(xx, yy, zz, levels=14, cmap="viridis")
        fig.colorbar(cs, ax=ax)
        if targets and name in targets and zz.min() <= targets[name] <= zz.max():
            ax.contour(xx, yy, zz, levels=[targets[name]], colors="w", linewidths=2.5)
        ax.set_title(name)
        ax.set_xlabel(x)
        ax.set_ylabel(y)
    if targets:
        ax = axes[len(z)]
        for i, (name, zz) in enumerate(z.items()):
            if name in targets and zz.min() <= targets[name] <= zz.max():
                ax.contour(xx, yy, zz, levels=[targets[name]], colors=colors[i % 6], linewidths=2)
                ax.plot([], [], color=colors[i % 6], label=f"{name} = {targets[name]:g}")
        for s in solutions or []:
            ax.plot(s[x], s[y], "k*", ms=12)
        ax.set_xlim(xx.min(), xx.max())
        ax.set_ylim(yy.min(), yy.max())
        ax.set_title("targets (other unknowns at the solution)")
        ax.set_xlabel(x)
        ax.set_ylabel(y)
        ax.legend(fontsize=7)
    for ax in axes[k:]:
        ax.set_visible(False)
    return fig


def plot_profiles(profiles: Mapping[str, pd.DataFrame]) -> Figure:
    """Objective profiles (min cost over the other unknowns vs one unknown)."""
    k = len(profiles)
    fig = Figure(figsize=(4 * k, 3.4), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, k)).ravel()
    for ax, (name, df) in zip(axes, profiles.items()):
        ax.semilogy(df[name], np.maximum(df["cost"], 1e-16), "o-")
        ax.set_xlabel(name)
        ax.set_ylabel("profile cost")
    return fig


def plot_feeder_trace(trace: object) -> Figure:
    """Mass flow, screw speed, hopper mass and feed factor vs time, refills shaded."""
    t = trace.t_s  # type: ignore[attr-defined]
    fig = Figure(figsize=(10, 8), layout="constrained")
    axes = fig.subplots(4, 1, sharex=True)
    series = [
        ("mass_flow_kg_h", "mass flow (kg/h)"),
        ("screw_speed_rpm", "screw speed (rpm)"),
        ("hopper_mass_kg", "hopper mass (kg)"),
        ("feed_factor_g_rev", "feed factor (g/rev)"),
    ]
    for ax, (attr, label) in zip(axes, series):
        ax.plot(t, getattr(trace, attr), lw=0.8)
        ax.set_ylabel(label)
        for a, b in trace.refills:  # type: ignore[attr-defined]
            ax.axvspan(a, b, color="orange", alpha=0.3)
    sp = getattr(trace, "setpoint_kg_h", None)
    if sp is not None:
        axes[0].plot(t, sp, "k--", lw=1, label="set point")
        axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("time (s)")
    return fig


def plot_prediction_profiles(
    model: object, ranges: Mapping[str, tuple[float, float]], at: Mapping[str, float] | None = None
) -> Figure:
    """JMP-style prediction profiler (seed Figs. 8.9-8.11): the prediction and its 95 %
    confidence band along each factor of the model, the others held at ``at`` (default: the
    model's centres, i.e. the design means)."""
    m = getattr(model, "model_", model)
    factors = list(m.factors_)
    base = {f: float((at or {}).get(f, m.centers_[f])) for f in factors}
    fig = Figure(figsize=(2.8 * max(len(factors), 1), 3.0), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, max(len(factors), 1))).ravel()
    for ax, f in zip(axes, factors):
        lo, hi = ranges[f]
        x = np.linspace(lo, hi, 60)
        data = {g: np.full(x.size, base[g]) for g in factors}
        data[f] = x
        iv = m.predict_interval(data, kind="confidence")
        ax.fill_between(x, iv["lower"], iv["upper"], alpha=0.25)
        ax.plot(x, iv["predicted"], "C3-")
        ax.axvline(base[f], color="k", ls=":", lw=1)
        ax.set_xlabel(f)
    axes[0].set_ylabel(m.response)
    return fig


def plot_feed_factor_fit(
    weight: np.ndarray, ff: np.ndarray, fit: object, weight_label: str, ff_label: str
) -> Figure:
    """Feed factor against hopper mass with the fitted seed Eq. (2) curve and its R^2."""
    fig = Figure(figsize=(6, 4), layout="constrained")
    ax = fig.subplots()
    ax.plot(weight, ff, ".", ms=3, label="data")
    w = np.linspace(0, float(np.max(weight)), 200)
    ax.plot(w, fit.predict(w), "r-", label=f"Eq. (2), R$^2$ = {fit.r2:.3f}")  # type: ignore[attr-defined]
    ax.set_xlabel(weight_label)
    ax.set_ylabel(ff_label)
    ax.legend()
    return fig
