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


def section_rsd(
    net: CompartmentNetwork,
    c0: np.ndarray,
    t: np.ndarray,
    weighted: bool = False,
) -> np.ndarray:
    """RSD(t) across compartments (Eq. 2; holdup-weighted if ``weighted``)."""
    c = section_concentrations(net, c0, t)
    return rsd(c, weights=net.holdup if weighted else None, axis=1)


def grid_rsd_from_compartments(
    c: np.ndarray,
    labels: np.ndarray,
    holdup_cell: np.ndarray,
    coarse: np.ndarray,
    n_coarse: int,
    particles_per_kg: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Model counterpart of the DEM grid RSD (Eq. B.1) on coarse sampling cells.

    Each occupied cell takes its compartment's concentration; a coarse cell takes the
    holdup-weighted mean.  Returns (RSD without sampling noise, RSD with the binomial
    sampling variance c (1 - c) / N_cell of a finite particle sample added when
    ``particles_per_kg`` is given, else the same array).
    """
    hit = labels >= 0
    w = holdup_cell[hit]
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
