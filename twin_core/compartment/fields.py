"""Time-averaged DEM grid fields: the input of the compartment model.

File format (``.npz``, one file per DEM run; all arrays SI):

==================  ===============  ==================================================
key                 shape            meaning
==================  ===============  ==================================================
``x_edges``         (nx+1,)          cell edges along x (m), strictly increasing
``y_edges``         (ny+1,)          cell edges along y (m)
``z_edges``         (nz+1,)          cell edges along z (m)
``velocity``        (nx,ny,nz,3)     time-averaged particle velocity (m/s)
``solid_fraction``  (nx,ny,nz)       time-averaged solid volume fraction (-), >= 0 (a
                                     centre-counting estimate may pass 1 in small cells)
``occupancy``       (nx,ny,nz)       time-averaged particle count in the cell (-)
``crossings_x``     (nx,ny,nz,2)     particles crossing the + face of cell (i,j,k):
``crossings_y``                      [...,0] in the + direction, [...,1] in the -
``crossings_z``                      direction; periodic axes wrap, the last face of a
                                     closed axis is 0 (optional keys, all three or none)
``duration_s``      ()               averaging duration (s), > 0
``particle_mass_kg``  ()             mass of one particle (kg), > 0
``periodic``        (3,)             bool, which axes are periodic
``transition_*``    (m,) / ()        optional: cell-to-cell particle transitions at a lag
                                     (``src``, ``dst`` flat cell indices, ``shift``
                                     periods crossed, ``count``, ``lag_s``, ``origins``;
                                     :mod:`twin_core.compartment.transitions`)
==================  ===============  ==================================================

:func:`load_fields` reads and validates such a file, :func:`validate_fields` validates a
mapping already in memory and :func:`save_fields` writes one.  Every problem raises
``ValueError`` naming the key, the expected and the found shape or value.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from twin_core.compartment.transitions import (
    CellTransitions,
    mirror_transitions,
    validate_transitions,
)

REQUIRED_KEYS: tuple[str, ...] = (
    "x_edges",
    "y_edges",
    "z_edges",
    "velocity",
    "solid_fraction",
    "occupancy",
    "duration_s",
    "particle_mass_kg",
    "periodic",
)
CROSSING_KEYS: tuple[str, ...] = ("crossings_x", "crossings_y", "crossings_z")


@dataclass(frozen=True)
class GridFields:
    """Validated time-averaged grid fields of one DEM run (see module docstring)."""

    x_edges: np.ndarray
    y_edges: np.ndarray
    z_edges: np.ndarray
    velocity: np.ndarray
    solid_fraction: np.ndarray
    occupancy: np.ndarray
    duration_s: float
    particle_mass_kg: float
    periodic: tuple[bool, bool, bool]
    crossings: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    transitions: CellTransitions | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        """Number of cells (nx, ny, nz)."""
        return tuple(int(s) for s in self.solid_fraction.shape)  # type: ignore[return-value]

    @property
    def edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (self.x_edges, self.y_edges, self.z_edges)

    @property
    def widths(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cell widths along x, y, z (m)."""
        return tuple(np.diff(e) for e in self.edges)  # type: ignore[return-value]

    @property
    def centers(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cell centres along x, y, z (m)."""
        return tuple(0.5 * (e[1:] + e[:-1]) for e in self.edges)  # type: ignore[return-value]

    @property
    def cell_volume(self) -> np.ndarray:
        """Cell volumes (nx,ny,nz) in m^3."""
        dx, dy, dz = self.widths
        return dx[:, None, None] * dy[None, :, None] * dz[None, None, :]

    def face_area(self, axis: int) -> np.ndarray:
        """Area (m^2) of the + face normal to ``axis`` of every cell, shape (nx,ny,nz)."""
        dx, dy, dz = self.widths
        w = [dx[:, None, None], dy[None, :, None], dz[None, None, :]]
        a = np.ones(self.shape)
        for ax in range(3):
            if ax != axis:
                a = a * w[ax]
        return a

    @property
    def holdup_kg(self) -> np.ndarray:
        """Mean mass of particles in each cell (kg): occupancy x particle mass."""
        return self.occupancy * self.particle_mass_kg

    @property
    def has_crossings(self) -> bool:
        return self.crossings is not None

    def to_dict(self) -> dict[str, Any]:
        """Arrays keyed as in the file format."""
        d: dict[str, Any] = {
            "x_edges": self.x_edges,
            "y_edges": self.y_edges,
            "z_edges": self.z_edges,
            "velocity": self.velocity,
            "solid_fraction": self.solid_fraction,
            "occupancy": self.occupancy,
            "duration_s": np.float64(self.duration_s),
            "particle_mass_kg": np.float64(self.particle_mass_kg),
            "periodic": np.asarray(self.periodic, dtype=bool),
        }
        if self.crossings is not None:
            for key, c in zip(CROSSING_KEYS, self.crossings):
                d[key] = c
        if self.transitions is not None:
            d.update(self.transitions.to_dict())
        return d


def _array(data: Mapping[str, Any], key: str) -> np.ndarray:
    try:
        arr = np.asarray(data[key])
    except KeyError:
        raise ValueError(
            f"fields: missing key {key!r} (required: {', '.join(REQUIRED_KEYS)})"
        ) from None
    if arr.dtype == object:
        raise ValueError(f"fields: key {key!r} must be numeric, got dtype object")
    return arr


def _finite(key: str, arr: np.ndarray) -> None:
    if not np.all(np.isfinite(arr)):
        n = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise ValueError(f"fields: key {key!r} has {n} non-finite values")


def validate_fields(data: Mapping[str, Any]) -> GridFields:
    """Validate a mapping in the npz grid-field format and return :class:`GridFields`.

    Checks presence, dtype, shape (against the edge arrays), finiteness, monotone edges,
    ranges (solid fraction, occupancy and crossings >= 0, duration and particle
    mass > 0) and the closed-axis rule (the last + face of a non-periodic axis carries no
    crossings).  Raises ``ValueError`` naming the key.
    """
    edges = []
    for key in ("x_edges", "y_edges", "z_edges"):
        e = _array(data, key).astype(float)
        if e.ndim != 1 or e.size < 2:
            raise ValueError(
                f"fields: key {key!r} must be 1-D with >= 2 edges, got shape {e.shape}"
            )
        _finite(key, e)
        if np.any(np.diff(e) <= 0):
            raise ValueError(f"fields: key {key!r} must be strictly increasing")
        edges.append(e)
    shape = tuple(e.size - 1 for e in edges)

    velocity = _array(data, "velocity").astype(float)
    if velocity.shape != (*shape, 3):
        raise ValueError(
            f"fields: key 'velocity' must have shape {(*shape, 3)} (from the edges), "
            f"got {velocity.shape}"
        )
    _finite("velocity", velocity)
    sf = _array(data, "solid_fraction").astype(float)
    if sf.shape != shape:
        raise ValueError(f"fields: key 'solid_fraction' must have shape {shape}, got {sf.shape}")
    _finite("solid_fraction", sf)
    if sf.min() < 0:
        raise ValueError(f"fields: key 'solid_fraction' must be >= 0, got min {sf.min()}")
    occ = _array(data, "occupancy").astype(float)
    if occ.shape != shape:
        raise ValueError(f"fields: key 'occupancy' must have shape {shape}, got {occ.shape}")
    _finite("occupancy", occ)
    if occ.min() < 0:
        raise ValueError(f"fields: key 'occupancy' must be >= 0, got min {occ.min()}")

    duration = _array(data, "duration_s")
    if duration.size != 1:
        raise ValueError(f"fields: key 'duration_s' must be a scalar, got shape {duration.shape}")
    duration_s = float(duration.reshape(()))
    if not np.isfinite(duration_s) or duration_s <= 0:
        raise ValueError(f"fields: key 'duration_s' must be > 0, got {duration_s}")
    pm = _array(data, "particle_mass_kg")
    if pm.size != 1:
        raise ValueError(f"fields: key 'particle_mass_kg' must be a scalar, got shape {pm.shape}")
    particle_mass = float(pm.reshape(()))
    if not np.isfinite(particle_mass) or particle_mass <= 0:
        raise ValueError(f"fields: key 'particle_mass_kg' must be > 0, got {particle_mass}")
    per = _array(data, "periodic")
    if per.shape != (3,):
        raise ValueError(f"fields: key 'periodic' must have shape (3,), got {per.shape}")
    periodic = tuple(bool(p) for p in per)

    present = [k for k in CROSSING_KEYS if k in data]
    crossings = None
    if present:
        if len(present) != 3:
            missing = sorted(set(CROSSING_KEYS) - set(present))
            raise ValueError(f"fields: crossing keys come as a set of three; missing {missing}")
        cs = []
        for axis, key in enumerate(CROSSING_KEYS):
            c = _array(data, key).astype(float)
            if c.shape != (*shape, 2):
                raise ValueError(
                    f"fields: key {key!r} must have shape {(*shape, 2)}, got {c.shape}"
                )
            _finite(key, c)
            if c.min() < 0:
                raise ValueError(f"fields: key {key!r} must be >= 0, got min {c.min()}")
            if not periodic[axis]:
                last = np.take(c, shape[axis] - 1, axis=axis)
                if np.any(last != 0):
                    raise ValueError(
                        f"fields: key {key!r}: axis {axis} is closed, so the last face must "
                        f"carry no crossings (found {float(last.sum())})"
                    )
            cs.append(c)
        crossings = (cs[0], cs[1], cs[2])
    return GridFields(
        x_edges=edges[0],
        y_edges=edges[1],
        z_edges=edges[2],
        velocity=velocity,
        solid_fraction=sf,
        occupancy=occ,
        duration_s=duration_s,
        particle_mass_kg=particle_mass,
        periodic=periodic,  # type: ignore[arg-type]
        crossings=crossings,
        transitions=validate_transitions(data, shape),  # type: ignore[arg-type]
    )


def load_fields(path: str | Path) -> GridFields:
    """Read and validate a grid-field ``.npz`` file (format in the module docstring)."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"fields file {str(path)!r} does not exist")
    with np.load(path, allow_pickle=False) as npz:
        data = {k: npz[k] for k in npz.files}
    return validate_fields(data)


def save_fields(path: str | Path, fields: GridFields) -> Path:
    """Write ``fields`` to ``path`` as a compressed ``.npz`` in the documented format."""
    path = Path(path)
    np.savez_compressed(path, **fields.to_dict())
    return path


def mirror_axis(fields: GridFields, axis: int = 0) -> GridFields:
    """The same fields seen with ``axis`` reversed (x -> x0 + x1 - x): arrays flipped, the
    velocity component negated, and the crossings re-indexed (the + face of a mirrored cell is
    the - face of the original one, i.e. the + face of its - neighbour, with the directions
    swapped).  Used to orient the axial axis along the net flow."""
    if axis not in (0, 1, 2):
        raise ValueError(f"axis must be 0, 1 or 2, got {axis}")
    e = fields.edges[axis]
    new_e = e[0] + e[-1] - e[::-1]
    edges = list(fields.edges)
    edges[axis] = new_e
    vel = np.flip(fields.velocity, axis=axis).copy()
    vel[..., axis] *= -1.0
    crossings = None
    if fields.crossings is not None:
        cs = []
        for a, c in enumerate(fields.crossings):
            if a == axis:
                c = np.flip(np.roll(c, 1, axis=axis), axis=axis)[..., ::-1]
                if not fields.periodic[axis]:
                    idx = [slice(None)] * 4
                    idx[axis] = -1
                    c = c.copy()
                    c[tuple(idx)] = 0.0
            else:
                c = np.flip(c, axis=axis)
            cs.append(np.ascontiguousarray(c))
        crossings = (cs[0], cs[1], cs[2])
    return GridFields(
        x_edges=edges[0],
        y_edges=edges[1],
        z_edges=edges[2],
        velocity=vel,
        solid_fraction=np.flip(fields.solid_fraction, axis=axis).copy(),
        occupancy=np.flip(fields.occupancy, axis=axis).copy(),
        duration_s=fields.duration_s,
        particle_mass_kg=fields.particle_mass_kg,
        periodic=fields.periodic,
        crossings=crossings,
        transitions=None
        if fields.transitions is None
        else mirror_transitions(fields.transitions, fields.shape, axis, fields.periodic[axis]),
    )
