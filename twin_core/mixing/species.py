"""Species from positions or sizes: split a bed into two "colours" of equal number or volume.

DEM output of a real blend often carries no colour. The usual analysis colours the bed at the
first frame: particles below the median along an axis (or radius from an axis, or size) are
the tracer. On a polydisperse bed a median by number gives the tracer a volume fraction far
from one half; the split by volume puts the cut at the volume-weighted median, so each species
holds half the particle volume (DEMToolbox's ``split_particles`` splits by number).
"""

from __future__ import annotations

import numpy as np

from twin_core.mixing.grid import WEIGHTS, sphere_volumes

#: what a split may follow: a coordinate, the distance from an axis, or the particle radius
SPLIT_BY = ("x", "y", "z", "r", "radius")


def split_species(
    positions: np.ndarray,
    radii: np.ndarray,
    by: str = "y",
    weight: str = "volume",
    fraction: float = 0.5,
    axis: int = 2,
    centre: tuple[float, float] | None = None,
) -> np.ndarray:
    """Types 0 (tracer: below the cut) and 1 (the rest) split along ``by`` so that the tracer
    holds ``fraction`` of the particles (``weight="number"``) or of their volume
    (``weight="volume"``), to within one particle.

    ``by``: a coordinate (``x``, ``y``, ``z``), ``r`` the distance from the axis ``axis``
    through ``centre`` (default: the bed's mean position in the cross-section), or ``radius``
    (the smaller particles are the tracer). Ties at the cut go to the tracer side one by one in
    a stable order, so the fraction is met even for equal values (a lattice layer, equal sizes).
    """
    if by not in SPLIT_BY:
        raise ValueError(f"split must be one of {SPLIT_BY}, got {by!r}")
    if weight not in WEIGHTS:
        raise ValueError(f"weight must be one of {WEIGHTS}, got {weight!r}")
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"fraction must be in (0, 1), got {fraction!r}")
    pos = np.asarray(positions, float)
    radii = np.asarray(radii, float)
    if by == "radius":
        value = radii
    elif by == "r":
        a, b = (axis + 1) % 3, (axis + 2) % 3
        c = pos[:, [a, b]].mean(axis=0) if centre is None else np.asarray(centre, float)
        value = np.hypot(pos[:, a] - c[0], pos[:, b] - c[1])
    else:
        value = pos[:, "xyz".index(by)]
    w = sphere_volumes(radii) if weight == "volume" else np.ones(len(pos))
    order = np.argsort(value, kind="stable")
    cum = np.cumsum(w[order])
    n_tracer = int(np.searchsorted(cum, fraction * cum[-1], side="left")) + 1
    if cum[n_tracer - 1] - fraction * cum[-1] > fraction * cum[-1] - (
        cum[n_tracer - 2] if n_tracer > 1 else 0.0
    ):
        n_tracer -= 1  # the cut nearer the target
    types = np.ones(len(pos), np.int64)
    types[order[:n_tracer]] = 0
    return types
