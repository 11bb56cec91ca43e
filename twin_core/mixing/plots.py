"""Figures of the mixing analysis (PNG files written where the caller asks).

``plot_analysis``: each index's progress, smoothed curve and T95 fit (seed Figure 4.6);
``plot_t95_by_speed``: T95 per index and blade speed (seed Figure 4.7); ``velocity_figure``:
the mean velocity field in a plane; ``homogeneity_figure``: homogeneity indices over time.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from twin_core.mixing.analysis import MixingAnalysis
from twin_core.mixing.fields import VelocityFields
from twin_core.mixing.grid import CylindricalGrid, GridSpec
from twin_core.mixing.series import INDEX_NAMES
from twin_core.mixing.t95 import exponential_model, oscillating_model, smooth

__all__ = [
    "analysis_figure", "homogeneity_figure", "plot_analysis", "plot_t95_by_speed", "save_figure",
    "velocity_figure",
]  # fmt: skip

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


def _plane_average(values: np.ndarray, amount: np.ndarray, shape, axis: int):
    """Amount-weighted average of a cell field over one grid axis: ``(n_a, n_b, d)``."""
    v = np.nan_to_num(values).reshape(*shape, -1)
    w = amount.reshape(shape)[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (v * w).sum(axis=axis) / w.sum(axis=axis)
    return np.where(w.sum(axis=axis) > 0, out, np.nan)


def velocity_figure(fields: VelocityFields, grid: GridSpec | CylindricalGrid):
    """The mean velocity field in a plane, arrows coloured by speed. Cartesian grids: averaged
    over the axis with the fewest cells (a slab's thickness); cylindrical bins: the
    cross-section when one bin deep, else the radius-axial plane averaged over the angle."""
    import matplotlib.pyplot as plt

    amount = fields.amount.sum(axis=0)
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    if isinstance(grid, CylindricalGrid):
        n_t, n_r, n_z = grid.shape
        if n_z == 1:
            centre = grid.cell_centres()
            a, b = grid.cross_axes
            theta = np.arctan2(centre[:, b] - grid.centre[1], centre[:, a] - grid.centre[0])
            vr, vt = fields.mean[:, 0], fields.mean[:, 1]
            u, v = vr * np.cos(theta) - vt * np.sin(theta), vr * np.sin(theta) + vt * np.cos(theta)
            x, y = centre[:, a], centre[:, b]
            labels = ("xyz"[a] + " (m)", "xyz"[b] + " (m)")
            ax.set_aspect("equal")
        else:
            plane = _plane_average(fields.mean, amount, grid.shape, 0)
            e = grid.ring_edges()
            rr, zz = np.meshgrid(0.5 * (e[:-1] + e[1:]), grid.lo + (np.arange(n_z) + 0.5) * (grid.hi - grid.lo) / n_z, indexing="ij")  # fmt: skip
            x, y, u, v = rr.ravel(), zz.ravel(), plane[..., 0].ravel(), plane[..., 2].ravel()
            labels = ("r (m)", "xyz"[grid.axis] + " (m)")
    else:
        axis = int(np.argmin(grid.shape))
        keep = [k for k in range(3) if k != axis]
        plane = _plane_average(fields.mean, amount, grid.shape, axis)
        centre = grid.cell_centres().reshape(*grid.shape, 3)
        centre = np.take(centre, 0, axis=axis)
        x, y = centre[..., keep[0]].ravel(), centre[..., keep[1]].ravel()
        u, v = plane[..., keep[0]].ravel(), plane[..., keep[1]].ravel()
        labels = ("xyz"[keep[0]] + " (m)", "xyz"[keep[1]] + " (m)")
        ax.set_aspect("equal")
    speed = np.hypot(u, v)
    ok = np.isfinite(speed)
    still = not np.any(speed[ok] > 0)  # no in-plane motion: dots, not a zero-length scale
    q = ax.quiver(
        x[ok], y[ok], u[ok], v[ok], speed[ok], cmap="viridis", scale=1.0 if still else None
    )
    fig.colorbar(q, ax=ax, label="in-plane speed (m/s)")
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.set_title("mean velocity field", fontsize=9)
    fig.tight_layout()
    return fig


def homogeneity_figure(series: pd.DataFrame):
    """Homogeneity index of each attribute over time (one panel per attribute: units differ)."""
    import matplotlib.pyplot as plt

    cols = [c for c in series.columns if c.startswith("HI_")]
    fig, axes = plt.subplots(1, len(cols), figsize=(3.6 * len(cols), 2.8), squeeze=False)
    for ax, col in zip(axes[0], cols):
        ax.plot(series["t"], series[col], "-", color="C0", lw=1)
        ax.set_title(f"homogeneity of {col[3:]}", fontsize=9)
        ax.set_xlabel("time (s)")
    axes[0, 0].set_ylabel("HI (attribute units)")
    fig.tight_layout()
    return fig


def save_figure(fig, path: str | Path) -> Path:
    """Save a figure drawn by this module (120 dpi) and close it."""
    return _save(fig, path)
