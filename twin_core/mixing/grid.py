"""Sampling grids for the grid-based (variance) mixing indices and the cell fields.

The seed (section 4.4.1, after Boukouvala et al.) divides the periodic blender section into
1 x 8 x 8 cells (X, Y, Z) and drops every cell that holds fewer than 50 % of the average
number of particles per cell (``0.5 * N / n_cells``): such cells are empty or incomplete
samples near the free surface and only add noise. Drums and cylindrical mixers are sampled in
cylindrical bins instead (``CylindricalGrid``: angle x radius x axial position), and thin slabs
of either grid (``slab``) give 2-D slices.

Two grids share one interface: ``n_cells``, ``shape``, ``cell_volumes()``, ``cell_centres()``,
``cell_index(positions, box)`` (flat index, -1 where not sampled) and ``shares(positions,
radii, box)`` (fractional mapping: the volume of each sphere inside each cell). The minimum-fill
rule generalises to cells of unequal size: a cell is kept when it holds at least ``min_fill``
times its volume's share of the whole amount.

Particle amounts per cell (:func:`cell_amounts`) are counts (``weight="number"``) or particle
volumes (``weight="volume"``), each particle in the cell of its centre (``mapping="point"``) or
split over the cells it overlaps by volume (``mapping="fractional"``; exact sphere-box volumes
for Cartesian cells, :func:`twin_core.mixing.overlap.box_volume`, and a quadrature of the ball
for cylindrical bins, :func:`twin_core.mixing.overlap.ball_quadrature`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from twin_core.mixing.overlap import ball_quadrature, box_volume

WEIGHTS = ("number", "volume")
MAPPINGS = ("point", "fractional")
_AXES = "xyz"


def sphere_volumes(radii: np.ndarray) -> np.ndarray:
    """``4/3 pi r^3`` of each particle."""
    return 4.0 / 3.0 * math.pi * np.asarray(radii, float) ** 3


def _check_fill(min_fill: float) -> None:
    if not 0.0 <= min_fill < 1.0:
        raise ValueError(f"min_fill must be in [0, 1), got {min_fill!r}")


def _shape3(shape, text: str = "shape") -> tuple[int, int, int]:
    if len(shape) != 3 or any(int(n) < 1 for n in shape):
        raise ValueError(f"{text} must be three positive integers, got {shape!r}")
    return tuple(int(n) for n in shape)  # type: ignore[return-value]


def _periodic_axes(lo: np.ndarray, hi: np.ndarray, box) -> np.ndarray:
    """Axes on which the grid spans exactly one period of ``box`` (wrapped, not clipped)."""
    if box is None:
        return np.zeros(3, np.int64)
    b = np.asarray(box, float)
    span = hi - lo
    return (np.isfinite(b) & (np.abs(span - b) <= 1e-9 * np.abs(b))).astype(np.int64)


@dataclass(frozen=True)
class GridSpec:
    """A regular grid of ``shape = (nx, ny, nz)`` cells over the box ``[lo, hi]`` (m).

    ``min_fill`` is the fraction of the mean occupancy (amount per cell over *all* cells) below
    which a cell is excluded from the variance indices (seed: 0.5). ``clip=True`` puts particles
    outside the box into the nearest edge cell (a grid over the whole domain); ``clip=False``
    leaves them unsampled (a slab or a sub-volume). An axis on which the grid spans exactly the
    period of the frames' box wraps around.
    """

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    shape: tuple[int, int, int] = (1, 8, 8)
    min_fill: float = 0.5
    clip: bool = True

    def __post_init__(self) -> None:
        _shape3(self.shape)
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
        _check_fill(self.min_fill)

    @classmethod
    def parse(cls, text: str, lo, hi, min_fill: float = 0.5) -> GridSpec:
        """Build from a string such as ``"1x8x8"``."""
        return cls(tuple(map(float, lo)), tuple(map(float, hi)), _parse_shape(text), min_fill)

    @property
    def n_cells(self) -> int:
        return int(np.prod(self.shape))

    @property
    def axis_labels(self) -> tuple[str, str, str]:
        return ("x", "y", "z")

    def cell_volumes(self) -> np.ndarray:
        """Geometric volume of each cell (flat order)."""
        size = (np.asarray(self.hi) - np.asarray(self.lo)) / np.asarray(self.shape)
        return np.full(self.n_cells, float(np.prod(size)))

    def cell_centres(self) -> np.ndarray:
        """Centre (x, y, z) of each cell, flat order ``(n_cells, 3)``."""
        lo, hi, n = np.asarray(self.lo), np.asarray(self.hi), np.asarray(self.shape)
        axes = [lo[k] + (np.arange(n[k]) + 0.5) * (hi[k] - lo[k]) / n[k] for k in range(3)]
        mesh = np.meshgrid(*axes, indexing="ij")
        return np.stack([m.ravel() for m in mesh], axis=1)

    def cell_index(self, positions: np.ndarray, box=None) -> np.ndarray:
        """Flat cell index of each position: clipped to the edge cells (``clip``) or -1 outside;
        periodic axes (see the class docstring) wrap."""
        pos = np.asarray(positions, float)
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        shape = np.asarray(self.shape)
        ijk = np.floor((pos - lo) / (hi - lo) * shape).astype(np.int64)
        periodic = _periodic_axes(lo, hi, box).astype(bool)
        ijk = np.where(periodic, np.mod(ijk, shape), ijk)
        if self.clip:
            ijk = np.clip(ijk, 0, shape - 1)
            return np.ravel_multi_index(ijk.T, self.shape)
        inside = np.all((ijk >= 0) & (ijk < shape), axis=1)
        flat = np.full(len(pos), -1, np.int64)
        flat[inside] = np.ravel_multi_index(ijk[inside].T, self.shape)
        return flat

    def shares(self, positions: np.ndarray, radii: np.ndarray, box=None):
        """Fractional mapping: ``(particle, cell, volume)`` of every part of every sphere inside a
        cell (exact sphere-box volumes; with ``clip`` the edge cells extend to infinity)."""
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        return _box_shares(
            np.ascontiguousarray(positions, dtype=np.float64),
            np.ascontiguousarray(radii, dtype=np.float64),
            lo,
            (hi - lo) / np.asarray(self.shape),
            np.asarray(self.shape, np.int64),
            _periodic_axes(lo, hi, box),
            self.clip,
        )

    def slab(self, axis: int | str, centre: float, thickness: float) -> GridSpec:
        """The 2-D slice ``|x_axis - centre| < thickness / 2`` of this grid (one cell thick;
        particles outside it are not sampled)."""
        k = _axis(axis)
        if not thickness > 0:
            raise ValueError(f"thickness must be > 0, got {thickness!r}")
        lo, hi, shape = list(self.lo), list(self.hi), list(self.shape)
        lo[k], hi[k], shape[k] = centre - thickness / 2, centre + thickness / 2, 1
        return replace(self, lo=tuple(lo), hi=tuple(hi), shape=tuple(shape), clip=False)


@dataclass(frozen=True)
class CylindricalGrid:
    """Cylindrical bins around an axis: ``shape = (n_theta, n_r, n_axial)`` cells over the
    angle (from ``theta0``, counter-clockwise about the axis), the radius ``0 .. r_max`` and the
    axial range ``lo .. hi`` (m).

    ``axis`` is the cylinder axis (0, 1, 2 or "x", "y", "z"), ``centre`` its position in the two
    other coordinates (in axis order). ``radial="area"`` makes rings of equal cross-section
    area (equal cell volumes; the DEMToolbox "volume" sampling), ``"radius"`` rings of equal
    width. Particles beyond ``r_max`` or outside ``lo .. hi`` are not sampled.
    """

    centre: tuple[float, float]
    r_max: float
    lo: float
    hi: float
    shape: tuple[int, int, int] = (8, 4, 8)
    axis: int | str = 2
    radial: str = "area"
    theta0: float = 0.0
    min_fill: float = 0.5

    def __post_init__(self) -> None:
        _shape3(self.shape)
        object.__setattr__(self, "axis", _axis(self.axis))
        if len(self.centre) != 2 or not np.all(np.isfinite(self.centre)):
            raise ValueError(f"centre must be two finite numbers, got {self.centre!r}")
        if not (np.isfinite(self.r_max) and self.r_max > 0):
            raise ValueError(f"r_max must be > 0, got {self.r_max!r}")
        if not (np.isfinite(self.lo) and np.isfinite(self.hi) and self.hi > self.lo):
            raise ValueError(f"hi must exceed lo, got lo={self.lo!r}, hi={self.hi!r}")
        if self.radial not in ("area", "radius"):
            raise ValueError(f"radial must be 'area' or 'radius', got {self.radial!r}")
        _check_fill(self.min_fill)

    @property
    def n_cells(self) -> int:
        return int(np.prod(self.shape))

    @property
    def axis_labels(self) -> tuple[str, str, str]:
        return ("theta", "r", _AXES[self.axis])

    @property
    def cross_axes(self) -> tuple[int, int]:
        """The two coordinates of the cross-section, in the right-handed order about the axis."""
        return ((self.axis + 1) % 3, (self.axis + 2) % 3)

    def ring_edges(self) -> np.ndarray:
        """Radii of the ring boundaries, ``0 .. r_max``."""
        n_r = self.shape[1]
        if self.radial == "area":
            return self.r_max * np.sqrt(np.arange(n_r + 1) / n_r)
        return self.r_max * np.arange(n_r + 1) / n_r

    def cell_volumes(self) -> np.ndarray:
        n_t, n_r, n_z = self.shape
        edges = self.ring_edges()
        ring = 0.5 * (2 * math.pi / n_t) * np.diff(edges**2) * (self.hi - self.lo) / n_z
        return np.broadcast_to(ring[None, :, None], self.shape).ravel().copy()

    def cell_centres(self) -> np.ndarray:
        """Centre of each cell (mid angle, mid radius, mid axial position) in x, y, z."""
        n_t, n_r, n_z = self.shape
        theta = self.theta0 + (np.arange(n_t) + 0.5) * 2 * math.pi / n_t
        e = self.ring_edges()
        r = 0.5 * (e[:-1] + e[1:])
        z = self.lo + (np.arange(n_z) + 0.5) * (self.hi - self.lo) / n_z
        tt, rr, zz = np.meshgrid(theta, r, z, indexing="ij")
        out = np.empty((self.n_cells, 3))
        a, b = self.cross_axes
        out[:, a] = self.centre[0] + (rr * np.cos(tt)).ravel()
        out[:, b] = self.centre[1] + (rr * np.sin(tt)).ravel()
        out[:, self.axis] = zz.ravel()
        return out

    def polar(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Angle (from ``theta0``, in [0, 2 pi)), radius and axial coordinate of positions."""
        pos = np.asarray(positions, float)
        a, b = self.cross_axes
        dx, dy = pos[:, a] - self.centre[0], pos[:, b] - self.centre[1]
        theta = np.mod(np.arctan2(dy, dx) - self.theta0, 2 * math.pi)
        return theta, np.hypot(dx, dy), pos[:, self.axis]

    def local_axes(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit vectors (radial, tangential, axial) at each position, each ``(N, 3)``."""
        theta, _, _ = self.polar(positions)
        theta = theta + self.theta0
        a, b = self.cross_axes
        n = len(theta)
        e_r, e_t, e_z = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
        e_r[:, a], e_r[:, b] = np.cos(theta), np.sin(theta)
        e_t[:, a], e_t[:, b] = -np.sin(theta), np.cos(theta)
        e_z[:, self.axis] = 1.0
        return e_r, e_t, e_z

    def cell_index(self, positions: np.ndarray, box=None) -> np.ndarray:
        """Flat cell index of each position, -1 outside the cylinder or its axial range."""
        return _cylinder_index(np.ascontiguousarray(positions, dtype=np.float64), *self._args())

    def shares(self, positions: np.ndarray, radii: np.ndarray, box=None):
        """Fractional mapping: ``(particle, cell, volume)`` of the parts of each sphere in each
        bin. A sphere crossing no bin boundary goes whole into its bin. One that crosses
        boundaries away from the axis is split in its local (radial, tangential, axial) frame:
        exact for axial faces and sector planes, the ring faces taken as their tangent planes
        (curvature-corrected when a ring face is the only cut; within 0.1 r / e of the sphere's
        volume otherwise, ``e`` the ring's radius). Within two radii of the axis, or over more
        than two sectors, the sphere is split by
        :func:`twin_core.mixing.overlap.ball_quadrature` (1,536 points, within 1 %)."""
        points, weights = _QUADRATURE
        return _cylinder_shares(
            np.ascontiguousarray(positions, dtype=np.float64),
            np.ascontiguousarray(radii, dtype=np.float64),
            points,
            weights,
            *self._args(),
        )

    def slab(self, axis: int | str, centre: float, thickness: float) -> CylindricalGrid:
        """The cross-section ``|x_axis - centre| < thickness / 2`` (axis = the cylinder axis):
        an (angle, radius) map one bin thick."""
        if _axis(axis) != self.axis:
            raise ValueError(
                f"a cylindrical grid is sliced across its axis {_AXES[self.axis]!r}, got {axis!r}"
            )
        if not thickness > 0:
            raise ValueError(f"thickness must be > 0, got {thickness!r}")
        n_t, n_r, _ = self.shape
        return replace(
            self, lo=centre - thickness / 2, hi=centre + thickness / 2, shape=(n_t, n_r, 1)
        )

    def _args(self):
        a, b = self.cross_axes
        return (
            np.array([a, b, self.axis], np.int64),
            np.asarray(self.centre, float),
            self.theta0,
            self.ring_edges(),
            float(self.lo),
            float(self.hi),
            np.asarray(self.shape, np.int64),
        )


#: the ball quadrature of the cylindrical fractional mapping
_QUADRATURE = ball_quadrature()


def _axis(axis: int | str) -> int:
    if isinstance(axis, str):
        if axis.lower() not in _AXES:
            raise ValueError(f"axis must be x, y or z, got {axis!r}")
        return _AXES.index(axis.lower())
    if axis not in (0, 1, 2):
        raise ValueError(f"axis must be 0, 1 or 2, got {axis!r}")
    return int(axis)


def _parse_shape(text: str) -> tuple[int, int, int]:
    parts = text.lower().split("x")
    try:
        shape = tuple(int(p) for p in parts)
    except ValueError:
        raise ValueError(f"grid must look like '1x8x8', got {text!r}") from None
    if len(shape) != 3:
        raise ValueError(f"grid must have three sizes like '1x8x8', got {text!r}")
    return _shape3(shape, "grid")


@njit(cache=True)
def _box_cells(x, r, lo, width, n, periodic, clip, cells, lower, upper):
    """Cells along one axis overlapped by ``[x - r, x + r]``: their indices and the bounds of
    each cell relative to ``x`` in units of ``r`` (infinite beyond clipped edges). Returns the
    number of cells."""
    first = int(math.floor((x - r - lo) / width))
    last = int(math.floor((x + r - lo) / width))
    if clip and not periodic:
        first, last = min(max(first, 0), n - 1), max(min(last, n - 1), 0)
    m = 0
    for j in range(first, last + 1):
        if not periodic and (j < 0 or j >= n):
            continue
        b0 = (lo + j * width - x) / r
        b1 = (lo + (j + 1) * width - x) / r
        if clip and not periodic:
            if j == 0:
                b0 = -np.inf
            if j == n - 1:
                b1 = np.inf
        cells[m] = j % n
        lower[m] = b0
        upper[m] = b1
        m += 1
    return m


@njit(cache=True)
def _box_shares(pos, radii, lo, width, shape, periodic, clip):
    n = pos.shape[0]
    cap = 8 * n + 16
    part = np.empty(cap, np.int64)
    cell = np.empty(cap, np.int64)
    vol = np.empty(cap)
    m = 0
    span = 2 * int(math.ceil(radii.max() / width.min())) + 3 if n else 3
    cells = np.empty((3, span), np.int64)
    lower = np.empty((3, span))
    upper = np.empty((3, span))
    counts = np.empty(3, np.int64)
    for p in range(n):
        r = radii[p]
        for a in range(3):
            counts[a] = _box_cells(pos[p, a], r, lo[a], width[a], shape[a], periodic[a], clip,
                                   cells[a], lower[a], upper[a])  # fmt: skip
        total = counts[0] * counts[1] * counts[2]
        if m + total > cap:
            cap = 2 * (m + total)
            part, cell, vol = _grow(part, m, cap), _grow(cell, m, cap), _growf(vol, m, cap)
        v_p = 4.0 / 3.0 * math.pi * r**3
        for i in range(counts[0]):
            for j in range(counts[1]):
                for k in range(counts[2]):
                    if (lower[0, i] <= -1.0 and lower[1, j] <= -1.0 and lower[2, k] <= -1.0
                            and upper[0, i] >= 1.0 and upper[1, j] >= 1.0
                            and upper[2, k] >= 1.0):  # fmt: skip
                        v = v_p  # whole sphere in one cell
                    else:
                        v = r**3 * box_volume(lower[0, i], lower[1, j], lower[2, k],
                                              upper[0, i], upper[1, j], upper[2, k])  # fmt: skip
                    if v > 0.0:
                        part[m] = p
                        cell[m] = (cells[0, i] * shape[1] + cells[1, j]) * shape[2] + cells[2, k]
                        vol[m] = v
                        m += 1
    return part[:m], cell[:m], vol[:m]


@njit(cache=True)
def _grow(a, m, cap):
    out = np.empty(cap, a.dtype)
    out[:m] = a[:m]
    return out


@njit(cache=True)
def _growf(a, m, cap):
    out = np.empty(cap)
    out[:m] = a[:m]
    return out


@njit(cache=True)
def _polar_cell(x, y, z, theta0, edges, lo, hi, shape):
    """Flat bin of a point given its cross-section coordinates (x, y) about the axis and its
    axial coordinate z; -1 outside."""
    r = math.sqrt(x * x + y * y)
    n_t, n_r, n_z = shape[0], shape[1], shape[2]
    if r >= edges[n_r] or z < lo or z >= hi:
        return -1
    theta = math.atan2(y, x) - theta0
    theta -= 2 * math.pi * math.floor(theta / (2 * math.pi))
    it = min(int(theta / (2 * math.pi) * n_t), n_t - 1)
    ir = 0
    while ir < n_r - 1 and r >= edges[ir + 1]:
        ir += 1
    iz = min(int((z - lo) / (hi - lo) * n_z), n_z - 1)
    return (it * n_r + ir) * n_z + iz


@njit(cache=True)
def _cylinder_index(pos, axes, centre, theta0, edges, lo, hi, shape):
    n = pos.shape[0]
    out = np.empty(n, np.int64)
    for p in range(n):
        out[p] = _polar_cell(pos[p, axes[0]] - centre[0], pos[p, axes[1]] - centre[1],
                             pos[p, axes[2]], theta0, edges, lo, hi, shape)  # fmt: skip
    return out


@njit(cache=True)
def _crosses_boundary(x, y, z, r, theta0, edges, lo, hi, shape):
    """Whether a sphere (centre x, y about the axis, z along it; radius r) crosses a bin face."""
    rho = math.sqrt(x * x + y * y)
    if rho <= r:
        return True  # the axis runs through it
    for e in edges[1:]:
        if abs(rho - e) < r:
            return True
    dz = (hi - lo) / shape[2]
    for k in range(shape[2] + 1):
        if abs(z - (lo + k * dz)) < r:
            return True
    if shape[0] > 1:
        phi = math.atan2(y, x)
        for k in range(shape[0]):
            edge = theta0 + k * 2 * math.pi / shape[0]
            d = phi - edge
            d -= 2 * math.pi * math.floor((d + math.pi) / (2 * math.pi))
            if abs(d) < math.pi / 2 and rho * abs(math.sin(d)) < r:
                return True
    return False


@njit(cache=True)
def _ring_of(v, edges, n_r):
    """Ring holding radius ``v`` (clamped to the rings)."""
    i = 0
    while i < n_r - 1 and v >= edges[i + 1]:
        i += 1
    return i


@njit(cache=True)
def _local_shares(x, y, z, r, theta0, edges, lo, hi, shape, cells, vols):
    """Shares of a sphere away from the axis in cylindrical bins, in the local orthogonal frame
    (radial, tangential, axial): axial faces and sector planes are exact planes, ring faces their
    tangent planes (:func:`twin_core.mixing.overlap.box_volume` of the local box). A sphere cut
    by a single ring face gets the first-order curvature correction of that face,
    ``pi r^4 (1 - d^2)^2 / (8 e)`` moved from the inner to the outer ring (``d`` the centre's
    distance from the face in radii, ``e`` the face's radius). Returns the number of shares, or
    -1 where the local frame does not hold (the sphere within two radii of the axis or over
    more than two sectors)."""
    n_t, n_r, n_z = shape[0], shape[1], shape[2]
    rho = math.sqrt(x * x + y * y)
    if rho <= 2.0 * r:
        return -1
    if rho - r >= edges[n_r] or z + r <= lo or z - r >= hi:
        return 0
    two_pi = 2.0 * math.pi
    phi = math.atan2(y, x) - theta0
    phi -= two_pi * math.floor(phi / two_pi)
    d_theta = two_pi / n_t
    alpha = math.asin(r / rho)
    k0, k1 = 0, 0
    if n_t > 1:
        k0 = int(math.floor((phi - alpha) / d_theta))
        k1 = int(math.floor((phi + alpha) / d_theta))
        if k1 - k0 > 1:
            return -1
    i0 = _ring_of(max(rho - r, 0.0), edges, n_r)
    i1 = _ring_of(rho + r, edges, n_r)
    dz = (hi - lo) / n_z
    j0 = max(int(math.floor((z - r - lo) / dz)), 0)
    j1 = min(int(math.floor((z + r - lo) / dz)), n_z - 1)
    if (k1 - k0 + 1) * (i1 - i0 + 1) * (j1 - j0 + 1) > cells.shape[0]:
        return -1
    m = 0
    for k in range(k0, k1 + 1):
        t_lo, t_hi = -np.inf, np.inf
        if n_t > 1:
            a = phi - k * d_theta
            b = (k + 1) * d_theta - phi
            if a < 0.5 * math.pi:
                t_lo = -rho * math.sin(a) / r
            if b < 0.5 * math.pi:
                t_hi = rho * math.sin(b) / r
        for i in range(i0, i1 + 1):
            r_lo = -np.inf if i == 0 else (edges[i] - rho) / r
            r_hi = (edges[i + 1] - rho) / r
            for j in range(j0, j1 + 1):
                z_lo = (lo + j * dz - z) / r
                z_hi = (lo + (j + 1) * dz - z) / r
                v = r**3 * box_volume(r_lo, t_lo, z_lo, r_hi, t_hi, z_hi)
                if v > 0.0:
                    cells[m] = ((k % n_t) * n_r + i) * n_z + j
                    vols[m] = v
                    m += 1
    # a single ring face cutting the sphere: curvature correction of its tangent plane
    faces = 0
    ring_face = -1
    for q in range(1, n_r + 1):
        if abs(rho - edges[q]) < r:
            faces += 1
            ring_face = q
    for jz in range(n_z + 1):
        if abs(z - (lo + jz * dz)) < r:
            faces += 1
    if n_t > 1 and k1 > k0:
        faces += 1
    if faces == 1 and ring_face > 0:
        e = edges[ring_face]
        d = (rho - e) / r
        shift = math.pi * r**4 * (1.0 - d * d) ** 2 / (8.0 * e)
        for q in range(m):
            ring = (cells[q] // n_z) % n_r
            vols[q] += -shift if ring == ring_face - 1 else shift
    return m


@njit(cache=True)
def _cylinder_shares(pos, radii, points, weights, axes, centre, theta0, edges, lo, hi, shape):
    n = pos.shape[0]
    n_cells = shape[0] * shape[1] * shape[2]
    cap = 4 * n + 16
    part = np.empty(cap, np.int64)
    cell = np.empty(cap, np.int64)
    vol = np.empty(cap)
    acc = np.zeros(n_cells)
    touched = np.empty(points.shape[0], np.int64)
    local_c = np.empty(64, np.int64)
    local_v = np.empty(64)
    m = 0
    for p in range(n):
        x = pos[p, axes[0]] - centre[0]
        y = pos[p, axes[1]] - centre[1]
        z = pos[p, axes[2]]
        r = radii[p]
        if m + points.shape[0] > cap:
            cap = 2 * (m + points.shape[0])
            part, cell, vol = _grow(part, m, cap), _grow(cell, m, cap), _growf(vol, m, cap)
        if not _crosses_boundary(x, y, z, r, theta0, edges, lo, hi, shape):
            c = _polar_cell(x, y, z, theta0, edges, lo, hi, shape)
            if c >= 0:
                part[m], cell[m], vol[m] = p, c, 4.0 / 3.0 * math.pi * r**3
                m += 1
            continue
        k = _local_shares(x, y, z, r, theta0, edges, lo, hi, shape, local_c, local_v)
        if k >= 0:
            for q in range(k):
                part[m], cell[m], vol[m] = p, local_c[q], local_v[q]
                m += 1
            continue
        n_t = 0
        r3 = r**3
        for q in range(points.shape[0]):
            c = _polar_cell(x + r * points[q, 0], y + r * points[q, 1], z + r * points[q, 2],
                            theta0, edges, lo, hi, shape)  # fmt: skip
            if c < 0:
                continue
            if acc[c] == 0.0:
                touched[n_t] = c
                n_t += 1
            acc[c] += weights[q] * r3
        for t in range(n_t):
            c = touched[t]
            part[m], cell[m], vol[m] = p, c, acc[c]
            acc[c] = 0.0
            m += 1
    return part[:m], cell[:m], vol[:m]


def sampled_weights(
    grid: GridSpec | CylindricalGrid,
    positions: np.ndarray,
    radii: np.ndarray,
    weight: str = "number",
    mapping: str = "point",
    box=None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(particle, cell, weight)`` of every sampled particle, or part of one: weight 1 or the
    particle volume (``mapping="point"``, the cell of its centre), or its volume share of the
    cell, as a volume or a fraction of the particle (``mapping="fractional"``)."""
    if weight not in WEIGHTS:
        raise ValueError(f"weight must be one of {WEIGHTS}, got {weight!r}")
    if mapping not in MAPPINGS:
        raise ValueError(f"mapping must be one of {MAPPINGS}, got {mapping!r}")
    radii = np.asarray(radii, float)
    if mapping == "point":
        part = np.arange(len(radii))
        cell = grid.cell_index(positions, box)
        w = sphere_volumes(radii) if weight == "volume" else np.ones(len(radii))
    else:
        part, cell, w = grid.shares(positions, radii, box)
        if weight == "number":
            w = w / sphere_volumes(radii[part])
    ok = cell >= 0
    return part[ok], cell[ok], w[ok]


def cell_amounts(
    grid: GridSpec | CylindricalGrid,
    positions: np.ndarray,
    radii: np.ndarray,
    types: np.ndarray,
    type_ids,
    *,
    weight: str = "number",
    mapping: str = "point",
    box=None,
) -> np.ndarray:
    """Amount of each type in each cell, ``(n_cells, len(type_ids))``.

    ``weight="number"`` counts particles, ``"volume"`` sums their volumes ``4/3 pi r^3``;
    ``mapping="point"`` puts a particle in the cell of its centre, ``"fractional"`` splits it
    over the cells by the volume of its parts (fractional counts with ``weight="number"``).
    Reference: volume-weighted sampling, Chandratilleke et al., AIChE J. 58 (2012) 1099-1118;
    fractional mapping, Füvesi et al., Powder Technol. (2025) 120775."""
    types = np.asarray(types)
    type_ids = list(type_ids)
    slot = np.full(len(types), -1, np.int64)
    for k, tid in enumerate(type_ids):
        slot[types == tid] = k
    part, cell, amount = sampled_weights(grid, positions, radii, weight, mapping, box)
    ok = slot[part] >= 0
    flat = cell[ok] * len(type_ids) + slot[part[ok]]
    out = np.bincount(flat, weights=amount[ok], minlength=grid.n_cells * len(type_ids))
    return out.reshape(grid.n_cells, len(type_ids))


def cell_counts(grid: GridSpec | CylindricalGrid, positions, types, type_ids) -> np.ndarray:
    """Counts per cell and type (point mapping), ``(n_cells, len(type_ids))`` integers."""
    amounts = cell_amounts(grid, positions, np.zeros(len(types)), types, type_ids)
    return np.rint(amounts).astype(np.int64)


def occupied_cells(grid: GridSpec | CylindricalGrid, amounts: np.ndarray) -> np.ndarray:
    """Boolean mask of the cells kept for the variance indices (the seed's 50 % rule).

    A cell is kept when its total amount is non-zero and at least ``min_fill`` times its share
    of the whole amount by cell volume (``min_fill * N / n_cells`` for equal cells)."""
    total = np.asarray(amounts, float).sum(axis=1)
    volumes = grid.cell_volumes()
    threshold = grid.min_fill * total.sum() * volumes / volumes.sum()
    return (total >= threshold * (1 - 1e-12)) & (total > 0)


def parse_bins(
    text: str,
    lo,
    hi,
    *,
    min_fill: float = 0.5,
    clip: bool = True,
) -> GridSpec | CylindricalGrid:
    """A sampling grid from text: ``"8x8x52"`` or ``"cartesian:8x8x52"`` (over ``lo .. hi``),
    ``"cylindrical:NTxNRxNA[,axis=z][,radial=area|radius][,theta0=RAD]"`` (the cylinder
    inscribed in ``lo .. hi`` about the axis: centre in the middle of the cross-section, radius
    half its smaller side)."""
    kind, _, spec = text.partition(":")
    if not spec:
        kind, spec = "cartesian", text
    kind = kind.strip().lower()
    parts = [p.strip() for p in spec.split(",")]
    options = {}
    for opt in parts[1:]:
        key, eq, value = opt.partition("=")
        if not eq:
            raise ValueError(f"bins option must look like key=value, got {opt!r}")
        options[key.strip().lower()] = value.strip()
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    if kind == "cartesian":
        if options:
            raise ValueError(f"cartesian bins take no options, got {sorted(options)}")
        return GridSpec(tuple(lo), tuple(hi), _parse_shape(parts[0]), min_fill, clip)
    if kind != "cylindrical":
        raise ValueError(f"bins must be 'cartesian:...' or 'cylindrical:...', got {text!r}")
    unknown = set(options) - {"axis", "radial", "theta0"}
    if unknown:
        raise ValueError(f"unknown cylindrical bins option(s) {sorted(unknown)}")
    axis = _axis(options.get("axis", "z"))
    a, b = (axis + 1) % 3, (axis + 2) % 3
    try:
        theta0 = float(options.get("theta0", 0.0))
    except ValueError:
        raise ValueError(f"theta0 must be a number, got {options['theta0']!r}") from None
    return CylindricalGrid(
        centre=(0.5 * (lo[a] + hi[a]), 0.5 * (lo[b] + hi[b])),
        r_max=0.5 * min(hi[a] - lo[a], hi[b] - lo[b]),
        lo=float(lo[axis]),
        hi=float(hi[axis]),
        shape=_parse_shape(parts[0]),
        axis=axis,
        radial=options.get("radial", "area"),
        theta0=theta0,
        min_fill=min_fill,
    )
