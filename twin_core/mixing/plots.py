"""Figures of the mixing analysis (PNG files written where the caller asks).

``plot_analysis``: each index's progress, smoothed curve and T95 fit (seed Figure 4.6);
``plot_t95_by_speed``: T95 per index and blade speed (seed Figure 4.7).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from twin_core.mixing.analysis import MixingAnalysis
from twin_core.mixing.series import INDEX_NAMES
from twin_core.mixing.t95 import exponential_model, oscillating_model, smooth

__all__ = ["analysis_figure", "plot_analysis", "plot_t95_by_speed"]

#: what 1 means on the progress axis, by the normalisation of :func:`~twin_core.mixing.analysis.analyze`
PROGRESS_LABEL = {
    "plateau": "mixing progress (0 initial, 1 own plateau)",
    "random": "mixing progress (0 initial, 1 random mixture)",
}


def plot_analysis(an: MixingAnalysis, path: str | Path, smooth_window: int = 11) -> Path:
    """Write :func:`analysis_figure` to ``path``."""
    return _save(analysis_figure(an, smooth_window), path)


def analysis_figure(an: MixingAnalysis, smooth_window: int = 11):
    """Figure 4.6-like panel: each index's progress, its smoothed curve and the fit; the y label
    says what 1 means (the run's own plateau or a random mixture, ``an.normalize``)."""
    import matplotlib.pyplot as plt

    names = [c for c in an.progress.columns if c in INDEX_NAMES]
    ncol = 4
    nrow = int(np.ceil(len(names) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.2 * ncol, 2.4 * nrow), squeeze=False)
    t = an.progress["t"].to_numpy()
    for ax, name in zip(axes.ravel(), names):
        y = an.progress[name].to_numpy()
        ax.plot(t, y, ".", ms=2, color="0.6", label="index")
        ax.plot(t, smooth(y, smooth_window), "-", color="C0", lw=1, label="smoothed")
        fit = an.fits.get(name)
        if fit is not None:
            tt = t - t[0]
            model = (
                oscillating_model(tt, fit.A, fit.gamma, fit.w)
                if fit.model == "osc"
                else exponential_model(tt, fit.A, fit.gamma)
            )
            ax.plot(t, model, "--", color="C3", lw=1, label="fit")
            ax.axvline(fit.t95, color="C3", lw=0.6, ls=":")
            ax.set_title(f"{name}: T95 = {fit.t95:.2f} s, R2 = {fit.r2:.2f}", fontsize=8)
        else:
            ax.set_title(f"{name}: no fit", fontsize=8)
        ax.axhline(0.95, color="k", lw=0.4)
        ax.set_ylim(-0.3, 1.3)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(names) :]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=6)
    fig.supxlabel("time (s)")
    fig.supylabel(PROGRESS_LABEL[an.normalize])
    fig.tight_layout()
    return fig


def plot_t95_by_speed(table: pd.DataFrame, path: str | Path) -> Path:
    """Figure 4.7-like grouped bars of T95 per index and blade speed."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 3.5))
    width = 0.8 / max(len(table.columns), 1)
    x = np.arange(len(table.index))
    for k, col in enumerate(table.columns):
        ax.bar(x + k * width, table[col].to_numpy(), width, label=col)
    ax.set_xticks(x + width * (len(table.columns) - 1) / 2, table.index)
    ax.set_ylabel("T95 (s)")
    ax.legend()
    fig.tight_layout()
    return _save(fig, path)


def _save(fig, path: str | Path) -> Path:
    """Save a figure (120 dpi) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
