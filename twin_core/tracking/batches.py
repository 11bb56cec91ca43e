"""Batches of a continuous line and the numbers of their batch record (ICH Q13 section 3.1).

A batch is cut by a quantity of output, of input or by time (``schemas.line.BatchSettings``):

    product_mass: boundaries where the cumulative product mass P(t) = int_0^t sum_j y_j dt
                  (the blender outlet, diverted product included) crosses k * size;
    api_mass:     where the cumulative API fed A(t) = int_0^t q_api dt (the API feeders'
                  measured discharge) crosses k * size;
    run_time:     every ``size`` seconds of plant time from ``start_s``.

A boundary falls on the first tick at or after the crossing; the last batch of a record may be
partial (``complete`` False). In each batch, lot j's mass is sum_n y_j[n] dt over its ticks
(``twin_core.tracking.tracker``), its fraction of the batch that mass over the batch's product
mass and its fraction of its component that mass over the component's mass in the batch. The
diverted mass is the product leaving inside the divert windows.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from twin_core.tracking.tracker import LotTrace

__all__ = ["Batch", "BatchCounter", "batch_bounds", "batch_summaries", "window_mask"]


def batch_bounds(
    trace: LotTrace, by: str, size: float, start_s: float = 0.0, api_component: str = "api"
) -> list[tuple[int, int, bool]]:
    """Batches as (first tick, end tick exclusive, complete) (module docstring)."""
    t = trace.t_s
    n = t.size
    dt = float(t[1] - t[0])
    a = int(np.searchsorted(t, start_s - 1e-9))
    if a >= n:
        raise ValueError(f"batch.start_s must be within the record (<= {t[-1]:g} s), got {start_s}")
    if by == "run_time":
        q = np.full(n, dt)
    elif by == "product_mass":
        q = trace.outlet_kg_s.sum(axis=1) * dt
    elif by == "api_mass":
        cols = [j for j, c in enumerate(trace.lot_component) if c == api_component]
        if not cols:
            raise ValueError(
                f"batch.api_component must be a component of the line, got {api_component!r}"
            )
        q = trace.fed_kg_s[:, cols].sum(axis=1) * dt
    else:
        raise ValueError(f"batch.by must be product_mass, api_mass or run_time, got {by!r}")
    counter = BatchCounter(size, float(t[a]))
    out = []
    first = a
    for i in range(a, n):
        for kind, _, _ in counter.push(float(t[i]), float(q[i])):
            if kind == "start":
                first = i
            else:
                out.append((first, i + 1, True))
                first = i + 1
    if first < n:
        out.append((first, n, False))
    return out


class BatchCounter:
    """The batch boundaries of a stream of ticks, one tick at a time (the rule of the module
    docstring; :func:`batch_bounds` over a record, the trace service live).

    Args:
        size: quantity per batch (kg or s).
        start_s: plant time the first batch starts.
    """

    def __init__(self, size: float, start_s: float = 0.0) -> None:
        if not size > 0:
            raise ValueError(f"batch.size must be > 0, got {size!r}")
        self.size = float(size)
        self.start_s = float(start_s)
        #: quantity so far (from start_s), the batch in progress, whether it has started
        self.total = 0.0
        self.batch = 1
        self._open = False

    def push(self, t: float, quantity: float) -> list[tuple[str, int, float]]:
        """One tick's quantity; returns ``("start", k, t)`` when batch k starts with this tick
        and ``("end", k, t)`` when it ends with it (its cumulative quantity reaches k size)."""
        if t < self.start_s - 1e-9:
            return []
        out = []
        if not self._open:
            out.append(("start", self.batch, t))
            self._open = True
        self.total += quantity
        if self.total >= self.batch * self.size * (1 - 1e-12):
            out.append(("end", self.batch, t))
            self.batch += 1
            self._open = False
        return out

    def to_state(self) -> dict[str, float | int | bool]:
        return {
            "size": self.size,
            "start_s": self.start_s,
            "total": self.total,
            "batch": self.batch,
            "open": self._open,
        }


def window_mask(t_s: np.ndarray, windows: Sequence[tuple[float, float]]) -> np.ndarray:
    """Ticks whose time lies in one of the windows [start, end]."""
    mask = np.zeros(t_s.size, dtype=bool)
    for a, b in windows:
        mask |= (t_s >= a) & (t_s <= b)
    return mask


@dataclass
class Batch:
    """The numbers of one batch record (module docstring)."""

    index: int
    t_start_s: float
    t_end_s: float
    complete: bool
    product_kg: float
    diverted_kg: float
    lots: list[dict[str, Any]] = field(default_factory=list)


def batch_summaries(
    trace: LotTrace,
    bounds: Sequence[tuple[int, int, bool]],
    divert_windows: Sequence[tuple[float, float]] = (),
) -> list[Batch]:
    """Per batch: time span, product and diverted mass, every lot with its mass and its
    fractions of the batch and of its component (module docstring)."""
    t = trace.t_s
    dt = float(t[1] - t[0])
    diverted = window_mask(t, divert_windows)
    y = trace.outlet_kg_s
    out = []
    for b, (a, e, complete) in enumerate(bounds, start=1):
        mass = y[a:e].sum(axis=0) * dt
        product = float(mass.sum())
        comp_mass: dict[str, float] = {}
        for j, c in enumerate(trace.lot_component):
            comp_mass[c] = comp_mass.get(c, 0.0) + float(mass[j])
        lots = [
            {
                "lot": trace.lots[j],
                "feeder": trace.lot_feeder[j],
                "component": trace.lot_component[j],
                "mass_kg": float(mass[j]),
                "fraction_of_batch": float(mass[j] / product) if product > 0 else 0.0,
                "fraction_of_component": (
                    float(mass[j] / comp_mass[trace.lot_component[j]])
                    if comp_mass[trace.lot_component[j]] > 0
                    else 0.0
                ),
            }
            for j in range(len(trace.lots))
            if mass[j] > 0
        ]
        lots.sort(key=lambda r: (r["component"], -r["mass_kg"]))
        out.append(
            Batch(
                index=b,
                t_start_s=float(t[a]),
                t_end_s=float(t[e - 1] + dt),
                complete=complete,
                product_kg=product,
                diverted_kg=float(y[a:e][diverted[a:e]].sum() * dt),
                lots=lots,
            )
        )
    return out
