"""Sampling grids for grid-based (variance) mixing indices.

The seed (section 4.4.1, after Boukouvala et al.) divides the periodic blender section into
1 x 8 x 8 cells (X, Y, Z) and drops every cell that holds fewer than 50 % of the average
number of particles per cell (``0.5 * N / n_cells``): such cells are empty or incomplete
samples near the free surface and only add noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GridSpec:
    """A regular grid of ``shape = (nx, ny, nz)`` cells over the box ``[lo, hi]`` (m).

    ``min_fill`` is the fraction of the mean occupancy (particles per cell over *all* cells)
    below which a cell is excluded from the variance indices (seed: 0.5).
    """

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    shape: tuple[int, int, int] = (1, 8, 8)
    min_fill: float = 0.5

    def __post_init__(self) -> None:
        if len(self.shape) != 3 or any(int(n) < 1 for n in self.shape):
            raise ValueError(f"shape must be three positive integers, got {self.shape!r}")
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        if (
            lo.shape != (3,)
            or hi.shape != (3,)
            or not np.all(np.isfinite(lo))
            or not np.all(np.isfinite(hi))
        ):
            raise ValueError(
                f"lo and hi must be three finite numbers, got {self.lo!r}, {self.hi!r}"
            )
        if np.any(hi <= lo):
            raise ValueError(f"hi must exceed lo on every axis, got lo={self.lo!r}, hi={self.hi!r}")
        if not 0.0 <= self.min_fill < 1.0:
            raise ValueError(f"min_fill must be in [0, 1), got {self.min_fill!r}")

    @classmethod
    def parse(cls, text: str, lo, hi, min_fill: float = 0.5) -> GridSpec:
        """Build from a string such as ``"1x8x8"``."""
        parts = text.lower().split("x")
        try:
            shape = tuple(int(p) for p in parts)
        except ValueError:
            raise ValueError(f"grid must look like '1x8x8', got {text!r}") from None
        if len(shape) != 3:
            raise ValueError(f"grid must have three sizes like '1x8x8', got {text!r}")
        return cls(tuple(map(float, lo)), tuple(map(float, hi)), shape, min_fill)

    @property
    def n_cells(self) -> int:
        return int(np.prod(self.shape))

    def cell_index(self, positions: np.ndarray) -> np.ndarray:
        """Flat cell index of each position; particles outside the box are clipped to the edge."""
        pos = np.asarray(positions, float)
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        shape = np.asarray(self.shape)
        ijk = np.floor((pos - lo) / (hi - lo) * shape).astype(np.int64)
        ijk = np.clip(ijk, 0, shape - 1)
        return np.ravel_multi_index(ijk.T, self.shape)


def cell_counts(grid: GridSpec, positions: np.ndarray, types: np.ndarray, type_ids) -> np.ndarray:
    """Counts per cell and type: array of shape ``(n_cells, len(type_ids))``."""
    cells = grid.cell_index(positions)
    types = np.asarray(types)
    out = np.zeros((grid.n_cells, len(type_ids)), dtype=np.int64)
    for k, tid in enumerate(type_ids):
        out[:, k] = np.bincount(cells[types == tid], minlength=grid.n_cells)
    return out


def occupied_cells(grid: GridSpec, counts: np.ndarray) -> np.ndarray:
    """Boolean mask of the cells kept for the variance indices (the seed's 50 % rule).

    A cell is kept when its total count is at least ``min_fill * N / n_cells`` and non-zero.
    """
    total = counts.sum(axis=1)
    threshold = grid.min_fill * total.sum() / grid.n_cells
    return (total >= threshold) & (total > 0)
