"""Zoning and compartmentalisation of grid fields (dissertation chapter 5.2.3, 5.3.1-5.3.2).

* Zones: each occupied cell is classed by the value of one or several variables against
  thresholds.  The seed's sign zones are the special case of one velocity component with a
  tolerance band: +1 (v > tol), 0 (|v| <= tol), -1 (v < -tol), and -2 for empty cells.
* Compartments: connected components (``scipy.ndimage.label``, face connectivity) of equal
  zone value inside each slice normal to the axial axis; every slice is labelled apart,
  as in the seed (compartments never span two slices).
* Overlay: the radial compartment map is the intersection of the Y and Z compartment maps
  (each intersection region labelled again into connected pieces), generalised to any
  number of maps.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import ndimage

from twin_core.compartment.fields import GridFields

EMPTY_ZONE = -2
VARIABLES: tuple[str, ...] = (
    "vx",
    "vy",
    "vz",
    "speed",
    "solid_fraction",
    "occupancy",
    "mobility",
)


def occupied_mask(fields: GridFields, empty_fraction: float = 0.01) -> np.ndarray:
    """Cells holding material: occupancy > ``empty_fraction`` x the largest occupancy."""
    if not 0 <= empty_fraction < 1:
        raise ValueError(f"empty_fraction must be in [0, 1), got {empty_fraction}")
    occ = fields.occupancy
    return occ > empty_fraction * float(occ.max())


def field_variable(fields: GridFields, name: str) -> np.ndarray:
    """One zoning variable of the fields by name (see ``VARIABLES``)."""
    if name in ("vx", "vy", "vz"):
        return fields.velocity[..., "xyz".index(name[1])]
    if name == "speed":
        return np.linalg.norm(fields.velocity, axis=-1)
    if name == "solid_fraction":
        return fields.solid_fraction
    if name == "occupancy":
        return fields.occupancy
    if name == "mobility":
        return cell_mobility(fields)
    raise ValueError(f"variable must be one of {VARIABLES}, got {name!r}")


def cell_mobility(fields: GridFields) -> np.ndarray:
    """Escape rate of each cell (1/s) from the particle transitions at lag tau
    (:mod:`twin_core.compartment.transitions`): k_i = sum_{j != i} C_ij / (n_origins N_i tau),
    N_i the cell's mean particle count; 0 in empty cells.  A kinetic zoning variable: it
    separates a bed that barely moves from the conveyed powder even where their mean
    velocities are alike (the Markov-state lumping of slow and fast states)."""
    tr = fields.transitions
    if tr is None:
        raise ValueError("fields: variable 'mobility' needs the transition_* keys")
    out = np.bincount(tr.src, weights=tr.count, minlength=fields.occupancy.size)
    occ = fields.occupancy.ravel()
    k = np.where(occ > 0, out / (tr.origins * tr.lag_s * np.maximum(occ, 1e-300)), 0.0)
    return k.reshape(fields.shape)


def sign_zones(values: np.ndarray, tol: float, mask: np.ndarray) -> np.ndarray:
    """Sign zones with a tolerance band (seed 5.2.3): +1 if v > tol, -1 if v < -tol, else 0.

    Cells outside ``mask`` get -2 (empty).  Returns int8 of the shape of ``values``.
    """
    if tol < 0:
        raise ValueError(f"tol must be >= 0, got {tol}")
    z = np.zeros(values.shape, dtype=np.int8)
    z[values > tol] = 1
    z[values < -tol] = -1
    z[~mask] = EMPTY_ZONE
    return z


def threshold_zones(
    values: np.ndarray, thresholds: Sequence[float], mask: np.ndarray
) -> np.ndarray:
    """Zones by several thresholds: zone k if thresholds[k-1] < v <= thresholds[k].

    Zones run 0..len(thresholds); empty cells get -2.  With thresholds (-tol, tol) this is
    :func:`sign_zones` shifted by one.
    """
    th = np.asarray(thresholds, dtype=float)
    if th.ndim != 1 or np.any(np.diff(th) <= 0):
        raise ValueError(f"thresholds must be strictly increasing, got {list(th)}")
    z = np.digitize(values, th, right=True).astype(np.int16)
    z[~mask] = EMPTY_ZONE
    return z


def combine_zones(zone_maps: Sequence[np.ndarray]) -> np.ndarray:
    """Combine zone maps of several variables into one code per distinct tuple of zones.

    A cell empty in any map is empty (-2).  Codes are 0..n-1 in lexicographic tuple order.
    """
    if len(zone_maps) == 0:
        raise ValueError("zone_maps must hold at least one map")
    shape = zone_maps[0].shape
    for k, z in enumerate(zone_maps):
        if z.shape != shape:
            raise ValueError(f"zone_maps[{k}] has shape {z.shape}, expected {shape}")
    empty = np.zeros(shape, dtype=bool)
    for z in zone_maps:
        empty |= z == EMPTY_ZONE
    stack = np.stack([z.ravel() for z in zone_maps], axis=1)
    _, inv = np.unique(stack, axis=0, return_inverse=True)
    out = inv.reshape(shape).astype(np.int32)
    out[empty] = EMPTY_ZONE
    # renumber the non-empty codes compactly
    vals = np.unique(out[~empty])
    remap = np.full(int(out.max(initial=0)) + 1, EMPTY_ZONE, dtype=np.int32)
    remap[vals] = np.arange(vals.size, dtype=np.int32)
    out[~empty] = remap[out[~empty]]
    return out


def slice_components(zones: np.ndarray, axis: int = 0, connected: bool = True) -> np.ndarray:
    """Compartment map: connected components of equal zone inside each slice normal to ``axis``
    (connectivity by faces, 4-neighbours in the slice); with ``connected=False`` all cells of
    one zone in a slice form one compartment (a kinetic lumping, where cells of like behaviour
    need not touch).

    Returns int32 labels 0..n-1 numbered slice by slice (slice 0 first), -1 for empty cells.
    """
    if zones.ndim != 3:
        raise ValueError(f"zones must be 3-D, got shape {zones.shape}")
    z = np.moveaxis(zones, axis, 0)
    labels = np.full(z.shape, -1, dtype=np.int32)
    nxt = 0
    for i in range(z.shape[0]):
        sl = z[i]
        for value in np.unique(sl[sl != EMPTY_ZONE]):
            same = sl == value
            lab, n = ndimage.label(same) if connected else (same.astype(np.int32), 1)
            hit = lab > 0
            labels[i][hit] = lab[hit] - 1 + nxt
            nxt += n
    return np.moveaxis(labels, 0, axis)


def quantile_thresholds(values: np.ndarray, mask: np.ndarray, classes: int) -> list[float]:
    """Thresholds splitting the occupied cells into ``classes`` classes of equal cell count
    (duplicate quantiles removed)."""
    if classes < 1:
        raise ValueError(f"classes must be >= 1, got {classes}")
    q = np.quantile(values[mask], np.linspace(0.0, 1.0, classes + 1)[1:-1]) if mask.any() else []
    return [float(v) for v in np.unique(q)]


def overlay_maps(maps: Sequence[np.ndarray], axis: int = 0) -> np.ndarray:
    """Overlay compartment maps (seed 5.3.1): each intersection region of the maps, split into
    its connected pieces per slice, becomes one compartment.  -1 (empty) wins."""
    codes = combine_zones([np.where(m < 0, EMPTY_ZONE, m) for m in maps])
    return slice_components(codes, axis=axis)


def compartment_slices(labels: np.ndarray, axis: int = 0) -> np.ndarray:
    """Slice index (along ``axis``) of every compartment 0..n-1 of a slice-wise map."""
    n = int(labels.max()) + 1
    idx = np.indices(labels.shape)[axis]
    out = np.full(n, -1, dtype=np.int64)
    hit = labels >= 0
    out[labels[hit]] = idx[hit]
    return out


def merge_small(labels: np.ndarray, min_cells: int, axis: int = 0) -> np.ndarray:
    """Merge compartments of fewer than ``min_cells`` cells into the neighbour of the same
    slice with which they share the most faces (repeated until none is left or an isolated
    one remains); labels are renumbered compactly, slice by slice.

    Zoning noisy DEM fields leaves many one-cell compartments; this is the usual clean-up
    of compartment maps (Tajssoleiman et al. 2019, the seed's ref. [49]).
    """
    if min_cells < 1:
        raise ValueError(f"min_cells must be >= 1, got {min_cells}")
    lab = np.moveaxis(labels, axis, 0).copy()
    for _ in range(64):
        n = int(lab.max()) + 1
        if n <= 0:
            break
        size = np.bincount(lab[lab >= 0], minlength=n)
        small = size < min_cells
        if not small.any():
            break
        pairs = []
        for ax in (1, 2):
            a = np.moveaxis(lab, ax, 0)
            p, q = a[:-1].ravel(), a[1:].ravel()
            ok = (p >= 0) & (q >= 0) & (p != q)
            pairs.append(np.stack([p[ok], q[ok]], 1))
            pairs.append(np.stack([q[ok], p[ok]], 1))
        pr = np.concatenate(pairs)
        pr = pr[small[pr[:, 0]]]
        if pr.size == 0:
            break
        key, cnt = np.unique(pr, axis=0, return_counts=True)
        # prefer the neighbour sharing most faces, then the larger neighbour
        order = np.lexsort((-size[key[:, 1]], -cnt, key[:, 0]))
        key = key[order]
        first = np.concatenate([[True], key[1:, 0] != key[:-1, 0]])
        target = np.arange(n)
        src, dst = key[first, 0], key[first, 1]
        # do not merge two small compartments into each other in the same pass
        keep = ~(small[dst] & (dst < src))
        target[src[keep]] = dst[keep]
        # resolve chains a -> b -> c
        for _ in range(32):
            nt = target[target]
            if np.array_equal(nt, target):
                break
            target = nt
        hit = lab >= 0
        lab[hit] = target[lab[hit]]
    # compact renumbering slice by slice
    out = np.full(lab.shape, -1, dtype=np.int32)
    nxt = 0
    for i in range(lab.shape[0]):
        sl = lab[i]
        vals = np.unique(sl[sl >= 0])
        remap = {int(v): nxt + k for k, v in enumerate(vals)}
        for v, r in remap.items():
            out[i][sl == v] = r
        nxt += vals.size
    return np.moveaxis(out, 0, axis)
