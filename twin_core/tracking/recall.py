"""Recall questions on a lot trace: which product holds a lot, and what the product leaving at
a time is made of.

A recall of lot j at threshold F lists the maximal runs of ticks where the lot's mass fraction
in the product w_j(t) = y_j(t) / sum_i y_i(t) exceeds F (``twin_core.tracking.tracker``), each
with its product mass sum_n sum_i y_i[n] dt and the lot's mass sum_n y_j[n] dt in it. The
coverage of a recall is the lot's mass in its intervals over the lot's mass that left: what a
threshold leaves out is the lot's dilute front and tail (bounded by F times the product
leaving there); docs/traceability.md measures it against an independent parcel simulation.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from twin_core.tracking.tracker import LotTrace

__all__ = [
    "Interval",
    "LotShare",
    "composition_at",
    "lot_intervals",
    "recall_coverage",
    "threshold_for_coverage",
]


@dataclass(frozen=True)
class Interval:
    """A product interval holding a lot: [t_start_s, t_end_s] (the ticks' times; each tick
    stands for the product leaving in [t, t + dt)), the product and lot masses, the largest
    lot fraction."""

    t_start_s: float
    t_end_s: float
    product_kg: float
    lot_kg: float
    max_fraction: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def lot_intervals(trace: LotTrace, lot: str, threshold: float) -> list[Interval]:
    """The product intervals where lot ``lot``'s mass fraction exceeds ``threshold`` (module
    docstring)."""
    if not 0.0 < threshold < 1.0:
        raise ValueError(f"threshold must be in (0, 1), got {threshold!r}")
    j = trace.column(lot)
    dt = float(trace.t_s[1] - trace.t_s[0])
    total = trace.outlet_kg_s.sum(axis=1)
    y = trace.outlet_kg_s[:, j]
    w = np.where(total > 0, y / np.where(total > 0, total, 1.0), 0.0)
    on = w > threshold
    if not on.any():
        return []
    edges = np.diff(np.concatenate([[0], on.astype(np.int8), [0]]))
    starts = np.nonzero(edges == 1)[0]
    ends = np.nonzero(edges == -1)[0]
    out = []
    for a, b in zip(starts, ends):
        out.append(
            Interval(
                float(trace.t_s[a]),
                float(trace.t_s[b - 1]),
                float(total[a:b].sum() * dt),
                float(y[a:b].sum() * dt),
                float(w[a:b].max()),
            )
        )
    return out


def recall_coverage(trace: LotTrace, lot: str, intervals: list[Interval]) -> float:
    """The lot's mass in ``intervals`` over its mass that left the blender in the record."""
    j = trace.column(lot)
    dt = float(trace.t_s[1] - trace.t_s[0])
    out = float(trace.outlet_kg_s[:, j].sum() * dt)
    return sum(i.lot_kg for i in intervals) / out if out > 0 else 0.0


def threshold_for_coverage(trace: LotTrace, lot: str, coverage: float) -> float:
    """The largest threshold F whose recall holds at least ``coverage`` of the lot's mass that
    left (by the model): the ticks sorted by the lot's fraction w_j, highest first, are taken
    until their lot mass reaches ``coverage``; F is just below the last fraction taken."""
    if not 0.0 < coverage < 1.0:
        raise ValueError(f"coverage must be in (0, 1), got {coverage!r}")
    j = trace.column(lot)
    total = trace.outlet_kg_s.sum(axis=1)
    y = trace.outlet_kg_s[:, j]
    w = np.where(total > 0, y / np.where(total > 0, total, 1.0), 0.0)
    order = np.argsort(-w, kind="stable")
    cum = np.cumsum(y[order])
    if cum[-1] <= 0:
        raise ValueError(f"lot {lot!r} did not leave the blender in the record")
    k = int(np.searchsorted(cum, coverage * cum[-1]))
    return float(w[order[min(k, w.size - 1)]]) * (1 - 1e-9)


@dataclass(frozen=True)
class LotShare:
    """One lot in the product leaving at a time: its component, its mass fraction of the
    product and of its component."""

    lot: str
    component: str
    feeder: str
    fraction: float
    component_fraction: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def composition_at(trace: LotTrace, t_s: float, min_fraction: float = 0.0) -> list[LotShare]:
    """The lots in the product leaving at plant time ``t_s`` (the tick at or before it), by
    component then decreasing fraction; lots at or below ``min_fraction`` of the product
    left out."""
    t = trace.t_s
    if not t[0] <= t_s <= t[-1] + (t[1] - t[0]):
        raise ValueError(f"at must be within the record [{t[0]:g}, {t[-1]:g}] s, got {t_s!r}")
    i = int(np.searchsorted(t, t_s, side="right") - 1)
    row = trace.outlet_kg_s[i]
    total = row.sum()
    out = []
    for j, lot in enumerate(trace.lots):
        if row[j] <= 0 or total <= 0:
            continue
        frac = float(row[j] / total)
        if frac <= min_fraction:
            continue
        comp = trace.lot_component[j]
        ctot = sum(row[k] for k, c in enumerate(trace.lot_component) if c == comp)
        out.append(LotShare(lot, comp, trace.lot_feeder[j], frac, float(row[j] / ctot)))
    return sorted(out, key=lambda s: (s.component, -s.fraction))
