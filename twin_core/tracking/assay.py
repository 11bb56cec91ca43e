"""Raw-material lots whose content differs from the label: the plant's truth and the twin's
prediction.

A lot j of the API with assay a_j (mass of API per mass of material, 1 = label claim) delivers
a_j of its mass as API and (1 - a_j) as inert matter. With s_j(t) the share of lot j in the
feeder's discharge q(t) (the hopper law, ``twin_core.tracking.hopper``), the feeder delivers

    q_api(t) = q(t) (1 - sum_j (1 - a_j) s_j(t)),   q_inert(t) = q(t) - q_api(t)        (1)

(total mass unchanged: the load cell weighs material, not API). At the outlet the same holds
with the outlet shares: the API content of the product leaving at t is, with w_j(t) the lot's
mass fraction in the product (``LotTrace.fractions``),

    c(t) = c_label(t) - 100 sum_j (1 - a_j) w_j(t)   [% w/w]                              (2)

so a lot at 90 % of label that makes up the whole API (10 % w/w) lowers the content by
1 % w/w where it leaves (:func:`content_deviation`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["LotAssay", "content_deviation", "delivered_flows", "parse_lot_assay"]


@dataclass(frozen=True)
class LotAssay:
    """Lot ``lot_id`` of feeder ``feeder`` holds ``assay`` of label (0.9: 90 %)."""

    feeder: str
    lot_id: str
    assay: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.assay) and 0.0 <= self.assay <= 2.0):
            raise ValueError(f"lot assay must be in [0, 2] (fraction of label), got {self.assay!r}")


def parse_lot_assay(text: str) -> LotAssay:
    """``FEEDER:LOT:ASSAY`` (e.g. ``api:L0003:0.9``; a LOT without the feeder's prefix gets
    it: ``api-L0003``) -> :class:`LotAssay`."""
    parts = text.split(":")
    if len(parts) != 3 or not parts[0] or not parts[1]:
        raise ValueError(f"lot assay must be FEEDER:LOT:ASSAY, got {text!r}")
    try:
        assay = float(parts[2])
    except ValueError:
        raise ValueError(f"lot assay ASSAY must be a number, got {text!r}") from None
    lot = parts[1] if parts[1].startswith(f"{parts[0]}-") else f"{parts[0]}-{parts[1]}"
    return LotAssay(parts[0], lot, assay)


def delivered_flows(
    q_kg_h: np.ndarray, shares: Mapping[str, np.ndarray], assays: Sequence[LotAssay]
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (1): (API flow, inert flow) of a feeder discharging ``q_kg_h`` whose discharge holds
    the lot shares ``shares`` (lot -> share on the same grid)."""
    q = np.asarray(q_kg_h, dtype=float)
    loss = np.zeros_like(q)
    for a in assays:
        s = shares.get(a.lot_id)
        if s is not None:
            loss += (1.0 - a.assay) * np.asarray(s, dtype=float)
    api = q * (1.0 - loss)
    return api, q - api


def content_deviation(
    fractions: np.ndarray, lots: Sequence[str], assays: Mapping[str, float]
) -> np.ndarray:
    """Eq. (2): the change of the API content (% w/w) of the product leaving at each tick
    caused by the lots of known assay (``assays``: lot -> fraction of label)."""
    out = np.zeros(fractions.shape[0])
    for j, lot in enumerate(lots):
        if lot in assays:
            out -= 100.0 * (1.0 - float(assays[lot])) * fractions[:, j]
    return out


def refills_from_events(events: Sequence[Any]) -> list[Any]:
    """The :class:`~twin_core.tracking.tracker.Refill` s of a list of ``schemas.messages.Event``
    (a ``refill_start`` and the next ``refill_stop`` of the same feeder; lot and mass from
    either)."""
    from twin_core.tracking.tracker import Refill

    open_: dict[str, tuple[float, str | None, float | None]] = {}
    out: list[Refill] = []
    for ev in sorted(events, key=lambda e: e.t):
        lot, mass = ev.lot_id, ev.mass_kg
        if ev.kind == "refill_start":
            open_[ev.source] = (float(ev.t), lot, mass)
        elif ev.kind == "refill_stop":
            t0, lot0, mass0 = open_.pop(ev.source, (float(ev.t), None, None))
            m = mass if mass is not None else mass0
            out.append(Refill(ev.source, t0, float(ev.t), lot or lot0, m))
    return out


def lot_assay_flows(
    t_s: np.ndarray,
    flows_kg_h: Mapping[str, np.ndarray],
    components: Mapping[str, str],
    hopper_kg: Mapping[str, np.ndarray],
    events: Sequence[Any],
    assays: Sequence[LotAssay],
    alpha: float = 0.0,
    initial_lots: Mapping[str, str | None] | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The plant's truth under lots of other assay (Eq. (1)): the feeders' delivered flows and
    components, where the API feeder delivers q_api and a new feeder ``<feeder>.inert`` (of the
    first other component) the inert rest. The lot shares of the discharge follow the hopper law
    with ``alpha`` (``twin_core.tracking.hopper``) on the measured hopper masses ``hopper_kg``
    and the refill ``events`` (``schemas.messages.Event``)."""
    from twin_core.tracking.tracker import track_lots

    comps = dict(components)
    for a in assays:
        if a.feeder not in comps:
            raise ValueError(f"lot assay feeder must be one of {sorted(comps)}, got {a.feeder!r}")
    t = np.asarray(t_s, dtype=float)
    dt = float(t[1] - t[0])
    flows = {f: np.asarray(v, dtype=float) for f, v in flows_kg_h.items()}
    trace = track_lots(
        t,
        flows,
        comps,
        [(0.0, np.array([1.0 / dt]))],
        refills_from_events(events),
        hopper_kg,
        alpha,
        initial_lots,
    )
    known = set(trace.lots)
    for a in assays:
        if a.lot_id not in known:
            raise ValueError(f"lot assay lot must be one of {sorted(known)}, got {a.lot_id!r}")
    for f in sorted({a.feeder for a in assays}):
        cols = [j for j, x in enumerate(trace.lot_feeder) if x == f]
        fed = trace.fed_kg_s[:, cols]
        tot = fed.sum(axis=1)
        shares = {
            trace.lots[j]: np.where(tot > 0, fed[:, k] / np.where(tot > 0, tot, 1.0), 0.0)
            for k, j in enumerate(cols)
        }
        api, inert = delivered_flows(flows[f], shares, [a for a in assays if a.feeder == f])
        others = [c for c in comps.values() if c != comps[f]]
        if not others:
            raise ValueError(f"lot assay of feeder {f!r} needs another component for the rest")
        flows[f] = api
        flows[f"{f}.inert"] = inert
        comps[f"{f}.inert"] = others[0]
    return flows, comps
