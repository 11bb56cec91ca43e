"""Which grid cell a position lies in: the one binning of particle positions onto the
compartment model's grid (radial-mixing snapshots, particle transitions)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def cell_index(
    positions: np.ndarray, edges: Sequence[np.ndarray], periodic: Sequence[bool]
) -> tuple[np.ndarray, np.ndarray]:
    """Flat cell index (C order over the cells of ``edges``) of positions (n, 3) and whether
    each lies in the grid: periodic axes are wrapped into the box; along a closed axis a
    position outside the edges is clipped to the end cell and marked outside."""
    pos = np.asarray(positions, dtype=float)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions must have shape (n, 3), got {pos.shape}")
    shape = tuple(int(e.size) - 1 for e in edges)
    idx = []
    inside = np.ones(pos.shape[0], dtype=bool)
    for axis in range(3):
        e = edges[axis]
        x = pos[:, axis]
        if periodic[axis]:
            x = e[0] + np.mod(x - e[0], e[-1] - e[0])
        else:
            inside &= (x >= e[0]) & (x <= e[-1])
        idx.append(np.clip(np.searchsorted(e, x, side="right") - 1, 0, shape[axis] - 1))
    return np.ravel_multi_index(tuple(idx), shape), inside
