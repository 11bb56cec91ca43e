"""Mixing indices over a sequence of particle frames.

A frame is a :class:`twin_core.dem.frames.Frame` (``t`` in s, ``ids``, ``types``, ``radii``,
``positions`` and ``velocities`` ``(N, 3)``, SI) -- the indices read every attribute but the
velocities. Frames are aligned by particle id to the first frame, which is the reference
("initial, segregated") state of VRR, NDM and SM.
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
from twin_core.mixing.grid import GridSpec, cell_counts, occupied_cells
from twin_core.mixing.neighbours import contacts_from_positions, nearest_neighbours

#: the seed's fifteen indices (section 4.3.1), in the order of its Figure 4.4
INDEX_NAMES: tuple[str, ...] = (
    "LI", "RSD", "VRR", "VBBC", "ESI", "ME", "DM", "MSI", "SM", "AH", "NDM", "NNM", "PS", "CN", "SI",
)  # fmt: skip

#: direction of mixing progress: +1 the index grows when mixing, -1 it falls
DIRECTION: dict[str, int] = {
    "LI": 1, "RSD": -1, "VRR": 1, "VBBC": -1, "ESI": -1, "ME": 1, "DM": 1, "MSI": -1, "SM": 1,
    "AH": -1, "NDM": 1, "NNM": 1, "PS": 1, "CN": 1, "SI": -1,
}  # fmt: skip


@dataclass
class MixingConfig:
    """Options of :func:`compute_indices`.

    ``box``: period length per axis for periodic axes, ``inf`` otherwise (e.g.
    ``(0.04, inf, inf)`` for the blender section). ``tracer``: type id of the "A"/red particles
    (default: the smallest type id). ``sm_pairs``: ``None`` evaluates the Siiria index exactly
    (O(N^2)), an integer uses the sampled estimator with that many pairs (and reports its
    standard error in ``SM_se``). ``sm_g``: ``None`` takes ``5 / L`` with ``L`` the diagonal of
    the grid box (Siiria's rule ``g L < 10``).
    """

    grid: GridSpec
    box: tuple[float, float, float] = (np.inf, np.inf, np.inf)
    tracer: int | None = None
    contact_tolerance: float = 0.02
    n_neighbours: int = 12
    ah_axis: int = 2
    sm_R: float = 0.87
    sm_g: float | None = None
    sm_pairs: int | None = None
    ndm_random_pairs: int = 20_000
    seed: int = 0


def _parse_indices(indices: str | Sequence[str]) -> list[str]:
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
    ids = np.asarray(frame.ids)
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


def _common_subset(frames: list[Frame]) -> tuple[list[Frame], int]:
    """Frames restricted to the particle ids present in every frame, and the number dropped."""
    common = np.asarray(frames[0].ids)
    for f in frames[1:]:
        common = np.intersect1d(common, np.asarray(f.ids))
    out = []
    for f in frames:
        keep = np.isin(np.asarray(f.ids), common)
        out.append(
            Frame(float(f.t), np.asarray(f.ids)[keep], np.asarray(f.types)[keep],
                  np.asarray(f.radii)[keep], np.asarray(f.positions)[keep],
                  np.asarray(f.velocities)[keep])
        )  # fmt: skip
    return out, len(frames[0].ids) - len(common)


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
        raise ValueError("config is required (at least a GridSpec)")
    names = _parse_indices(indices)
    dropped = 0
    if allow_lost:
        frames = list(frames)
        if frames:
            frames, dropped = _common_subset(frames)
    frames = iter(frames)
    try:
        first = next(frames)
    except StopIteration:
        raise ValueError("frames is empty") from None
    order_ids = np.sort(np.asarray(first.ids))
    if len(np.unique(order_ids)) != len(order_ids):
        raise ValueError("particle ids of the first frame are not unique")
    types0, radii0, pos0 = _aligned(first, order_ids)
    tracer = int(np.min(types0)) if config.tracer is None else int(config.tracer)
    if not np.any(types0 == tracer) or np.all(types0 == tracer):
        raise ValueError(f"tracer type {tracer} must be present together with another type")
    box = np.asarray(config.box, float)
    grid = config.grid
    state = _Reference(pos0, types0, radii0, tracer, grid, box, config, names)
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
    return df


class _Reference:
    """Reference-frame quantities (initial contacts, random pairs, VRR variance)."""

    def __init__(self, pos0, types0, radii0, tracer, grid, box, config, names):
        self.tracer, self.grid, self.box, self.cfg, self.names = tracer, grid, box, config, names
        self.pos0 = pos0
        self.type_ids = [tracer] + sorted(set(np.unique(types0).tolist()) - {tracer})
        rng = np.random.default_rng(config.seed)
        if "VRR" in names:
            a, n = self._an(pos0, types0)
            self.var0 = vi.cell_variance(a, n)
        if "NDM" in names:
            pairs = contacts_from_positions(pos0, radii0, box, config.contact_tolerance)
            if len(pairs) == 0:
                raise ValueError("no contacts in the first frame: NDM needs a packed bed")
            self.nb_pairs = pairs
            self.d_contact = float(np.mean(radii0[pairs[:, 0]] + radii0[pairs[:, 1]]))
            self.rand_pairs = di.random_pairs(len(pos0), config.ndm_random_pairs, rng)
        if "SM" in names:
            diag = float(np.linalg.norm(np.subtract(grid.hi, grid.lo)))
            self.sm_g = config.sm_g if config.sm_g is not None else 5.0 / diag
            if config.sm_pairs is not None:
                self.sm_pairs = di.random_pairs(len(pos0), int(config.sm_pairs), rng)

    def _an(self, pos, types):
        counts = cell_counts(self.grid, pos, types, self.type_ids)
        keep = occupied_cells(self.grid, counts)
        a = counts[keep, 0]
        n = counts[keep].sum(axis=1)
        return a, n

    def row(self, t, types, radii, pos) -> dict:
        names, cfg, tracer, box = self.names, self.cfg, self.tracer, self.box
        out: dict = {"t": float(t)}
        counts = cell_counts(self.grid, pos, types, self.type_ids)
        keep = occupied_cells(self.grid, counts)
        kc = counts[keep]
        a, n = kc[:, 0], kc.sum(axis=1)
        if "LI" in names:
            out["LI"] = vi.lacey(a, n)
        if "RSD" in names:
            out["RSD"] = vi.relative_standard_deviation(a, n)
        if "VRR" in names:
            s = vi.cell_variance(a, n)
            out["VRR"] = self.var0 / s if s > 0 else np.inf
        if "VBBC" in names:
            out["VBBC"] = vi.vbbc_variance(a, n - a)
        if "ESI" in names:
            out["ESI"] = vi.intensity_of_segregation(a, n)
        if "ME" in names:
            out["ME"] = vi.mixing_entropy(kc)
        if "DM" in names:
            out["DM"] = vi.degree_of_mixedness(a, n)
        if "MSI" in names:
            out["MSI"] = vi.mixing_segregation_index(a, n)
        if "SM" in names:
            if cfg.sm_pairs is None:
                out["SM"] = di.siiria_index(self.pos0, pos, cfg.sm_R, self.sm_g, box)
            else:
                out["SM"], out["SM_se"] = di.siiria_index_sampled(
                    self.pos0, pos, self.sm_pairs, cfg.sm_R, self.sm_g, box
                )
        if "AH" in names:
            for axis, label in enumerate("xyz"):
                out[f"AH_{label}"] = di.average_height(
                    pos[:, axis], types, tracer, self.grid.lo[axis]
                )
            out["AH"] = out[f"AH_{'xyz'[cfg.ah_axis]}"]
        if "NDM" in names:
            out["NDM"] = di.neighbour_distance_index(
                pos, self.nb_pairs, self.rand_pairs, self.d_contact, box
            )
        if "NNM" in names:
            nb = nearest_neighbours(pos, cfg.n_neighbours, box)
            out["NNM"] = ci.nearest_neighbour_index(nb, types)
        if {"PS", "CN", "SI"} & set(names):
            pairs = contacts_from_positions(pos, radii, box, cfg.contact_tolerance)
            if "PS" in names:
                out["PS"] = ci.particle_scale_index(pairs, types, tracer)
            if "CN" in names:
                out["CN"] = ci.coordination_number_index(pairs, types, tracer)
            if "SI" in names:
                out["SI"] = ci.segregation_index(pairs, types, tracer)
        return out


def shuffled_frame(frame: Frame, seed: int | np.random.Generator = 0) -> Frame:
    """The frame with particle positions (and their velocities) randomly permuted among the
    particles.

    This is the random mixture of the same bed (same cells, same contacts, same geometry):
    the "mixed" reference of every index at once.
    """
    rng = np.random.default_rng(seed)
    perm = rng.permutation(len(frame.ids))
    return Frame(
        float(frame.t), np.asarray(frame.ids), np.asarray(frame.types),
        np.asarray(frame.radii), np.asarray(frame.positions)[perm],
        np.asarray(frame.velocities)[perm],
    )  # fmt: skip


def mixed_reference(
    frame: Frame,
    indices: str | Sequence[str] = "all",
    config: MixingConfig | None = None,
    n_shuffles: int = 5,
    seed: int = 0,
) -> pd.Series:
    """Expected value of each index for a random mixture of the bed in ``frame`` (mean of
    ``n_shuffles`` random permutations of positions, each evaluated against ``frame`` as the
    reference state). VBBC is reported as the ratio of the random to the initial raw value."""
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
