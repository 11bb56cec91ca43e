"""Figures of the live twin (matplotlib ``Figure`` objects; the caller saves them). No pyplot
state is used, so these are safe in servers and threads."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

__all__ = ["plot_outlet"]


def plot_outlet(
    measured: Mapping[float, float],
    predicted: Mapping[float, float],
    component: str,
    line: str,
    limits: tuple[float, float, float] | None = None,
    alert_windows: Sequence[tuple[float, float]] = (),
    predicted_label: str = "predicted (blender)",
    others: Mapping[str, Mapping[float, float]] | None = None,
) -> Figure:
    """Measured (NIR) vs predicted (blender) outlet concentration of ``component`` by plant
    time, the target and limits ``(target, lower, upper)`` as horizontal lines, the OOS alert
    windows shaded; ``others``: more predictions by label (e.g. another blender model)."""
    fig = Figure(figsize=(11, 4.5), layout="tight")
    ax = fig.subplots()
    tm = np.array(sorted(measured))
    tp = np.array(sorted(predicted))
    if tm.size:
        ax.plot(tm, [measured[t] for t in tm], ".", ms=2, color="0.55", label="measured (NIR)")
    if tp.size:
        ax.plot(tp, [predicted[t] for t in tp], "-", lw=1.2, color="C0", label=predicted_label)
    for i, (label, series) in enumerate((others or {}).items()):
        ts = np.array(sorted(series))
        ax.plot(ts, [series[t] for t in ts], "--", lw=1.0, color=f"C{i + 1}", label=label)
    if limits is not None:
        for v, ls in zip(limits, ("-", "--", "--")):
            ax.axhline(v, color="k", lw=0.8, ls=ls)
    for i, (a, b) in enumerate(sorted(alert_windows)):
        ax.axvspan(a, b, color="C3", alpha=0.2, label="OOS alert window" if i == 0 else None)
    ax.set_xlabel("plant time (s)")
    ax.set_ylabel(f"{component} at the outlet (% w/w)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"Live twin of {line}: measured vs predicted, alert windows shaded")
    return fig
