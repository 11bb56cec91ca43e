"""Raw-material lots at the blender outlet: the material-tracking model (ICH Q13 section 3.3).

Chain, per tick of dt:

1. each feeder's hopper (:class:`~twin_core.tracking.hopper.Hopper`) turns its measured
   discharge q_f dt into the mass d_{f,j} of each lot j it holds (plug flow, stirred heel or a
   mixture of both; refills put lots on top);
2. the blender distributes each tick's inlet mass of lot j over the following ticks with the
   E(t) in use when the mass entered (the blender's and the diverter's kernel,
   ``twin_core.online.blender.BlenderKernel``; one kernel per time segment when the twin
   adopts another one):

       y_j[n] = sum_k dt e_{s(n - k)}[k] u_j[n - k],    u_j = sum_f d_{f,j} / dt  [kg/s]   (1)

   with e_s normalised so that dt sum_k e_s[k] = 1 (Danckwerts 1953; Levenspiel 1999 ch. 11:
   the outlet of a linear vessel is the convolution of its inlet with E(t)). Between kernel
   switches Eq. (1) is the blender service's convolution (``StreamingConvolver``); across a
   switch each parcel keeps the E(t) it entered with, so every lot's mass leaves exactly once
   (the service's output-time switch changes only the first kernel length after a switch);
3. the outlet mass fraction of lot j is w_j[n] = y_j[n] / sum_i y_i[n] (of the product) and
   y_j[n] / sum_{i in c(j)} y_i[n] (of its component c(j)); both sum to one.

Mass balance, lot by lot and to rounding: mass in (initial hopper + refills) = hopper content +
blender content + mass out (:meth:`MaterialTracker.balance`).

:class:`MaterialTracker` is the streaming form (one :meth:`~MaterialTracker.push` per tick,
restart-safe with :meth:`~MaterialTracker.to_state` / :meth:`~MaterialTracker.from_state`);
:func:`track_lots` the offline form over arrays (FFT convolution per kernel segment), equal to
the streaming form to rounding.

References: ICH Q13 (2022) Continuous manufacturing of drug substances and drug products,
sections 3.3 (material traceability) and 3.1 (batch definition); Levenspiel, O. (1999)
Chemical Reaction Engineering, 3rd ed., ch. 11; Danckwerts, P.V. (1953) Chem. Eng. Sci. 2, 1.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from twin_core.tracking.hopper import Hopper

__all__ = [
    "LotTrace",
    "MaterialTracker",
    "Refill",
    "initial_lot_id",
    "normalised_kernel",
    "refill_lot_id",
    "track_lots",
]


def initial_lot_id(feeder: str, initial_lot: str | None = None) -> str:
    """The lot in feeder ``feeder``'s hopper at the start: the configured one, else
    ``<feeder>-L0000``."""
    return initial_lot or f"{feeder}-L0000"


def refill_lot_id(feeder: str, k: int) -> str:
    """The plant simulator's lot of the ``k``-th refill (1-based) of ``feeder``:
    ``<feeder>-L<k:04d>``; also the tracker's name of a refill event without ``lot_id``."""
    return f"{feeder}-L{k:04d}"


def normalised_kernel(e: np.ndarray, dt: float) -> np.ndarray:
    """E(t) on the tick grid scaled to dt sum(e) = 1 (every parcel leaves once)."""
    e = np.asarray(e, dtype=float)
    gain = dt * float(e.sum())
    if e.ndim != 1 or e.size == 0 or not np.all(np.isfinite(e)) or gain <= 0:
        raise ValueError(f"kernel must be a finite 1-D E(t) with dt*sum(e) > 0, got gain {gain!r}")
    return e / gain


@dataclass(frozen=True)
class Refill:
    """One hopper refill: lot ``lot_id`` of ``mass_kg`` (None: from the load cell) added to
    feeder ``feeder``'s hopper when the refill stops (``t_stop_s``)."""

    feeder: str
    t_start_s: float
    t_stop_s: float
    lot_id: str | None = None
    mass_kg: float | None = None


class MaterialTracker:
    """The material-tracking model, one tick at a time (module docstring).

    Args:
        components: feeder id -> component.
        dt_s: tick, s.
        e: E(t) in use on the tick grid (normalised here).
        alpha: the hopper's stirred share of the discharge (``twin_core.tracking.hopper``):
            one value, or one per feeder.
        initial_lots: feeder id -> lot in its hopper at the start (default
            :func:`initial_lot_id`).

    Feed refill events with :meth:`refill_start` / :meth:`refill_stop` as they come, then one
    :meth:`push` per tick with the feeders' measured flows and hopper masses. A new E(t)
    (:meth:`set_kernel`) applies to the mass entering from the next push on.
    """

    def __init__(
        self,
        components: Mapping[str, str],
        dt_s: float,
        e: np.ndarray,
        alpha: float | Mapping[str, float] = 0.0,
        initial_lots: Mapping[str, str | None] | None = None,
    ) -> None:
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
        self.dt = float(dt_s)
        self.components = dict(components)
        alphas = (
            {f: float(alpha) for f in self.components}
            if not isinstance(alpha, Mapping)
            else {f: float(alpha.get(f, 0.0)) for f in self.components}
        )
        for f, a in alphas.items():
            if not 0.0 <= a <= 1.0:
                raise ValueError(f"alpha of feeder {f} must be in [0, 1], got {a!r}")
        self.alphas = alphas
        #: lot names, their component and feeder, by index
        self.lots: list[str] = []
        self.lot_component: list[str] = []
        self.lot_feeder: list[str] = []
        self._index: dict[str, int] = {}
        #: kg of each lot put in (initial hopper + refills), discharged by the hopper, left
        self.mass_in = np.zeros(0)
        self._fed: list[float] = []
        self.mass_out = np.zeros(0)
        self._initial = {f: initial_lot_id(f, (initial_lots or {}).get(f)) for f in self.components}
        self.hoppers: dict[str, Hopper] = {}
        self._pending: dict[str, list[list[Any]]] = {f: [] for f in self.components}
        self._n_refills: dict[str, int] = {f: 0 for f in self.components}
        self.e = normalised_kernel(e, self.dt)
        self._buf = np.zeros((2 * self.e.size, 4))
        self._pos = 0
        self.n = 0
        self.t: float | None = None

    # ------------------------------------------------------------------ lots
    def lot_index(self, lot: str, feeder: str) -> int:
        """Index of ``lot`` (registered on first use, as a lot of ``feeder``'s component)."""
        i = self._index.get(lot)
        if i is not None:
            return i
        i = len(self.lots)
        self._index[lot] = i
        self.lots.append(lot)
        self.lot_feeder.append(feeder)
        self.lot_component.append(self.components[feeder])
        for name in ("mass_in", "mass_out"):
            setattr(self, name, np.append(getattr(self, name), 0.0))
        self._fed.append(0.0)
        if i >= self._buf.shape[1]:
            grown = np.zeros((self._buf.shape[0], 2 * self._buf.shape[1]))
            grown[:, : self._buf.shape[1]] = self._buf
            self._buf = grown
        return i

    # ------------------------------------------------------------------ inputs
    def refill_start(self, feeder: str, lot_id: str | None = None) -> str:
        """A refill of ``feeder`` starts, adding ``lot_id`` (None: :func:`refill_lot_id` of
        its count); returns the lot's name."""
        if feeder not in self.components:
            raise ValueError(f"feeder must be one of {sorted(self.components)}, got {feeder!r}")
        self._n_refills[feeder] += 1
        lot = lot_id or refill_lot_id(feeder, self._n_refills[feeder])
        self._pending[feeder].append([lot, None, False])
        return lot

    def refill_stop(self, feeder: str, mass_kg: float | None = None) -> None:
        """The refill of ``feeder`` stopped: its lot goes on top of the hopper at the next
        :meth:`push` (``mass_kg``, else what brings the model to the measured hopper mass)."""
        if feeder not in self.components:
            raise ValueError(f"feeder must be one of {sorted(self.components)}, got {feeder!r}")
        if not self._pending[feeder] or self._pending[feeder][-1][2]:
            self.refill_start(feeder)  # a stop without its start: an unnamed lot
        entry = self._pending[feeder][-1]
        entry[1], entry[2] = mass_kg, True

    def set_kernel(self, e: np.ndarray) -> None:
        """The E(t) in use from the next tick's inlet mass on."""
        self.e = normalised_kernel(e, self.dt)

    def push(
        self,
        t: float,
        flows_kg_h: Mapping[str, float],
        hopper_kg: Mapping[str, float] | None = None,
    ) -> np.ndarray:
        """One tick: the feeders' measured flows (kg/h) and hopper masses (kg, NaN unknown);
        returns the outlet mass flow of every lot (kg/s, indexed like :attr:`lots`)."""
        idx, val = self.feed(flows_kg_h, hopper_kg)
        if self.n == 0:
            self._prefill(idx, val)
        return self._blend(t, idx, val)

    def _prefill(self, idx: list[int], val: list[float]) -> None:
        """The blender full at the start, like the blender service's stream: the first tick's
        inlet taken as the inlet of every earlier tick (``StreamingConvolver``'s ``initial``),
        its mass counted in (the lots in the blender at the start)."""
        k = self.e.size
        tail = self.dt * (self.e[::-1].cumsum()[::-1])  # dt sum_{k' >= m} e[k']
        prior = np.concatenate([tail[1:], [0.0]])  # dt sum_{k' > m} e[k'], m = 0..K-1
        block = self._buf[self._pos : self._pos + k]
        for i, v in zip(idx, val):
            block[:, i] += prior * v
            self.mass_in[i] += float(prior.sum() * v * self.dt)

    def feed(
        self, flows_kg_h: Mapping[str, float], hopper_kg: Mapping[str, float] | None = None
    ) -> tuple[list[int], list[float]]:
        """The hoppers' part of a tick (step 1 of the module docstring): pending refills go
        in, each feeder discharges q dt; returns the inlet mass flow of each lot fed (lot
        indices, kg/s). :meth:`push` calls it; alone it leaves the blender out."""
        hopper_kg = hopper_kg or {}
        dt = self.dt
        u_idx: list[int] = []
        u_val: list[float] = []
        isfinite = math.isfinite
        for f in self.components:
            measured = float(hopper_kg.get(f, math.nan))
            if f not in self.hoppers:
                lot = self.lot_index(self._initial[f], f)
                m0 = measured if np.isfinite(measured) and measured > 0 else 0.0
                self.hoppers[f] = Hopper(lot, m0, self.alphas[f])
                self.mass_in[lot] += m0
            hop = self.hoppers[f]
            pending = self._pending[f]
            while pending and pending[0][2]:  # refills that stopped
                name, mass, _ = pending.pop(0)
                lot = self.lot_index(name, f)
                if mass is None:
                    mass = measured - hop.mass_kg if isfinite(measured) else 0.0
                mass = max(float(mass), 0.0)
                hop.refill(lot, mass)
                self.mass_in[lot] += mass
            q = float(flows_kg_h.get(f, 0.0))
            q = q if isfinite(q) and q > 0 else 0.0
            before = hop.overdraw_kg
            for lot, kg in hop.discharge(q / 3600.0 * dt):
                u_idx.append(lot)
                u_val.append(kg / dt)
                self._fed[lot] += kg
            if hop.overdraw_kg != before:
                self.mass_in[hop.newest] += hop.overdraw_kg - before
        return u_idx, u_val

    def _blend(self, t: float, idx: list[int], val: list[float]) -> np.ndarray:
        """Eq. (1): scatter this tick's inlet over the coming ticks, return this tick's outlet."""
        k = self.e.size
        if self._pos + k > self._buf.shape[0]:
            rows = max(self._buf.shape[0], 2 * k)
            grown = np.zeros((rows, self._buf.shape[1]))
            rest = self._buf[self._pos :]
            grown[: rest.shape[0]] = rest
            self._buf, self._pos = grown, 0
        if idx:
            w = self.e * self.dt
            block = self._buf[self._pos : self._pos + k]
            for i, v in zip(idx, val):
                block[:, i] += w * v
        y = self._buf[self._pos, : len(self.lots)].copy()
        self._buf[self._pos] = 0.0
        self._pos += 1
        self.mass_out += y * self.dt
        self.n += 1
        self.t = float(t)
        return y

    # ------------------------------------------------------------------ outputs
    @property
    def mass_fed(self) -> np.ndarray:
        """kg of each lot the hoppers discharged."""
        return np.asarray(self._fed, dtype=float)

    def blender_content(self) -> np.ndarray:
        """kg of each lot in the blender (inlet mass not yet out)."""
        return self._buf[self._pos :, : len(self.lots)].sum(axis=0) * self.dt

    def hopper_content(self) -> np.ndarray:
        """kg of each lot in the hoppers."""
        out = np.zeros(len(self.lots))
        for hop in self.hoppers.values():
            for lot, kg in hop.layers:
                out[int(lot)] += kg
        return out

    def balance(self) -> np.ndarray:
        """Per lot: mass in - (hopper + blender content + mass out), kg (0 to rounding)."""
        return self.mass_in - (self.hopper_content() + self.blender_content() + self.mass_out)

    # ------------------------------------------------------------------ persistence
    def to_state(self) -> dict[str, Any]:
        """JSON-able state: enough to resume exactly after a restart."""
        return {
            "dt": self.dt,
            "components": self.components,
            "alphas": self.alphas,
            "initial": self._initial,
            "lots": self.lots,
            "lot_feeder": self.lot_feeder,
            "mass_in": self.mass_in.tolist(),
            "mass_fed": self.mass_fed.tolist(),
            "mass_out": self.mass_out.tolist(),
            "hoppers": {f: h.to_state() for f, h in self.hoppers.items()},
            "pending": self._pending,
            "n_refills": self._n_refills,
            "e": self.e.tolist(),
            "blender": self._buf[self._pos :, : len(self.lots)].tolist(),
            "n": self.n,
            "t": self.t,
        }

    @classmethod
    def from_state(cls, state: Mapping[str, Any]) -> MaterialTracker:
        """Rebuild a tracker saved by :meth:`to_state`."""
        obj = cls(
            state["components"],
            float(state["dt"]),
            np.asarray(state["e"], float),
            dict(state["alphas"]),
            dict(state["initial"]),
        )
        for lot, feeder in zip(state["lots"], state["lot_feeder"]):
            obj.lot_index(lot, feeder)
        for name in ("mass_in", "mass_out"):
            setattr(obj, name, np.asarray(state[name], float))
        obj._fed = [float(x) for x in state["mass_fed"]]
        obj.hoppers = {f: Hopper.from_state(h) for f, h in state["hoppers"].items()}
        obj._pending = {f: [list(p) for p in v] for f, v in state["pending"].items()}
        obj._n_refills = {f: int(v) for f, v in state["n_refills"].items()}
        rows = np.asarray(state["blender"], float).reshape(-1, len(obj.lots))
        obj._buf = np.zeros((max(2 * obj.e.size, 2 * rows.shape[0]), obj._buf.shape[1]))
        obj._buf[: rows.shape[0], : len(obj.lots)] = rows
        obj._pos = 0
        obj.n = int(state["n"])
        obj.t = state["t"]
        return obj


@dataclass
class LotTrace:
    """Result of :func:`track_lots`: the outlet mass flow of every lot on the tick grid.

    ``outlet_kg_s[n, j]``: lot j's mass flow at the outlet at ``t_s[n]``; ``fed_kg_s``: at the
    blender inlet (the hoppers' discharge); ``lots``, ``lot_component``, ``lot_feeder`` name
    the columns; ``mass_in_kg`` per lot; ``overdraw_kg`` per feeder.
    """

    t_s: np.ndarray
    lots: list[str]
    lot_component: list[str]
    lot_feeder: list[str]
    outlet_kg_s: np.ndarray
    fed_kg_s: np.ndarray
    mass_in_kg: np.ndarray
    overdraw_kg: dict[str, float] = field(default_factory=dict)

    def fractions(self) -> np.ndarray:
        """Mass fraction of each lot in the product leaving at each tick (rows sum to 1 where
        anything leaves, 0 elsewhere)."""
        total = self.outlet_kg_s.sum(axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(total > 0, self.outlet_kg_s / np.where(total > 0, total, 1.0), 0.0)

    def component_fractions(self) -> np.ndarray:
        """Mass fraction of each lot within its component's mass at each tick."""
        out = np.zeros_like(self.outlet_kg_s)
        for c in sorted(set(self.lot_component)):
            cols = [j for j, x in enumerate(self.lot_component) if x == c]
            sub = self.outlet_kg_s[:, cols]
            tot = sub.sum(axis=1, keepdims=True)
            out[:, cols] = np.where(tot > 0, sub / np.where(tot > 0, tot, 1.0), 0.0)
        return out

    def column(self, lot: str) -> int:
        try:
            return self.lots.index(lot)
        except ValueError:
            raise ValueError(f"lot must be one of {self.lots}, got {lot!r}") from None


def track_lots(
    t_s: np.ndarray,
    flows_kg_h: Mapping[str, np.ndarray],
    components: Mapping[str, str],
    kernels: Sequence[tuple[float, np.ndarray]],
    refills: Sequence[Refill] = (),
    hopper_kg: Mapping[str, np.ndarray] | None = None,
    alpha: float | Mapping[str, float] = 0.0,
    initial_lots: Mapping[str, str | None] | None = None,
) -> LotTrace:
    """The material-tracking model over a whole record (module docstring, Eq. (1)).

    Args:
        t_s: the tick grid (uniform, step dt).
        flows_kg_h: feeder id -> measured mass flow on the grid, kg/h.
        components: feeder id -> component.
        kernels: (plant time from which it applies, E(t) on the tick grid), in time order; the
            first applies from the start whatever its time.
        refills: the refills (lots added when each stops, at the first tick >= ``t_stop_s``).
        hopper_kg: feeder id -> measured hopper mass on the grid (None or NaN: unknown).
        alpha: the hoppers' stirred share (``twin_core.tracking.hopper``).
        initial_lots: feeder id -> lot in the hopper at the start.

    The hoppers run tick by tick (:class:`MaterialTracker`'s own law); the blender is one FFT
    convolution per kernel segment and lot.
    """
    from scipy.signal import fftconvolve

    t = np.asarray(t_s, dtype=float)
    n = t.size
    if n < 2:
        raise ValueError(f"t_s must have >= 2 ticks, got {n}")
    dt = float(t[1] - t[0])
    if not kernels:
        raise ValueError("kernels must hold at least one E(t), got none")
    tr = MaterialTracker(components, dt, kernels[0][1], alpha, initial_lots)
    by_feeder: dict[str, list[Refill]] = {f: [] for f in components}
    for r in sorted(refills, key=lambda r: r.t_stop_s):
        if r.feeder not in by_feeder:
            raise ValueError(f"refill feeder must be one of {sorted(components)}, got {r.feeder!r}")
        by_feeder[r.feeder].append(r)
    nexts = {f: 0 for f in components}
    flows = {f: np.asarray(flows_kg_h[f], dtype=float).tolist() for f in components}
    hops = {
        f: np.asarray((hopper_kg or {}).get(f, np.full(n, np.nan)), float).tolist()
        for f in components
    }
    tl = t.tolist()
    rows: list[tuple[int, int, float]] = []
    eps = 1e-9 * dt
    names = list(components)
    for i in range(n):
        ti = tl[i]
        for f in names:
            lst = by_feeder[f]
            while nexts[f] < len(lst) and lst[nexts[f]].t_stop_s <= ti + eps:
                r = lst[nexts[f]]
                tr.refill_start(f, r.lot_id)
                tr.refill_stop(f, r.mass_kg)
                nexts[f] += 1
        u_idx, u_val = tr.feed({f: flows[f][i] for f in names}, {f: hops[f][i] for f in names})
        rows.extend((i, j, v) for j, v in zip(u_idx, u_val))
    n_lots = len(tr.lots)
    fed = np.zeros((n, n_lots))
    for i, j, v in rows:
        fed[i, j] += v
    out = np.zeros((n, n_lots))
    mass_in = tr.mass_in.copy()
    starts = [0] + [int(np.searchsorted(t, ts - eps)) for ts, _ in kernels[1:]]
    ends = starts[1:] + [n]
    for (_, e), a, b in zip(kernels, starts, ends):
        if b <= a:
            continue
        w = normalised_kernel(e, dt) * dt
        seg = fed[a:b]
        live = np.nonzero(seg.any(axis=0))[0]
        if live.size == 0:
            continue
        conv = fftconvolve(seg[:, live], w[:, None], axes=0)[: n - a]
        # FFT rounding (~1e-16 of a lot's inlet times the kernel's peak) is no lot: zero it
        conv[conv < 1e-12 * seg[:, live].max(axis=0, keepdims=True) * w.max()] = 0.0
        out[a : a + conv.shape[0], live] += conv
        if a == 0:  # the blender full at the start (MaterialTracker._prefill)
            w0 = w
            tail = np.concatenate([w0[::-1].cumsum()[::-1][1:], [0.0]])[:n]
            for j in np.nonzero(fed[0])[0]:
                out[: tail.size, j] += tail * fed[0, j]
                mass_in[j] += float(tail.sum() * fed[0, j] * dt)
    return LotTrace(
        t_s=t,
        lots=list(tr.lots),
        lot_component=list(tr.lot_component),
        lot_feeder=list(tr.lot_feeder),
        outlet_kg_s=out,
        fed_kg_s=fed,
        mass_in_kg=mass_in,
        overdraw_kg={f: h.overdraw_kg for f, h in tr.hoppers.items()},
    )
