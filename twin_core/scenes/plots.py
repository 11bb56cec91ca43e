"""Matplotlib figures of the DEM scenes (PNG files written where the caller asks)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from twin_core.dem.frames import Frame  # noqa: E402

__all__ = ["curves", "heap_profiles", "snapshot", "xy_fit"]

_COLORS = {1: "tab:red", 2: "tab:blue"}


def snapshot(path: Path, frame: Frame, title: str = "") -> Path:
    """Three orthogonal projections of a frame, coloured by particle type."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    pos = frame.positions * 1e3
    cols = [_COLORS.get(int(t), "tab:gray") for t in frame.types]
    s = max(0.5, min(30.0, 4e4 / max(frame.n, 1)))
    for ax, (i, j), lab in zip(axes, ((0, 2), (1, 2), (0, 1)), ("x-z", "y-z", "x-y")):
        ax.scatter(pos[:, i], pos[:, j], c=cols, s=s, linewidths=0)
        ax.set_aspect("equal")
        ax.set_xlabel("xyz"[i] + " (mm)")
        ax.set_ylabel("xyz"[j] + " (mm)")
        ax.set_title(lab)
    fig.suptitle(f"{title} t = {frame.t:.2f} s, {frame.n} particles")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def _save_xy(fig: Any, ax: Any, path: Path, xlabel: str, ylabel: str, title: str) -> Path:
    """Label, grid and legend an x-y plot, write it as PNG and close the figure."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def curves(
    path: Path,
    series: list[tuple[np.ndarray, np.ndarray, str]],
    xlabel: str,
    ylabel: str,
    title: str = "",
    hline: tuple[float, str] | None = None,
) -> Path:
    """Line plot of (x, y, label) series, optional horizontal reference line."""
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for x, y, lab in series:
        ax.plot(x, y, label=lab)
    if hline is not None:
        ax.axhline(hline[0], color="k", ls="--", lw=1, label=hline[1])
    return _save_xy(fig, ax, path, xlabel, ylabel, title)


def xy_fit(
    path: Path,
    x: np.ndarray,
    y: np.ndarray,
    xf: np.ndarray,
    yf: np.ndarray,
    xlabel: str,
    ylabel: str,
    title: str,
) -> Path:
    """Scatter of data with a fitted curve."""
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    ax.plot(x, y, "o", ms=4, label="DEM")
    ax.plot(xf, yf, "-", label="fit")
    return _save_xy(fig, ax, path, xlabel, ylabel, title)


def heap_profiles(path: Path, res: dict, title: str = "") -> Path:
    """Upper and lower free-surface profiles of the drawdown test with fitted slope lines."""
    fig, ax = plt.subplots(figsize=(8, 5))
    for key, fits, col in (
        ("upper", res["upper_fit"], "tab:red"),
        ("lower", res["lower_fit"], "tab:blue"),
    ):
        p = res["profiles"][key]
        x = np.asarray(p["x"]) * 1e3
        h = np.asarray(p["h"]) * 1e3
        ax.plot(x, h, ".", color=col, label=f"{key} surface")
        for side, f in fits.items():
            if not np.isfinite(f.get("slope", np.nan)):
                continue
            half = x < x.mean() if side == "left" else x >= x.mean()
            xs = x[half]
            hs = h[half]
            lo, hi = hs.min(), hs.max()
            sel = (hs >= lo + 0.15 * (hi - lo)) & (hs <= lo + 0.85 * (hi - lo))
            if sel.sum() < 2:
                continue
            xx = xs[sel]
            b = np.mean(hs[sel]) - f["slope"] * np.mean(xx)
            ax.plot(xx, f["slope"] * xx + b, "-", color="k", lw=1.5)
            ax.annotate(
                f"{f['angle_deg']:.1f} deg", (xx.mean(), f["slope"] * xx.mean() + b), fontsize=8
            )
    return _save_xy(
        fig, ax, path, "x (mm)", "surface height (mm)", title or "drawdown heap profiles"
    )
