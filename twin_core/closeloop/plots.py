"""Figures of a close-loop result (matplotlib ``Figure`` objects; the caller saves them): measured
vs predicted before and after, the residuals with their autocorrelation, the candidates' held-out
improvement, and one figure per structure finding (``twin_core.closeloop.structure``). No pyplot
state is used."""

from __future__ import annotations

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from twin_core.closeloop.diagnostics import _acf
from twin_core.closeloop.report import CloseLoopResult
from twin_core.closeloop.structure_base import StructureFinding

__all__ = ["closeloop_figures", "structure_figures"]


def _shade_heldout(ax: Axes, result: CloseLoopResult) -> None:
    ho = result.data.t_s[result.ident.split.heldout]
    if ho.size:
        ax.axvspan(ho.min(), ho.max(), color="0.9", zorder=0, label="held out")


def plot_measured_vs_predicted(result: CloseLoopResult) -> Figure:
    """Measured vs predicted, declared model (before) and augmented model (after)."""
    t, y = result.data.t_s, result.ident.measured
    found = (
        "augmented: " + ", ".join(result.effects_found)
        if result.effects_found
        else f"no effect claimed ({result.status})"
    )
    fig = Figure(figsize=(11, 6.5), layout="tight")
    axes = fig.subplots(2, 1, sharex=True)
    for ax, p, title, color in (
        (axes[0], result.predicted_before, "declared model (before)", "C3"),
        (axes[1], result.predicted_after, f"{found} (after)", "C2"),
    ):
        _shade_heldout(ax, result)
        ax.plot(t, y, ".", ms=2, color="0.4", label="measured")
        ax.plot(t, p, "-", lw=1.2, color=color, label="predicted")
        ax.set_ylabel(f"{result.model.config.sensor.component} (% w/w)")
        ax.set_title(title)
        ax.legend(loc="upper right", fontsize=8)
    axes[1].set_xlabel("t (s)")
    return fig


def plot_residuals(result: CloseLoopResult, max_lag: int = 60) -> Figure:
    """Residual before and after (held-out RMSE in the title) and its autocorrelation with the
    95 % band of white noise, +-1.96 / sqrt(n)."""
    t, y, sp = result.data.t_s, result.ident.measured, result.ident.split
    fig = Figure(figsize=(11, 6.5), layout="tight")
    axes = fig.subplots(2, 2, gridspec_kw={"width_ratios": [3, 1]})
    for row, (p, lab) in enumerate(
        ((result.predicted_before, "before"), (result.predicted_after, "after"))
    ):
        r = y - p
        ax = axes[row, 0]
        _shade_heldout(ax, result)
        ax.plot(t, r, lw=0.6, color="C0")
        ax.axhline(0, color="k", lw=0.8)
        rmse_ho = float(np.sqrt(np.nanmean(r[sp.heldout] ** 2)))
        ax.set_title(f"residual {lab}: held-out RMSE {rmse_ho:.3f} % w/w")
        ax.set_ylabel("measured - predicted")
        ax2 = axes[row, 1]
        rr = r[(sp.train | sp.heldout) & np.isfinite(r)]
        a = _acf(rr, max_lag)
        ax2.bar(np.arange(1, max_lag + 1), a[1:], width=1.0, color="C1")
        ax2.axhline(1.96 / np.sqrt(rr.size), color="k", ls="--", lw=0.7)
        ax2.axhline(-1.96 / np.sqrt(rr.size), color="k", ls="--", lw=0.7)
        ax2.set_title(f"ACF {lab}")
        ax2.set_xlabel("lag (s)")
    axes[1, 0].set_xlabel("t (s)")
    return fig


def plot_candidates(result: CloseLoopResult) -> Figure:
    """Held-out relative MSE improvement of every candidate of the first step (green: passes
    the claim test), with the required margin."""
    rows = sorted(result.ident.steps[0], key=lambda f: -f.rel_improvement)
    fig = Figure(figsize=(8, 0.35 * len(rows) + 1.5), layout="tight")
    ax = fig.subplots()
    vals = [max(f.rel_improvement, -0.1) for f in rows]
    cols = ["C2" if f.claimable else "0.6" for f in rows]
    ax.barh([f.labels[-1] for f in rows], vals, color=cols)
    ax.axvline(result.ident.options.min_improvement, color="k", ls="--", lw=0.8, label="margin")
    ax.invert_yaxis()
    ax.set_xlabel("held-out relative MSE improvement, step 1 (green: passes the claim test)")
    ax.legend(fontsize=8)
    return fig


def closeloop_figures(result: CloseLoopResult) -> dict[str, Figure]:
    """The figures of a result by file name (``closeloop_*.png``)."""
    figs = {
        "closeloop_measured_vs_predicted.png": plot_measured_vs_predicted(result),
        "closeloop_residuals.png": plot_residuals(result),
    }
    if result.ident.steps:
        figs["closeloop_candidates.png"] = plot_candidates(result)
    return figs


def plot_parameter_dependence(finding: StructureFinding) -> Figure:
    """Window estimates of the parameter (95 % intervals) against the covariate, the fitted law
    and the declared value."""
    c = finding.curves
    fig = Figure(figsize=(7, 4.5), layout="tight")
    ax = fig.subplots()
    x = np.asarray(c["x"])
    ax.errorbar(
        x,
        c["levels"],
        yerr=1.96 * np.asarray(c["se"]),
        fmt="o",
        color="C0",
        capsize=3,
        label="window estimates (95 %)",
    )
    xx = np.linspace(x.min(), x.max(), 50)
    ax.plot(
        xx,
        c["theta_ref"] + c["slope"] * (xx - c["x_ref"]),
        "-",
        color="C1",
        label=f"law: {c['slope']:+.3g} {c['unit']} per {c['covariate_unit']}",
    )
    ax.axhline(c["declared"], color="k", ls="--", lw=0.8, label="declared")
    ax.set_xlabel(f"{c['covariate']} ({c['covariate_unit']})")
    ax.set_ylabel(f"{c['param']} ({c['unit']})")
    ax.set_title("parameter against the operating point (empirical)")
    ax.legend(fontsize=8)
    return fig


def plot_periodic(finding: StructureFinding, periods: float = 12.0) -> Figure:
    """Harmonic F statistic over the searched band with the search threshold, and the
    residual with the fitted sinusoid over ``periods`` periods."""
    c = finding.curves
    fig = Figure(figsize=(11, 4.5), layout="tight")
    ax, ax2 = fig.subplots(1, 2)
    ax.semilogx(c["freqs_hz"], c["f_stat"], lw=0.6, color="C0")
    ax.axhline(c["f_threshold"], color="k", ls="--", lw=0.8, label="search threshold")
    ax.axvline(c["f_hz"], color="C3", lw=0.8, label=f"{c['f_hz']:.5f} Hz")
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel(f"harmonic F (2, {c['dof']})")
    ax.legend(fontsize=8)
    t, r, fit = np.asarray(c["t_s"]), np.asarray(c["residual"]), np.asarray(c["fit"])
    sel = t < t[0] + periods / c["f_hz"]
    ax2.plot(t[sel], r[sel], ".", ms=2, color="0.5", label="residual")
    ax2.plot(t[sel], fit[sel], "-", color="C3", label="sinusoid")
    ax2.set_xlabel("t (s)")
    ax2.set_ylabel("measured - predicted (% w/w)")
    ax2.legend(fontsize=8)
    return fig


def plot_kernel_correction(finding: StructureFinding) -> Figure:
    """Corrected blender kernel with its bootstrap 95 % band against the declared E(t)."""
    c = finding.curves
    fig = Figure(figsize=(7, 4.5), layout="tight")
    ax = fig.subplots()
    lag = np.asarray(c["lag_s"])
    if c.get("band") is not None:
        ax.fill_between(
            lag, c["band"][0], c["band"][1], color="C0", alpha=0.25, label="bootstrap 95 %"
        )
    ax.plot(lag, c["kernel"], "-", color="C0", label="corrected kernel")
    ax.plot(lag, c["declared"], "--", color="k", lw=1.0, label="declared E(t)")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("E(t) (1/s)")
    ax.set_title("blender response (empirical)")
    ax.legend(fontsize=8)
    return fig


def structure_figures(findings: list[StructureFinding]) -> dict[str, Figure]:
    """One figure per structure finding by file name (``closeloop_structure_<i>_<kind>.png``)."""
    draw = {
        "parameter_dependence": plot_parameter_dependence,
        "periodic": plot_periodic,
        "kernel_correction": plot_kernel_correction,
    }
    return {
        f"closeloop_structure_{i}_{f.kind}.png": draw[f.kind](f) for i, f in enumerate(findings)
    }
