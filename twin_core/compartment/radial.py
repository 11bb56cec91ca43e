"""Radial mixing of the closed periodic section: RSD across compartments vs time.

The section is closed (no feed): an initial tracer pattern (the seed's two particle types
placed on either side of the section, 5.2.1) relaxes under dm/dt = A m.  The RSD is chapter 5
Eq. (2) over the compartments; for a conserving network it decays to 0 (uniform stationary
concentration, the holdup-proportional stationary law of the Markov chain), while the
seed's non-conserving Eq. (1) flows leave a non-uniform steady state (an RSD plateau).
"""

from __future__ import annotations

import numpy as np

from twin_core.compartment.fields import GridFields
from twin_core.compartment.grid_index import cell_index
from twin_core.compartment.network import CompartmentNetwork, closed_network, rsd


def split_initial(
    fields: GridFields, labels: np.ndarray, axis: int = 1, position: float | None = None
) -> np.ndarray:
    """Initial compartment concentrations of a two-type split along ``axis``.

    Cells with centre below ``position`` (default: the middle of the domain) hold tracer
    (c = 1), the others none; a compartment's concentration is the holdup-weighted mean of
    its cells.
    """
    if axis not in (0, 1, 2):
        raise ValueError(f"axis must be 0, 1 or 2, got {axis}")
    e = fields.edges[axis]
    pos = 0.5 * (e[0] + e[-1]) if position is None else position
    c_cell = (np.meshgrid(*fields.centers, indexing="ij")[axis] < pos).astype(float)
    n = int(labels.max()) + 1
    hit = labels >= 0
    w = fields.holdup_kg[hit]
    m = np.bincount(labels[hit], weights=w, minlength=n)
    tr = np.bincount(labels[hit], weights=w * c_cell[hit], minlength=n)
    return np.divide(tr, m, out=np.zeros(n), where=m > 0)


def section_concentrations(net: CompartmentNetwork, c0: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Compartment concentrations (len(t), n) of the closed section from c(0) = c0."""
    closed = closed_network(net)
    m = closed.states(np.asarray(t, dtype=float), np.asarray(c0, float) * closed.holdup)
    return m / closed.holdup[None, :]


def flowing(net: CompartmentNetwork) -> np.ndarray:
    """Compartments with any flow in or out (stagnant, isolated ones never mix)."""
    used = np.zeros(net.n, dtype=bool)
    used[net.src] = True
    used[net.dst] = True
    return used


def section_rsd(
    net: CompartmentNetwork,
    c0: np.ndarray,
    t: np.ndarray,
    weighted: bool = False,
) -> np.ndarray:
    """RSD(t) across the flowing compartments (Eq. 2; holdup-weighted if ``weighted``).

    Compartments without any flow (a stagnant pocket, or cells a short DEM run saw occupied
    but never crossed) keep their initial concentration for ever and are left out.
    """
    c = section_concentrations(net, c0, t)
    use = flowing(net)
    return rsd(c[:, use], weights=net.holdup[use] if weighted else None, axis=1)


def grid_rsd_from_compartments(
    c: np.ndarray,
    labels: np.ndarray,
    holdup_cell: np.ndarray,
    coarse: np.ndarray,
    n_coarse: int,
    particles_per_kg: float | None = None,
    active: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Model counterpart of the DEM grid RSD (Eq. B.1) on coarse sampling cells.

    Each occupied cell takes its compartment's concentration; a coarse cell takes the
    holdup-weighted mean.  Returns (RSD without sampling noise, RSD with the binomial
    sampling variance c (1 - c) / N_cell of a finite particle sample added when
    ``particles_per_kg`` is given, else the same array).  ``active`` (bool per compartment,
    e.g. :func:`flowing`) leaves the cells of inactive compartments out.
    """
    hit = labels >= 0
    w = holdup_cell[hit]
    if active is not None:
        w = w * np.asarray(active, dtype=bool)[labels[hit]]
    cc = coarse
    mass = np.bincount(cc, weights=w, minlength=n_coarse)
    ok = mass > 0
    out, out_s = [], []
    for ck in np.atleast_2d(c):
        conc = np.bincount(cc, weights=w * ck[labels[hit]], minlength=n_coarse)[ok] / mass[ok]
        mean = conc.mean()
        var = conc.var(ddof=1)
        out.append(np.sqrt(var) / mean)
        if particles_per_kg is not None:
            npart = mass[ok] * particles_per_kg
            samp = np.mean(conc * (1 - conc) / np.maximum(npart, 1.0))
            out_s.append(np.sqrt(var + samp) / mean)
    r = np.asarray(out)
    return r, (np.asarray(out_s) if particles_per_kg is not None else r)


def grid_rsd_from_positions(
    positions: np.ndarray,
    is_tracer: np.ndarray,
    fields: GridFields,
    bins: tuple[int, int, int] = (10, 6, 6),
    min_count: int = 1,
) -> float:
    """DEM grid RSD of one particle snapshot (seed Eq. B.1): tracer fraction per sampling cell
    of a ``bins`` grid spanning the field box (periodic axes wrapped into it), RSD over cells
    holding at least ``min_count`` particles."""
    pos = np.asarray(positions, dtype=float)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions must have shape (n, 3), got {pos.shape}")
    idx = []
    for axis, nb in enumerate(bins):
        lo, hi = fields.edges[axis][0], fields.edges[axis][-1]
        x = pos[:, axis]
        if fields.periodic[axis]:
            x = lo + np.mod(x - lo, hi - lo)
        idx.append(np.clip(((x - lo) / (hi - lo) * nb).astype(np.int64), 0, nb - 1))
    flat = (idx[0] * bins[1] + idx[1]) * bins[2] + idx[2]
    n = int(np.prod(bins))
    tot = np.bincount(flat, minlength=n)
    tr = np.bincount(flat, weights=np.asarray(is_tracer, dtype=float), minlength=n)
    ok = tot >= min_count
    if ok.sum() < 2:
        return float("nan")
    c = tr[ok] / tot[ok]
    return float(np.std(c, ddof=1) / np.mean(c)) if c.mean() > 0 else float("nan")


def grid_rsd_sampled(
    c: np.ndarray,
    labels: np.ndarray,
    occupancy: np.ndarray,
    coarse: np.ndarray,
    n_coarse: int,
    seed: int | np.random.Generator | None = None,
    n_samples: int = 20,
    active: np.ndarray | None = None,
    min_count: int = 1,
) -> np.ndarray:
    """Model counterpart of a DEM grid RSD (Eq. B.1) for sparse particle samples.

    For each time, ``n_samples`` particle snapshots are drawn: Poisson particle counts per
    occupied cell with the mean ``occupancy``, each particle a tracer with the probability
    given by its compartment's concentration; the RSD over sampling cells holding at least
    ``min_count`` particles is averaged over the snapshots.  Unlike the binomial-floor
    formula this is right when cells hold a particle or less on average.
    """
    rng = np.random.default_rng(seed)
    hit = labels >= 0
    lab = labels[hit]
    occ = occupancy[hit].astype(float)
    if active is not None:
        occ = occ * np.asarray(active, dtype=bool)[lab]
    out = np.empty(np.atleast_2d(c).shape[0])
    for k, ck in enumerate(np.atleast_2d(c)):
        p = np.clip(ck[lab], 0.0, 1.0)
        vals = []
        for _ in range(n_samples):
            n = rng.poisson(occ)
            nt = rng.binomial(n, p)
            tot = np.bincount(coarse, weights=n, minlength=n_coarse)
            tr = np.bincount(coarse, weights=nt, minlength=n_coarse)
            ok = tot >= min_count
            if ok.sum() > 1:
                cc = tr[ok] / tot[ok]
                if cc.mean() > 0:
                    vals.append(np.std(cc, ddof=1) / cc.mean())
        out[k] = float(np.mean(vals)) if vals else float("nan")
    return out


def cell_index_of_positions(positions: np.ndarray, fields: GridFields) -> np.ndarray:
    """Flat cell index (C order over (nx, ny, nz)) of particle positions; periodic axes are
    wrapped into the box, positions outside a closed axis are clipped to its end cells."""
    return cell_index(positions, fields.edges, fields.periodic)[0]


def initial_from_particles(
    positions: np.ndarray, is_tracer: np.ndarray, fields: GridFields, labels: np.ndarray
) -> np.ndarray:
    """Compartment concentrations from a particle snapshot: the tracer fraction of the
    particles found in each compartment (the overall fraction where none is found)."""
    cell = cell_index_of_positions(positions, fields)
    lab = labels.ravel()[cell]
    ok = lab >= 0
    n = int(labels.max()) + 1
    tot = np.bincount(lab[ok], minlength=n).astype(float)
    tr = np.bincount(lab[ok], weights=np.asarray(is_tracer, float)[ok], minlength=n)
    mean = float(np.mean(is_tracer))
    return np.where(tot > 0, tr / np.maximum(tot, 1.0), mean)
