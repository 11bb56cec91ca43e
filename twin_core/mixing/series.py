"""Mixing indices over a sequence of particle frames.

A frame is a :class:`twin_core.dem.frames.Frame` (``t`` in s, ``ids``, ``types``, ``radii``,
``positions`` and ``velocities`` ``(N, 3)``, SI) -- the indices read every attribute but the
velocities (a frame without velocities is taken at rest). Frames are aligned by particle id to
the first frame, which is the reference ("initial, segregated") state of VRR, NDM, SM and SSI.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from twin_core.dem.frames import Frame
from twin_core.mixing import contact_indices as ci
from twin_core.mixing import distance_indices as di
from twin_core.mixing import variance_indices as vi
from twin_core.mixing.grid import (
    MAPPINGS,
    WEIGHTS,
    CylindricalGrid,
    GridSpec,
    cell_amounts,
    occupied_cells,
    sphere_volumes,
)
from twin_core.mixing.neighbours import neighbour_search

#: the seed's fifteen indices (section 4.3.1), in the order of its Figure 4.4
SEED_INDICES: tuple[str, ...] = (
    "LI", "RSD", "VRR", "VBBC", "ESI", "ME", "DM", "MSI", "SM", "AH", "NDM", "NNM", "PS", "CN", "SI",
)  # fmt: skip

#: every index computed here: the seed's fifteen and the sphere spreading index (Füvesi 2025)
INDEX_NAMES: tuple[str, ...] = (*SEED_INDICES, "SSI")

#: direction of mixing progress: +1 the index grows when mixing, -1 it falls
DIRECTION: dict[str, int] = {
    "LI": 1, "RSD": -1, "VRR": 1, "VBBC": -1, "ESI": -1, "ME": 1, "DM": 1, "MSI": -1, "SM": 1,
    "AH": -1, "NDM": 1, "NNM": 1, "PS": 1, "CN": 1, "SI": -1, "SSI": 1,
}  # fmt: skip

#: indices that take a volume weighting (``MixingConfig.weight="volume"``); the others count
#: particles (contacts, neighbours and pair distances have no volume analogue in their papers)
VOLUME_WEIGHTED = frozenset({"LI", "RSD", "VRR", "VBBC", "ESI", "ME", "DM", "MSI", "AH", "SSI"})

_GRID_INDICES = frozenset({"LI", "RSD", "VRR", "VBBC", "ESI", "ME", "DM", "MSI"})


@dataclass
class MixingConfig:
    """Options of :func:`compute_indices`.

    ``grid``: a :class:`~twin_core.mixing.grid.GridSpec` or
    :class:`~twin_core.mixing.grid.CylindricalGrid`. ``box``: period length per axis for
    periodic axes, ``inf`` otherwise (e.g. ``(0.04, inf, inf)`` for the blender section).
    ``tracer``: type id of the "A"/red particles (default: the smallest type id). ``weight``:
    ``"number"`` (the seed's number fractions) or ``"volume"`` (cells weighted by particle
    volume, species by volume fraction: polydisperse beds; see :data:`VOLUME_WEIGHTED`).
    ``mapping``: ``"point"`` (a particle in the cell of its centre) or ``"fractional"`` (split
    over the cells by the volume of its parts). ``sm_pairs``: ``None`` evaluates the Siiria
    index exactly (O(N^2)), an integer uses the sampled estimator with that many pairs (and
    reports its standard error in ``SM_se``). ``sm_g``: ``None`` takes ``5 / L`` with ``L`` the
    diagonal of the grid's bounding box (Siiria's rule ``g L < 10``).
    """

    grid: GridSpec | CylindricalGrid
    box: tuple[float, float, float] = (np.inf, np.inf, np.inf)
    tracer: int | None = None
    weight: str = "number"
    mapping: str = "point"
    contact_tolerance: float = 0.02
    n_neighbours: int = 12
    ah_axis: int = 2
    sm_R: float = 0.87
    sm_g: float | None = None
    sm_pairs: int | None = None
    ndm_random_pairs: int = 20_000
    seed: int = 0

    def __post_init__(self) -> None:
        if self.weight not in WEIGHTS:
            raise ValueError(f"weight must be one of {WEIGHTS}, got {self.weight!r}")
        if self.mapping not in MAPPINGS:
            raise ValueError(f"mapping must be one of {MAPPINGS}, got {self.mapping!r}")


def parse_indices(indices: str | Sequence[str]) -> list[str]:
    """Index names from ``"all"``, a comma list or a sequence (case-insensitive)."""
    if isinstance(indices, str):
        indices = INDEX_NAMES if indices == "all" else [s.strip() for s in indices.split(",")]
    out = []
    for name in indices:
        key = name.upper()
        if key not in INDEX_NAMES:
            raise ValueError(f"unknown index {name!r}; known: {', '.join(INDEX_NAMES)}")
        out.append(key)
    return out


def _aligned(frame: Frame, order_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Types, radii and positions of the frame in the order of ``order_ids`` (sorted ids)."""
    ids = np.asarray(frame.ids)
    if np.array_equal(ids, order_ids):  # already in id order (the usual case): no copies
        return (
            np.asarray(frame.types),
            np.asarray(frame.radii, float),
            np.asarray(frame.positions, float),
        )
    sort = np.argsort(ids, kind="stable")
    if len(ids) != len(order_ids) or not np.array_equal(ids[sort], order_ids):
        raise ValueError(
            f"frame at t={frame.t} does not hold the same particle ids as the first frame"
        )
    return (
        np.asarray(frame.types)[sort],
        np.asarray(frame.radii, float)[sort],
        np.asarray(frame.positions, float)[sort],
    )


def common_subset(frames: list[Frame]) -> tuple[list[Frame], int]:
    """Frames restricted to the particle ids present in every frame, and the number dropped
    (particles that left the domain during the run)."""
    common = np.asarray(frames[0].ids)
    for f in frames[1:]:
        common = np.intersect1d(common, np.asarray(f.ids))
    out = [_subset(f, np.isin(np.asarray(f.ids), common)) for f in frames]
    return out, len(frames[0].ids) - len(common)


def frame_velocities(frame: Frame) -> np.ndarray:
    """The frame's velocities, zeros for frames that carry none."""
    vel = getattr(frame, "velocities", None)
    return np.zeros((len(frame.ids), 3)) if vel is None else np.asarray(vel, float)


def _subset(frame: Frame, keep: np.ndarray) -> Frame:
    """The frame restricted to the particles where ``keep`` is true."""
    return Frame(
        float(frame.t), np.asarray(frame.ids)[keep], np.asarray(frame.types)[keep],
        np.asarray(frame.radii)[keep], np.asarray(frame.positions)[keep],
        frame_velocities(frame)[keep],
    )  # fmt: skip


def compute_indices(
    frames: Iterable[Frame],
    indices: str | Sequence[str] = "all",
    config: MixingConfig | None = None,
    allow_lost: bool = False,
) -> pd.DataFrame:
    """All requested indices for every frame: a DataFrame with column ``t`` and one per index.

    Every frame must hold the same particle ids. With ``allow_lost=True`` (DEM runs where a few
    particles leave the domain) the indices are evaluated on the particles present in every
    frame, and the number left out is reported in ``df.attrs["dropped_particles"]``.

    ``AH`` is along ``config.ah_axis``; ``AH_x``, ``AH_y``, ``AH_z`` give all three axes.
    ``VBBC`` is normalised by its maximum over the series (seed Eq. 8); ``VBBC_raw`` keeps
    Eq. (7). With a sampled Siiria index, ``SM_se`` holds its standard error.
    """
    if config is None:
        raise ValueError("config is required (at least a grid)")
    names = parse_indices(indices)
    dropped = 0
    if allow_lost:
        frames = list(frames)
        if frames:
            frames, dropped = common_subset(frames)
    frames = iter(frames)
    try:
        first = next(frames)
    except StopIteration:
        raise ValueError("frames is empty") from None
    order_ids = np.sort(np.asarray(first.ids))
    if len(np.unique(order_ids)) != len(order_ids):
        raise ValueError("particle ids of the first frame are not unique")
    # the reference frame is kept: copies, which frames reusing their arrays cannot overwrite
    types0, radii0, pos0 = (np.array(x) for x in _aligned(first, order_ids))
    state = _Reference(pos0, types0, radii0, config, names)
    rows = [state.row(first.t, types0, radii0, pos0)]
    for frame in frames:
        types, radii, pos = _aligned(frame, order_ids)
        rows.append(state.row(frame.t, types, radii, pos))
    df = pd.DataFrame(rows)
    if "VBBC" in names:
        df["VBBC_raw"] = df["VBBC"]
        peak = df["VBBC_raw"].max()
        df["VBBC"] = df["VBBC_raw"] / peak if peak > 0 else np.nan
    df.attrs["dropped_particles"] = dropped
    df.attrs["weight"] = config.weight
    df.attrs["mapping"] = config.mapping
    return df


def _kappa(radii: np.ndarray, weight: str) -> float:
    """``<v^2> / <v>`` of the particle amounts (1 for counts, volumes for volume weighting)."""
    if weight == "number" or len(radii) == 0:
        return 1.0
    v = sphere_volumes(radii)
    return float(np.mean(v**2) / np.mean(v))


def _grid_diagonal(grid: GridSpec | CylindricalGrid) -> float:
    if isinstance(grid, CylindricalGrid):
        return float(np.hypot(2 * grid.r_max, grid.hi - grid.lo))
    return float(np.linalg.norm(np.subtract(grid.hi, grid.lo)))


def _grid_floor(grid: GridSpec | CylindricalGrid, axis: int) -> float:
    """Origin of the heights of AH along ``axis``: the grid's lower bound there."""
    if isinstance(grid, CylindricalGrid):
        if axis == grid.axis:
            return grid.lo
        k = grid.cross_axes.index(axis)
        return grid.centre[k] - grid.r_max
    return grid.lo[axis]


class _Reference:
    """Reference-frame quantities (initial contacts, random pairs, VRR variance, tracer
    spreading) and the per-frame evaluation of the indices."""

    def __init__(self, pos0, types0, radii0, config: MixingConfig, names: list[str]):
        self.cfg, self.names = config, names
        self.box = np.asarray(config.box, float)
        self.grid = config.grid
        self.tracer = int(np.min(types0)) if config.tracer is None else int(config.tracer)
        if not np.any(types0 == self.tracer) or np.all(types0 == self.tracer):
            raise ValueError(
                f"tracer type {self.tracer} must be present together with another type"
            )
        self.type_ids = [self.tracer] + sorted(set(np.unique(types0).tolist()) - {self.tracer})
        self.pos0 = pos0
        self.volume = config.weight == "volume"
        is_a = types0 == self.tracer
        self.kappa = (_kappa(radii0[is_a], config.weight), _kappa(radii0[~is_a], config.weight))
        rng = np.random.default_rng(config.seed)
        if "VRR" in names:
            kept = self._cells(pos0, types0, radii0)
            self.ref_cells = (kept[:, 0], kept.sum(axis=1))
        if "NDM" in names:
            pairs, _ = neighbour_search(pos0, radii0, self.box, config.contact_tolerance, 0)
            if len(pairs) == 0:
                raise ValueError("no contacts in the first frame: NDM needs a packed bed")
            self.nb_pairs = pairs
            self.d_contact = float(np.mean(radii0[pairs[:, 0]] + radii0[pairs[:, 1]]))
            self.rand_pairs = di.random_pairs(len(pos0), config.ndm_random_pairs, rng)
        if "SM" in names:
            self.sm_g = config.sm_g if config.sm_g is not None else 5.0 / _grid_diagonal(self.grid)
            if config.sm_pairs is not None:
                self.sm_pairs = di.random_pairs(len(pos0), int(config.sm_pairs), rng)
        if "SSI" in names:
            w0 = sphere_volumes(radii0) if self.volume else None
            self.ssi_r0 = di.spreading_radius(
                pos0[is_a], None if w0 is None else w0[is_a], self.box
            )

    def _cells(self, pos, types, radii) -> np.ndarray:
        """Amounts of each type (tracer first) in the kept cells, ``(cells, types)``."""
        amounts = cell_amounts(
            self.grid, pos, radii, types, self.type_ids,
            weight=self.cfg.weight, mapping=self.cfg.mapping, box=self.box,
        )  # fmt: skip
        return amounts[occupied_cells(self.grid, amounts)]

    def row(self, t, types, radii, pos) -> dict:
        names = self.names
        out: dict = {"t": float(t)}
        if _GRID_INDICES & set(names):
            out.update(self._grid_indices(types, radii, pos))
        weights = sphere_volumes(radii) if self.volume else None
        if "SM" in names:
            out.update(self._siiria(pos))
        if "AH" in names:
            for axis, label in enumerate("xyz"):
                out[f"AH_{label}"] = di.average_height(
                    pos[:, axis], types, self.tracer, _grid_floor(self.grid, axis), weights
                )
            out["AH"] = out[f"AH_{'xyz'[self.cfg.ah_axis]}"]
        if "SSI" in names:
            out["SSI"] = di.sphere_spreading_index(
                pos, types, self.tracer, self.ssi_r0, weights, self.box
            )
        if "NDM" in names:
            out["NDM"] = di.neighbour_distance_index(
                pos, self.nb_pairs, self.rand_pairs, self.d_contact, self.box
            )
        if {"NNM", "PS", "CN", "SI"} & set(names):
            out.update(self._contact_indices(types, radii, pos))
        return out

    def _grid_indices(self, types, radii, pos) -> dict:
        names, out = self.names, {}
        kept = self._cells(pos, types, radii)
        a, n = kept[:, 0], kept.sum(axis=1)
        w = n if self.volume else None
        p = a.sum() / n.sum()
        if "LI" in names:
            sr2 = vi.random_mixture_variance(p, n.mean(), *self.kappa) if self.volume else None
            out["LI"] = vi.lacey(a, n, w, sr2)
        if "RSD" in names:
            out["RSD"] = vi.relative_standard_deviation(a, n, w)
        if "VRR" in names:
            out["VRR"] = vi.variance_reduction_ratio(a, n, *self.ref_cells, self.volume)
        if "VBBC" in names:
            out["VBBC"] = vi.vbbc_variance(a, n - a)
        if "ESI" in names:
            out["ESI"] = vi.intensity_of_segregation(a, n, w)
        if "ME" in names:
            out["ME"] = vi.mixing_entropy(kept)
        if "DM" in names:
            out["DM"] = vi.degree_of_mixedness(a, n, w)
        if "MSI" in names:
            out["MSI"] = vi.mixing_segregation_index(a, n, w)
        return out

    def _siiria(self, pos) -> dict:
        cfg = self.cfg
        if cfg.sm_pairs is None:
            return {"SM": di.siiria_index(self.pos0, pos, cfg.sm_R, self.sm_g, self.box)}
        sm, se = di.siiria_index_sampled(
            self.pos0, pos, self.sm_pairs, cfg.sm_R, self.sm_g, self.box
        )
        return {"SM": sm, "SM_se": se}

    def _contact_indices(self, types, radii, pos) -> dict:
        names, cfg, out = self.names, self.cfg, {}
        need_contacts = bool({"PS", "CN", "SI"} & set(names))
        k = cfg.n_neighbours if "NNM" in names else 0
        tol = cfg.contact_tolerance if need_contacts else None
        pairs, nb = neighbour_search(pos, radii, self.box, tol, k)  # one pass for all four
        if "NNM" in names:
            out["NNM"] = ci.nearest_neighbour_index(nb, types)
        if "PS" in names:
            out["PS"] = ci.particle_scale_index(pairs, types, self.tracer)
        counts = ci.contact_type_counts(pairs, types, self.tracer) if need_contacts else None
        if "CN" in names:
            out["CN"] = ci.coordination_number_index(pairs, types, self.tracer, counts)
        if "SI" in names:
            out["SI"] = ci.segregation_index(pairs, types, self.tracer, counts)
        return out


def size_classes(radii: np.ndarray, max_classes: int = 16) -> np.ndarray:
    """A class label per particle: the distinct radii (to 1e-6 relative), or ``max_classes``
    quantile bins of the radius when there are more distinct values."""
    r = np.asarray(radii, float)
    scale = max(float(np.abs(r).max()), 1e-300)
    distinct, labels = np.unique(np.round(r / scale, 6), return_inverse=True)
    if len(distinct) <= max_classes:
        return labels
    edges = np.quantile(r, np.linspace(0, 1, max_classes + 1)[1:-1])
    return np.searchsorted(edges, r, side="right")


def shuffled_frame(frame: Frame, seed: int | np.random.Generator = 0) -> Frame:
    """The frame with particle positions randomly permuted among particles of the same size
    class (:func:`size_classes`; all particles in a monodisperse bed).

    This is the random mixture of the same bed (same cells, same contacts, same geometry): the
    "mixed" reference of every index at once. Swapping only equal sizes keeps a polydisperse
    packing a packing; a bed whose species differ in size cannot be mixed this way (see
    :func:`mixed_reference`).
    """
    rng = np.random.default_rng(seed)
    perm = np.arange(len(frame.ids))
    labels = size_classes(frame.radii)
    for c in np.unique(labels):
        members = np.flatnonzero(labels == c)
        perm[members] = members[rng.permutation(len(members))]
    return Frame(
        float(frame.t), np.asarray(frame.ids), np.asarray(frame.types),
        np.asarray(frame.radii), np.asarray(frame.positions)[perm],
        frame_velocities(frame)[perm],
    )  # fmt: skip


def mixed_reference(
    frame: Frame,
    indices: str | Sequence[str] = "all",
    config: MixingConfig | None = None,
    n_shuffles: int = 5,
    seed: int = 0,
) -> pd.Series:
    """Expected value of each index for a random mixture of the bed in ``frame`` (mean of
    ``n_shuffles`` random permutations of positions within size classes, each evaluated
    against ``frame`` as the reference state). VBBC is reported as the ratio of the random to
    the initial raw value.

    Raises ``ValueError`` when no size class holds both species (species told apart by size:
    no permutation of equal sizes mixes them)."""
    labels = size_classes(frame.radii)
    types = np.asarray(frame.types)
    if not any(len(np.unique(types[labels == c])) > 1 for c in np.unique(labels)):
        raise ValueError(
            "every size class holds one species: a random mixture of this bed cannot be made "
            "by swapping equal particles"
        )
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(n_shuffles):
        df = compute_indices([frame, shuffled_frame(frame, rng)], indices, config)
        rows.append(df.iloc[1])
    ref = pd.DataFrame(rows).mean()
    return ref.drop(labels=["t"])


def mixing_progress(
    df: pd.DataFrame, mixed: pd.Series, unmixed: pd.Series | None = None
) -> pd.DataFrame:
    """Normalise each index to 0 (unmixed) .. 1 (random mixture): ``(x - x_u) / (x_m - x_u)``.

    ``unmixed`` defaults to the first row (the segregated start), ``mixed`` comes from
    :func:`mixed_reference`. These are the curves the T95 fits of Eq. (29) are made on.
    """
    unmixed = df.iloc[0] if unmixed is None else unmixed
    out = pd.DataFrame({"t": df["t"]})
    for col in df.columns:
        if col == "t" or col not in mixed.index or col.endswith("_se") or col.endswith("_raw"):
            continue
        span = mixed[col] - unmixed[col]
        out[col] = (df[col] - unmixed[col]) / span if span != 0 else np.nan
    return out
