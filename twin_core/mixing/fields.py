"""Cell fields of particle attributes on a sampling grid: velocity fields and homogeneity.

A cell field is the amount-weighted mean of a particle attribute over the particles in each
cell (counts or volumes; point or fractional mapping, as the indices: see
:mod:`twin_core.mixing.grid`). On cylindrical bins velocities are taken in the bins' own
components (radial, tangential, axial).

The homogeneity index of an attribute is the root-mean-square deviation of the cell means
from the bulk mean, ``HI = sqrt(mean_i (m_i - m_bulk)^2)`` over the kept cells (Windows-Yule,
Nicusan, Herald, Manger & Parker, *Positron Emission Particle Tracking: A Comprehensive
Guide*, IOP Publishing 2022), 0 for an attribute spread evenly over the bed; in the units of
the attribute.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from twin_core.mixing.grid import (
    CylindricalGrid,
    GridSpec,
    occupied_cells,
    sampled_weights,
    sphere_volumes,
)
from twin_core.mixing.series import frame_velocities

#: particle attributes known by name (:func:`particle_attribute`)
ATTRIBUTES = ("radius", "volume", "type", "speed", "vx", "vy", "vz", "x", "y", "z")


def cell_means(
    grid: GridSpec | CylindricalGrid,
    positions: np.ndarray,
    radii: np.ndarray,
    values: np.ndarray,
    *,
    weight: str = "number",
    mapping: str = "point",
    box=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``values`` (``(N,)`` or ``(N, d)``) over the particles of each cell, weighted by
    count or volume: ``m_i = sum_p w_pi v_p / sum_p w_pi``. Returns ``(means, amount)``, means
    ``(n_cells,)`` or ``(n_cells, d)`` (NaN in empty cells) and the amount ``sum_p w_pi``."""
    values = np.asarray(values, float)
    part, cell, w = sampled_weights(grid, positions, radii, weight, mapping, box)
    amount = np.bincount(cell, weights=w, minlength=grid.n_cells)
    cols = values.reshape(len(values), -1)
    sums = np.stack(
        [np.bincount(cell, weights=w * cols[part, k], minlength=grid.n_cells) for k in range(cols.shape[1])],
        axis=1,
    )  # fmt: skip
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(amount[:, None] > 0, sums / amount[:, None], np.nan)
    return (means[:, 0] if values.ndim == 1 else means), amount


def homogeneity_index(means: np.ndarray, bulk_mean: float, kept: np.ndarray | None = None) -> float:
    """``HI = sqrt(mean_i (m_i - m_bulk)^2)`` over the kept cells (module docstring)."""
    m = np.asarray(means, float)
    if kept is not None:
        m = m[np.asarray(kept, bool)]
    m = m[np.isfinite(m)]
    if m.size == 0:
        raise ValueError("no occupied cell: homogeneity index undefined")
    return float(np.sqrt(np.mean((m - bulk_mean) ** 2)))


def particle_attribute(frame, name: str) -> np.ndarray:
    """A per-particle attribute of a frame by name (:data:`ATTRIBUTES`)."""
    pos = np.asarray(frame.positions, float)
    if name == "radius":
        return np.asarray(frame.radii, float)
    if name == "volume":
        return sphere_volumes(frame.radii)
    if name == "type":
        return np.asarray(frame.types, float)
    if name == "speed":
        return np.linalg.norm(frame_velocities(frame), axis=1)
    if name in ("vx", "vy", "vz"):
        return frame_velocities(frame)[:, "xyz".index(name[1])]
    if name in ("x", "y", "z"):
        return pos[:, "xyz".index(name)]
    raise ValueError(f"unknown attribute {name!r}; known: {', '.join(ATTRIBUTES)}")


def homogeneity_series(
    frames: Iterable,
    attributes: Sequence[str],
    grid: GridSpec | CylindricalGrid,
    *,
    weight: str = "number",
    mapping: str = "point",
    box=None,
) -> pd.DataFrame:
    """Homogeneity index of each attribute in every frame: columns ``t`` and ``HI_<name>``.
    Cells are kept by the grid's minimum-fill rule; the bulk mean is the amount-weighted mean
    over the sampled particles."""
    for name in attributes:
        if name not in ATTRIBUTES:
            raise ValueError(f"unknown attribute {name!r}; known: {', '.join(ATTRIBUTES)}")
    rows = []
    for frame in frames:
        row = {"t": float(frame.t)}
        values = np.stack([particle_attribute(frame, a) for a in attributes], axis=1)
        means, amount = cell_means(
            grid, frame.positions, frame.radii, values, weight=weight, mapping=mapping, box=box
        )
        kept = occupied_cells(grid, amount[:, None])
        bulk = np.nansum(means * amount[:, None], axis=0) / amount.sum()
        for k, name in enumerate(attributes):
            row[f"HI_{name}"] = homogeneity_index(means[:, k], float(bulk[k]), kept)
        rows.append(row)
    return pd.DataFrame(rows)


def velocity_components(
    grid: GridSpec | CylindricalGrid, positions: np.ndarray, velocities: np.ndarray
) -> np.ndarray:
    """Velocities in the grid's components: (vx, vy, vz) for Cartesian cells, (radial,
    tangential, axial) for cylindrical bins."""
    v = np.asarray(velocities, float)
    if isinstance(grid, CylindricalGrid):
        e_r, e_t, e_z = grid.local_axes(positions)
        return np.stack([np.sum(v * e_r, 1), np.sum(v * e_t, 1), np.sum(v * e_z, 1)], axis=1)
    return v


def component_labels(grid: GridSpec | CylindricalGrid) -> tuple[str, str, str]:
    if isinstance(grid, CylindricalGrid):
        return ("v_r", "v_theta", f"v_{'xyz'[grid.axis]}")
    return ("vx", "vy", "vz")


@dataclass
class VelocityFields:
    """Per-frame and mean velocity fields on a grid (m/s, the grid's components).

    ``per_frame[f, c]``: mean velocity of cell ``c`` in frame ``f`` (NaN where empty);
    ``amount[f, c]``: its particle amount; ``mean[c]``: the time-mean field, pooled over the
    frames (``sum_f sum_p w v / sum_f sum_p w``), so a cell is weighted by how full it was."""

    t: np.ndarray
    per_frame: np.ndarray
    amount: np.ndarray
    mean: np.ndarray
    labels: tuple[str, str, str]

    def mean_table(self, grid: GridSpec | CylindricalGrid) -> pd.DataFrame:
        """The mean field, one row per cell: cell index, centre (m), amount, components."""
        centre = grid.cell_centres()
        total = self.amount.sum(axis=0)
        df = pd.DataFrame({"cell": np.arange(grid.n_cells)})
        for k, name in enumerate("xyz"):
            df[f"{name}_m"] = centre[:, k]
        df["amount"] = total
        for k, name in enumerate(self.labels):
            df[f"{name}_m_s"] = self.mean[:, k]
        return df

    def frame_table(self) -> pd.DataFrame:
        """The per-frame fields, one row per frame and occupied cell."""
        f, c = np.nonzero(self.amount > 0)
        df = pd.DataFrame({"t": self.t[f], "cell": c, "amount": self.amount[f, c]})
        for k, name in enumerate(self.labels):
            df[f"{name}_m_s"] = self.per_frame[f, c, k]
        return df


def velocity_fields(
    frames: Iterable,
    grid: GridSpec | CylindricalGrid,
    *,
    weight: str = "number",
    mapping: str = "point",
    box=None,
) -> VelocityFields:
    """Mean velocity of each cell in every frame and over all frames (:class:`VelocityFields`).
    A uniform rotation ``omega`` about a cylindrical grid's axis gives ``v_theta = omega r``
    averaged over each bin's particles, and zero radial and axial components."""
    ts, per_frame, amounts = [], [], []
    for frame in frames:
        v = velocity_components(grid, frame.positions, frame_velocities(frame))
        means, amount = cell_means(
            grid, frame.positions, frame.radii, v, weight=weight, mapping=mapping, box=box
        )
        ts.append(float(frame.t))
        per_frame.append(means)
        amounts.append(amount)
    if not ts:
        raise ValueError("frames is empty")
    per = np.stack(per_frame)
    amt = np.stack(amounts)
    total = amt.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        pooled = np.nansum(per * amt[..., None], axis=0) / total[:, None]
    mean = np.where(total[:, None] > 0, pooled, np.nan)
    return VelocityFields(np.asarray(ts), per, amt, mean, component_labels(grid))
