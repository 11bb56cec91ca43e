"""Particle-tracking surrogate of DEM: a Markov-chain random walk on the grid cells.

Until DEM transit times are available, the compartment model is validated against a
stochastic particle simulation whose law is known exactly.  Each occupied grid cell is a
state; a particle in cell i jumps to neighbour j at rate F_ij / M_i (F_ij the cell-face mass
flow from the crossing counts, M_i the cell holdup) -- the continuous-time Markov chain whose
forward (Kolmogorov) equation is the cell-level tracer balance (Norris, *Markov Chains*,
1997, ch. 2-3).  Its transit-time RTD across one section is therefore known exactly:
:func:`~twin_core.compartment.network.first_passage_network` of the cell-level network.

The walk is sampled with the Gillespie (1977, J. Phys. Chem. 81, 2340) algorithm:
exponential holding times and jump targets drawn in proportion to the rates.
"""

from __future__ import annotations

import numpy as np

from twin_core.compartment.fields import GridFields
from twin_core.compartment.flows import Flows, aggregate_flows
from twin_core.compartment.network import CompartmentNetwork, _wrap_directions


def cell_network(
    fields: GridFields, flows: Flows, mask: np.ndarray, axial_axis: int = 0
) -> tuple[CompartmentNetwork, np.ndarray]:
    """Every occupied cell as its own compartment.  Returns (periodic network, labels)."""
    labels = np.full(fields.shape, -1, dtype=np.int32)
    labels[mask] = np.arange(int(mask.sum()), dtype=np.int32)
    g = aggregate_flows(flows, labels, fields.periodic, axial_axis=axial_axis)
    idx = np.indices(fields.shape)[axial_axis][mask]
    grids = np.meshgrid(*fields.centers, indexing="ij")
    net = CompartmentNetwork(
        holdup=fields.holdup_kg[mask],
        src=g.src,
        dst=g.dst,
        rate=g.rate,
        wrap=g.wrap,
        slice_index=idx,
        centroid=np.stack([gr[mask] for gr in grids], axis=1),
    )
    return net, labels


class _Chain:
    """CSR jump table of a periodic network: per node, cumulative rates and wrap offsets."""

    def __init__(self, net: CompartmentNetwork) -> None:
        n = net.n
        fwd, bwd = _wrap_directions(net)
        order = np.argsort(net.src, kind="stable")
        self.src = net.src[order]
        self.dst = net.dst[order]
        self.off = (fwd.astype(np.int64) - bwd.astype(np.int64))[order]
        rate = net.rate[order] / net.holdup[self.src]
        self.ptr = np.concatenate([[0], np.cumsum(np.bincount(self.src, minlength=n))])
        self.cum = np.cumsum(rate)
        self.total = np.bincount(self.src, weights=rate, minlength=n)
        # mean holding time 1 / total rate; a node without way out holds forever
        self.mean_hold = np.full(n, np.inf)
        np.divide(1.0, self.total, out=self.mean_hold, where=self.total > 0)
        self.entry = np.bincount(net.dst[fwd], weights=net.rate[fwd], minlength=n)

    def jump(self, state: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        base = np.where(self.ptr[state] > 0, self.cum[np.maximum(self.ptr[state] - 1, 0)], 0.0)
        target = base + rng.random(state.size) * self.total[state]
        e = np.searchsorted(self.cum, target, side="right")
        e = np.clip(e, self.ptr[state], self.ptr[state + 1] - 1)
        return self.dst[e], self.off[e]


def walk_transit_times(
    net: CompartmentNetwork,
    n_particles: int,
    seed: int | np.random.Generator | None = None,
    max_time: float | None = None,
    burn_in: int = 2,
) -> np.ndarray:
    """Transit times (s) across one section length, as the DEM transit sensor measures them.

    A walker's unwrapped axial position advances by one period at each forward crossing of
    the periodic face and goes back one at each backward crossing.  A *record* passage is the
    first time it reaches a new multiple of the period; a transit time is the time between
    two successive record passages (backflow included), the definition of the DEM
    ``PeriodicTransitSensor``.  Walkers start at the flux-weighted forward crossings; the
    first ``burn_in`` transits of each walker are discarded so that the entry state follows
    the stationary record-passage law, and the next one is returned (one per walker, so the
    samples are independent).  Walkers not done by ``max_time`` (default 50 x V/Q per
    transit) are returned as ``inf``.
    """
    if n_particles < 1:
        raise ValueError(f"n_particles must be >= 1, got {n_particles}")
    if burn_in < 0:
        raise ValueError(f"burn_in must be >= 0, got {burn_in}")
    rng = np.random.default_rng(seed)
    ch = _Chain(net)
    if ch.entry.sum() <= 0:
        raise ValueError("network has no forward flow through the periodic face")
    fwd, bwd = _wrap_directions(net)
    q = net.rate[fwd].sum() - net.rate[bwd].sum()
    if q <= 0:
        raise ValueError(f"net flow through the periodic face must be > 0, got {q}")
    if max_time is None:
        max_time = 50.0 * (burn_in + 1) * net.total_holdup / q
    p = ch.entry / ch.entry.sum()
    state = rng.choice(net.n, size=n_particles, p=p)
    offset = np.zeros(n_particles, dtype=np.int64)
    best = np.zeros(n_particles, dtype=np.int64)
    time = np.zeros(n_particles)
    t_rec = np.zeros(n_particles)
    out = np.full(n_particles, np.inf)
    alive = np.arange(n_particles)
    while alive.size:
        s = state[alive]
        time[alive] += rng.exponential(1.0, alive.size) * ch.mean_hold[s]
        nxt, off = ch.jump(s, rng)
        offset[alive] += off
        state[alive] = nxt
        idx = alive[offset[alive] > best[alive]]  # record passages
        best[idx] = offset[idx]
        last = best[idx] == burn_in + 1
        out[idx[last]] = time[idx[last]] - t_rec[idx[last]]
        t_rec[idx] = time[idx]
        keep = np.isinf(out[alive]) & (time[alive] <= max_time)
        alive = alive[keep]
    return out


def walk_snapshots(
    net: CompartmentNetwork,
    start: np.ndarray,
    times: np.ndarray,
    seed: int | np.random.Generator | None = None,
) -> np.ndarray:
    """Node of every walker at each of ``times`` (closed periodic section, no outlet).

    ``start`` holds the starting node of each walker.  Returns (len(times), n_walkers).
    """
    rng = np.random.default_rng(seed)
    ch = _Chain(net)
    times = np.asarray(times, dtype=float)
    if np.any(np.diff(times) < 0):
        raise ValueError("times must be non-decreasing")
    state = np.asarray(start, dtype=np.int64).copy()
    t_next = rng.exponential(1.0, state.size) * ch.mean_hold[state]
    out = np.empty((times.size, state.size), dtype=np.int64)
    for k, T in enumerate(times):
        moving = np.flatnonzero(t_next <= T)
        while moving.size:
            nxt, _ = ch.jump(state[moving], rng)
            state[moving] = nxt
            t_next[moving] += rng.exponential(1.0, moving.size) * ch.mean_hold[nxt]
            moving = moving[t_next[moving] <= T]
        out[k] = state
    return out


def coarse_index(fields: GridFields, mask: np.ndarray, bins: tuple[int, int, int]) -> np.ndarray:
    """Coarse sampling-cell index (0..prod(bins)-1) of every occupied cell (seed B.1: 10x6x6)."""
    idx = []
    for axis, nb in enumerate(bins):
        e = fields.edges[axis]
        c = fields.centers[axis]
        ce = np.linspace(e[0], e[-1], nb + 1)
        idx.append(np.clip(np.searchsorted(ce, c, side="right") - 1, 0, nb - 1))
    ii, jj, kk = np.meshgrid(*idx, indexing="ij")
    flat = (ii * bins[1] + jj) * bins[2] + kk
    return flat[mask]


def grid_rsd_from_particles(
    node_of_particle: np.ndarray,
    is_tracer: np.ndarray,
    node_coarse: np.ndarray,
    n_coarse: int,
    min_count: int = 1,
) -> np.ndarray:
    """DEM-style grid RSD (seed Eq. B.1) per snapshot from particle positions and types.

    ``node_of_particle`` (nt, N) node of each particle; the concentration of a coarse cell is
    its fraction of tracer particles; cells with fewer than ``min_count`` particles are skipped.
    """
    out = np.empty(node_of_particle.shape[0])
    for k, nodes in enumerate(node_of_particle):
        cc = node_coarse[nodes]
        tot = np.bincount(cc, minlength=n_coarse)
        tr = np.bincount(cc, weights=is_tracer.astype(float), minlength=n_coarse)
        ok = tot >= min_count
        c = tr[ok] / tot[ok]
        out[k] = np.std(c, ddof=1) / np.mean(c) if ok.sum() > 1 and c.mean() > 0 else np.nan
    return out
