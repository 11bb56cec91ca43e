"""Contacts and nearest neighbours from particle positions (periodic boxes allowed)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def _tree(positions: np.ndarray, box: np.ndarray | None) -> cKDTree:
    """A KD-tree; ``box`` holds the period per axis (``inf`` or ``nan`` = not periodic)."""
    pos = np.asarray(positions, float)
    if box is None:
        return cKDTree(pos)
    box = np.asarray(box, float)
    periodic = np.isfinite(box)
    if not periodic.any():
        return cKDTree(pos)
    lo = pos.min(axis=0)
    shifted = pos - np.where(periodic, 0.0, lo)
    size = np.where(periodic, box, 4.0 * (np.ptp(pos, axis=0) + 1.0))
    shifted = np.where(periodic, np.mod(shifted, size), shifted)
    return cKDTree(shifted, boxsize=size)


def contacts_from_positions(
    positions: np.ndarray,
    radii: np.ndarray,
    box: np.ndarray | None = None,
    tolerance: float = 0.02,
) -> np.ndarray:
    """Pairs ``(i, j)``, ``i < j``, whose centre distance is below ``(r_i + r_j)(1 + tolerance)``.

    ``box``: per-axis period length for periodic axes, ``inf`` for the others.
    The tolerance accepts near-touching pairs in frames saved with finite precision.
    """
    radii = np.asarray(radii, float)
    if tolerance < 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    tree = _tree(positions, box)
    cutoff = 2.0 * radii.max() * (1.0 + tolerance)
    pairs = tree.query_pairs(cutoff, output_type="ndarray")
    if pairs.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    d = minimum_image_distance(positions[pairs[:, 0]], positions[pairs[:, 1]], box)
    keep = d < (radii[pairs[:, 0]] + radii[pairs[:, 1]]) * (1.0 + tolerance)
    return pairs[keep].astype(np.int64)


def minimum_image_distance(p: np.ndarray, q: np.ndarray, box: np.ndarray | None) -> np.ndarray:
    """Euclidean distance with the minimum-image convention on periodic axes."""
    d = np.asarray(q, float) - np.asarray(p, float)
    if box is not None:
        box = np.asarray(box, float)
        per = np.isfinite(box)
        if per.any():
            L = np.where(per, box, 1.0)
            d = np.where(per, d - L * np.round(d / L), d)
    return np.sqrt(np.sum(d * d, axis=-1))


def nearest_neighbours(positions: np.ndarray, k: int, box: np.ndarray | None = None) -> np.ndarray:
    """Indices ``(N, k)`` of the ``k`` nearest other particles of each particle."""
    if k < 1 or k >= len(positions):
        raise ValueError(f"k must be in [1, N-1], got {k} for N={len(positions)}")
    tree = _tree(positions, box)
    _, idx = tree.query(tree.data, k=k + 1, workers=-1)
    return idx[:, 1:]
