"""Distance based mixing indices of seed section 4.3.1 (AH, NDM, SM).

Particle arrays of a frame must be aligned with those of the reference (initial) frame
(same particle in the same row); :func:`twin_core.mixing.series.compute_indices` aligns by id.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from twin_core.mixing.neighbours import minimum_image_distance


def average_height(
    coord: np.ndarray,
    types: np.ndarray,
    tracer: int,
    origin: float = 0.0,
    weights: np.ndarray | None = None,
) -> float:
    """AH = mean height of tracer particles / mean height of all particles (seed Eq. 28).

    ``coord``: positions along the chosen axis; heights are measured from ``origin`` (the
    container floor). 1 when mixed along that axis. The seed's Eq. (28) places 1/N_red outside
    the ratio; the intended quantity (text of 4.3.1.15 and the original, Deen et al. 2010) is
    the ratio of the two mean heights used here. ``weights`` (particle volumes): the ratio of
    the two centres of volume, for polydisperse beds.
    """
    h = np.asarray(coord, float) - origin
    sel = np.asarray(types) == tracer
    if not sel.any():
        raise ValueError(f"no particle of tracer type {tracer}")
    if weights is None:
        mean_all = h.sum() / len(h)
        mean_tracer = h[sel].sum() / np.count_nonzero(sel)
    else:
        w = np.asarray(weights, float)
        mean_all = np.sum(w * h) / w.sum()
        mean_tracer = np.sum(w[sel] * h[sel]) / w[sel].sum()
    if mean_all == 0:
        raise ValueError("mean height of all particles is zero: choose an origin below the bed")
    return float(mean_tracer / mean_all)


def centroid(positions: np.ndarray, weights: np.ndarray | None = None, box=None) -> np.ndarray:
    """(Weighted) centre of the positions; on periodic axes the circular mean (positions as
    angles on the period's circle), which does not depend on where the box is cut.
    Reference: Bai & Breen, J. Graphics Tools 13 (2008) 53 (centre of mass with periodic
    boundaries)."""
    pos = np.asarray(positions, float)
    w = np.ones(len(pos)) if weights is None else np.asarray(weights, float)
    if weights is None:
        out = pos.sum(axis=0) / len(pos)
    else:
        out = np.sum(w[:, None] * pos, axis=0) / w.sum()
    period = _box_array(box)
    for ax in np.flatnonzero(period > 0):
        angle = 2 * math.pi * pos[:, ax] / period[ax]
        mean = math.atan2(np.sum(w * np.sin(angle)), np.sum(w * np.cos(angle)))
        out[ax] = np.mod(mean, 2 * math.pi) * period[ax] / (2 * math.pi)
    return out


def spreading_radius(positions: np.ndarray, weights: np.ndarray | None = None, box=None) -> float:
    """Mean distance of the particles from their centroid (minimum image on periodic axes;
    volume-weighted with ``weights``)."""
    pos = np.asarray(positions, float)
    c = centroid(pos, weights, box)
    d = minimum_image_distance(c, pos, box)
    if weights is None:
        return float(d.sum() / len(d))
    w = np.asarray(weights, float)
    return float(np.sum(w * d) / w.sum())


def sphere_spreading_index(
    positions: np.ndarray,
    types: np.ndarray,
    tracer: int,
    radius0: float,
    weights: np.ndarray | None = None,
    box=None,
) -> float:
    """Sphere spreading index: ``SSI = (R_A - R_A,0) / (R - R_A,0)``.

    ``R_A`` is the mean distance of the tracer particles from their centroid (the radius of the
    "sphere" they fill), ``R`` the same for all particles, ``R_A,0 = radius0`` the tracer's at
    the reference (initial) frame. 0 initially; 1 once the tracer is spread over the bed as
    widely as the bed itself, whatever its shape; a tracer cut into a thin shell can overshoot
    1. A uniform ball of radius ``a`` has ``R = 3 a / 4``. ``weights``: volume weighting.

    Reference: Füvesi, Goniva, Luding & Magnanimo, "Mixing indices in up-scaled simulations",
    Powder Technol. (2025) 120775, doi:10.1016/j.powtec.2025.120775. The definition is the one
    of the authors' published code (``SphereSpreadingMethod`` in ``mixingIndices.py`` of the
    repository accompanying the paper); the paper's own text was not available to check it.
    """
    sel = np.asarray(types) == tracer
    if not sel.any():
        raise ValueError(f"no particle of tracer type {tracer}")
    pos = np.asarray(positions, float)
    w = None if weights is None else np.asarray(weights, float)
    r_a = spreading_radius(pos[sel], None if w is None else w[sel], box)
    r_all = spreading_radius(pos, w, box)
    if r_all == radius0:
        raise ValueError("the bed is no wider than the initial tracer: SSI undefined")
    return float((r_a - radius0) / (r_all - radius0))


def neighbour_distance_index(
    positions: np.ndarray,
    neighbour_pairs: np.ndarray,
    random_pairs: np.ndarray,
    contact_distance: float,
    box: np.ndarray | None = None,
) -> float:
    """NDM = (<d_ij> - d_p) / (<d_ik> - d_p) (seed Eq. 20 with means, as in the original).

    ``neighbour_pairs``: pairs in contact in the initial frame; ``random_pairs``: pairs drawn at
    random once; ``d_p``: initial contact distance. 0 initially, ~1 once initial neighbours are
    as far apart as random pairs.
    Reference: Deen et al., Chem. Eng. Sci. 65 (2010) 1 ("neighbour distance method"); the seed's
    Eq. (20) writes sums where the original compares mean distances.
    """
    d_nb = pair_distances(positions, neighbour_pairs, box)
    d_rand = pair_distances(positions, random_pairs, box)
    denom = d_rand.mean() - contact_distance
    if denom <= 0:
        raise ValueError("random pairs are not farther apart than the contact distance")
    return float((d_nb.mean() - contact_distance) / denom)


@njit(cache=True, inline="always")
def _dist(p, q, i, j, box):
    s = 0.0
    for a in range(3):
        d = q[j, a] - p[i, a]
        L = box[a]
        if L > 0.0:
            d -= L * np.rint(d / L)
        s += d * d
    return math.sqrt(s)


@njit(cache=True)
def _pair_distances(pos, pairs, box):
    """Minimum-image distance of each pair ``(i, j)`` (``box``: period per axis, 0 = none)."""
    out = np.empty(pairs.shape[0])
    for k in range(pairs.shape[0]):
        out[k] = _dist(pos, pos, pairs[k, 0], pairs[k, 1], box)
    return out


def pair_distances(positions: np.ndarray, pairs: np.ndarray, box=None) -> np.ndarray:
    """Centre distance of each pair ``(i, j)``, minimum image on periodic axes."""
    return _pair_distances(
        np.ascontiguousarray(positions, dtype=np.float64),
        np.ascontiguousarray(pairs, dtype=np.int64),
        _box_array(box),
    )


@njit(cache=True, parallel=True)
def _siiria_exact(pos0, pos, box, log_r_g):
    n = pos0.shape[0]
    partial = np.zeros(n)
    for i in prange(n):
        acc = 0.0
        for j in range(i + 1, n):
            d0 = _dist(pos0, pos0, i, j, box)
            dk = _dist(pos, pos, i, j, box)
            acc += math.exp(log_r_g * d0) * (1.0 - math.exp(log_r_g * abs(d0 - dk)))
        partial[i] = acc
    return 2.0 * partial.sum() / (n * n)


def _box_array(box: np.ndarray | None) -> np.ndarray:
    if box is None:
        return np.zeros(3)
    b = np.asarray(box, float)
    return np.where(np.isfinite(b), b, 0.0)


def siiria_index(
    positions0: np.ndarray,
    positions: np.ndarray,
    R: float = 0.87,
    g: float = 1.0,
    box: np.ndarray | None = None,
) -> float:
    """Siiria mixing index, exact O(N^2) numba kernel.

    ``M_ij = R^(g |x_ij|) (1 - R^(g | |x_ij| - |x_ijk| |))``, ``SM = sum_ij M_ij / N^2``
    with ``x_ij`` the initial and ``x_ijk`` the current distance of pair (i, j) (seed Eqs. 26-27).
    0 at the reference frame; grows as initially close pairs separate.
    ``g`` (1/m) should satisfy ``g L < 10`` for the largest distance ``L`` (Siiria & Yliruusi,
    Powder Technol. 2009; R = 0.87 recommended there).
    """
    _check_siiria(R, g)
    p0 = np.ascontiguousarray(positions0, dtype=np.float64)
    p = np.ascontiguousarray(positions, dtype=np.float64)
    if p0.shape != p.shape:
        raise ValueError(f"positions0 and positions differ in shape: {p0.shape} vs {p.shape}")
    return float(_siiria_exact(p0, p, _box_array(box), g * math.log(R)))


def _check_siiria(R: float, g: float) -> None:
    if not 0.0 < R < 1.0:
        raise ValueError(f"R must be in (0, 1), got {R}")
    if not g > 0.0:
        raise ValueError(f"g must be > 0, got {g}")


def siiria_index_sampled(
    positions0: np.ndarray,
    positions: np.ndarray,
    pairs: np.ndarray,
    R: float = 0.87,
    g: float = 1.0,
    box: np.ndarray | None = None,
) -> tuple[float, float]:
    """Unbiased Monte-Carlo estimate of :func:`siiria_index` from a sample of distinct pairs.

    Returns ``(estimate, standard_error)``. With pairs drawn uniformly among the
    ``N (N - 1) / 2`` distinct pairs, ``SM = (N - 1) / N * mean(M_ij)``; the standard error is
    that of the sample mean (central limit theorem), so an M-pair sample costs O(M).
    """
    _check_siiria(R, g)
    n = len(positions0)
    d0 = pair_distances(positions0, pairs, box)
    dk = pair_distances(positions, pairs, box)
    m = R ** (g * d0) * (1.0 - R ** (g * np.abs(d0 - dk)))
    scale = (n - 1) / n
    return float(scale * m.mean()), float(scale * m.std(ddof=1) / np.sqrt(len(m)))


def random_pairs(n: int, n_pairs: int, seed: int | np.random.Generator = 0) -> np.ndarray:
    """``n_pairs`` uniformly drawn pairs ``(i, j)`` with ``i != j`` (with replacement)."""
    rng = np.random.default_rng(seed)
    i = rng.integers(0, n, n_pairs)
    j = (i + rng.integers(1, n, n_pairs)) % n
    return np.stack([i, j], axis=1)
