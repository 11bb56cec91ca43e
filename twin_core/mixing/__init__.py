"""Mixing indices, sampling grids, cell fields and T95 mixing times (seed chapter 4).

The indices are computed on particle frames, ``twin_core.dem.frames.Frame`` (the one frame
type: the DEM engine writes it, the mixing analysis reads it); the figures of an analysis are
drawn by ``twin_core.mixing.plots``.
"""

from twin_core.mixing.grid import (
    CylindricalGrid,
    GridSpec,
    cell_amounts,
    cell_counts,
    occupied_cells,
    parse_bins,
)
from twin_core.mixing.properties import index_properties, select_indices
from twin_core.mixing.series import (
    DIRECTION,
    INDEX_NAMES,
    SEED_INDICES,
    VOLUME_WEIGHTED,
    MixingConfig,
    compute_indices,
    mixed_reference,
    mixing_progress,
    shuffled_frame,
)
from twin_core.mixing.species import split_species
from twin_core.mixing.t95 import T95Fit, fit_t95, t95_time

__all__ = [
    "DIRECTION", "INDEX_NAMES", "SEED_INDICES", "VOLUME_WEIGHTED", "CylindricalGrid", "GridSpec",
    "MixingConfig", "T95Fit", "cell_amounts", "cell_counts", "compute_indices", "fit_t95",
    "index_properties", "mixed_reference", "mixing_progress", "occupied_cells", "parse_bins",
    "select_indices", "shuffled_frame", "split_species", "t95_time",
]  # fmt: skip
