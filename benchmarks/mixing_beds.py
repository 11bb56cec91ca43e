"""Synthetic polydisperse particle beds for the mixing benchmarks.

A log-normal size distribution binned into a few radius classes (the DEM practice of a
handful of sizes standing for a distribution), packed into a vertical cylinder: random
positions relaxed by pushing overlapping pairs apart (half the overlap each, Jacobi sweeps)
and clamping to the walls until the largest overlap is a small fraction of the smallest
radius. The result is a dense random packing whose contacts and neighbour shells look like a
settled DEM bed's; the cost of the mixing indices does not depend on how it was made.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from twin_core.dem.frames import Frame
from twin_core.mixing.neighbours import neighbour_search


@dataclass(frozen=True)
class CylinderBed:
    """A packed bed in the cylinder ``x^2 + y^2 < radius^2``, ``0 < z < height`` (m)."""

    positions: np.ndarray
    radii: np.ndarray
    radius: float
    height: float


def lognormal_radii(
    n: int,
    rng: np.random.Generator,
    n_classes: int = 10,
    median: float = 1.0e-3,
    sigma: float = 0.25,
) -> np.ndarray:
    """``n`` radii drawn from a log-normal distribution (``median``, log-std ``sigma``),
    truncated to ``median * exp(+-2 sigma)`` and binned into ``n_classes`` classes of equal
    width in ``ln r``; each particle takes its class's geometric mid radius."""
    lo, hi = -2.0 * sigma, 2.0 * sigma
    z = rng.normal(0.0, sigma, 4 * n)
    z = z[(z > lo) & (z < hi)][:n]
    edges = np.linspace(lo, hi, n_classes + 1)
    k = np.clip(np.searchsorted(edges, z) - 1, 0, n_classes - 1)
    return median * np.exp(0.5 * (edges[k] + edges[k + 1]))


def packed_cylinder(
    radii: np.ndarray,
    rng: np.random.Generator,
    cylinder_radius: float = 0.035,
    packing: float = 0.57,
    max_overlap: float = 0.02,
    max_sweeps: int = 400,
    heights: np.ndarray | None = None,
) -> CylinderBed:
    """Particles of ``radii`` packed at solid fraction ``packing`` into a cylinder of radius
    ``cylinder_radius``, overlaps relaxed until none exceeds ``max_overlap`` times the smallest
    radius (or ``max_sweeps`` sweeps). ``heights``: each particle's starting height as a
    fraction of the bed height (default uniformly random), e.g. to start a species below the
    other."""
    r = np.asarray(radii, float)
    n = len(r)
    height = float(np.sum(4.0 / 3.0 * math.pi * r**3) / (packing * math.pi * cylinder_radius**2))
    rho = cylinder_radius * np.sqrt(rng.random(n))
    phi = 2 * math.pi * rng.random(n)
    z = height * (rng.random(n) if heights is None else np.asarray(heights, float))
    pos = np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)
    tol = max_overlap * r.min()
    for _ in range(max_sweeps):
        _clamp_to_cylinder(pos, r, cylinder_radius, height)
        pairs, _ = neighbour_search(pos, r, None, 0.0, 0)
        if len(pairs) == 0:
            break
        d = pos[pairs[:, 1]] - pos[pairs[:, 0]]
        dist = np.linalg.norm(d, axis=1)
        overlap = r[pairs[:, 0]] + r[pairs[:, 1]] - dist
        if overlap.max() < tol:
            break
        push = (0.5 * 1.3 * overlap / np.maximum(dist, 1e-12))[:, None] * d
        for ax in range(3):
            pos[:, ax] += np.bincount(pairs[:, 1], push[:, ax], n) - np.bincount(
                pairs[:, 0], push[:, ax], n
            )
    _clamp_to_cylinder(pos, r, cylinder_radius, height)
    return CylinderBed(pos, r, cylinder_radius, height)


def _clamp_to_cylinder(pos: np.ndarray, r: np.ndarray, radius: float, height: float) -> None:
    """Move particle centres inside the walls: radially to ``radius - r``, axially to
    ``r .. height - r``."""
    rho = np.hypot(pos[:, 0], pos[:, 1])
    limit = np.maximum(radius - r, 0.0)
    out = rho > limit
    pos[out, :2] *= (limit[out] / rho[out])[:, None]
    pos[:, 2] = np.clip(pos[:, 2], r, height - r)


def shuffled_frames(
    bed: CylinderBed,
    types: np.ndarray,
    n_frames: int,
    rng: np.random.Generator,
    swap_fraction: float = 0.02,
    dt: float = 0.1,
) -> list[Frame]:
    """A progressively mixed run: at each frame ``swap_fraction`` of the particles exchange
    positions with particles of their own size class (the packing stays a packing)."""
    n = len(bed.radii)
    classes = np.unique(bed.radii, return_inverse=True)[1]
    members = [np.flatnonzero(classes == c) for c in range(classes.max() + 1)]
    pos = bed.positions.copy()
    ids = np.arange(n)
    out = []
    for k in range(n_frames):
        out.append(Frame(dt * k, ids, types, bed.radii, pos.copy(), np.zeros_like(pos)))
        for m in members:
            sel = rng.choice(m, max(2, int(swap_fraction * len(m))), replace=False)
            pos[sel] = pos[rng.permutation(sel)]
    return out
