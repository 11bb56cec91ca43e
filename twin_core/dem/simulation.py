"""The DEM simulation object: state, walls, meshes, insertion, run loop and checkpoints.

It owns the arrays and calls the numba kernels: :mod:`twin_core.dem.contact` (contact law),
:mod:`~twin_core.dem.pairs` (pair forces, race-free schemes), :mod:`~twin_core.dem.walls` and
:mod:`~twin_core.dem.meshes` (walls), :mod:`~twin_core.dem.partition` (cell grid, neighbour
lists), :mod:`~twin_core.dem.integrator` (velocity Verlet for translation and rotation),
:mod:`~twin_core.dem.insertion` (placement) and :mod:`~twin_core.dem.energy`; see
``docs/dem_engine.md``.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numba
import numpy as np

from .energy import elastic_energy
from .insertion import BoxRegion, CylinderRegion, ParticleFactory, rsa_place, sample_radii
from .integrator import advance, compute_forces
from .materials import Material, MaterialTable, hertz_contact_time, rayleigh_time
from .mesh_contacts import MBLOCK_WORDS, MFLT_COLS, MINT_ROWS
from .meshes import update_mesh
from .motion import RotationMotion, TranslationMotion, motion_from_dict
from .pairs import BLOCK_WORDS
from .partition import rebuild, reverse_lists
from .space import NPC
from .threads import ThreadChooser, current_policy

__all__ = ["Simulation"]

_CHECKPOINT_VERSION = 1
_PLANE_COLS = 9  # point, normal, material, activation window (walls.py)
_CYL_COLS = 14  # point, axis, radius, side, omega, material, axial range, activation window


def _window(active: Sequence[float], name: str = "active") -> tuple[float, float]:
    """An activation window ``(t_on, t_off)`` with ``t_on < t_off``."""
    if len(active) != 2 or not float(active[1]) > float(active[0]):
        raise ValueError(f"{name} must be (t_on, t_off) with t_on < t_off, got {active}")
    return float(active[0]), float(active[1])


def _with_window(table: np.ndarray, ncols: int) -> np.ndarray:
    """A wall table of a checkpoint written before walls had activation windows, widened to
    ``ncols`` columns with an always-active window."""
    if table.shape[1] == ncols:
        return table
    pad = np.tile([-math.inf, math.inf], (table.shape[0], 1))
    return np.hstack([table.reshape(-1, ncols - 2), pad])


def _vec3(v: Sequence[float], name: str) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite 3-vector, got {v}")
    return a


class Simulation:
    """A discrete element simulation of spheres (Hertz-Mindlin, Tsuji damping, rolling friction).

    Parameters
    ----------
    domain_lo, domain_hi : 3-vectors (m)
        Simulation box. Along periodic axes it is the period; along the other axes a particle that
        leaves the box is removed (counted in ``removed_counts['lost']``).
    periodic : 3 bools
    gravity : 3-vector (m/s^2)
    materials : MaterialTable, Material or list of Material
    dt : float, optional
        Time step (s). Default: ``dt_fraction`` times the smallest Rayleigh time of the particles
        present (or announced by a factory) when the first ``run`` starts.
    dt_fraction : float
        Fraction of the Rayleigh time (default 0.2, seed Sec. 3.2.1).
    skin : float, optional
        Verlet skin (m). Default: 0.5 times the largest radius at the first build.
    seed : int
        Default seed of :meth:`insert_particles`.
    pair_scheme : {"auto", "scatter", "two_pass"}
        Pair-force scheme (attribute, may be changed between runs): ``"scatter"`` (``"auto"``,
        the default) evaluates each pair once and adds it to both particles, the owners split
        into ``pair_chunks`` chunks that run on as many threads as there are, each into its own
        force buffer; ``"two_pass"`` writes pair forces to a buffer and gathers them per
        particle. Results do not depend on the thread count; the two schemes are bit-identical
        with one chunk.
    pair_chunks : int, optional
        Chunks of the scatter scheme (attribute): at most this many threads share the pair
        forces, and the summation order (hence the last bits of a chaotic trajectory) depends
        on it, never on the threads running. Default: numba's thread count at start-up
        (``NUMBA_NUM_THREADS``).

    Attributes ``t, ids, type_id, material_id, radius, mass, pos, vel, omega, force, torque,
    n_particles`` expose the state. Rows are re-sorted by neighbour cell at every neighbour-list
    rebuild: identify particles by ``ids``, not by row.
    """

    def __init__(
        self,
        domain_lo: Sequence[float],
        domain_hi: Sequence[float],
        periodic: Sequence[bool] = (False, False, False),
        gravity: Sequence[float] = (0.0, 0.0, -9.81),
        materials: MaterialTable | Material | Sequence[Material] | None = None,
        dt: float | None = None,
        dt_fraction: float = 0.2,
        skin: float | None = None,
        seed: int = 0,
        pair_scheme: str = "auto",
        pair_chunks: int | None = None,
    ) -> None:
        lo = _vec3(domain_lo, "domain_lo")
        hi = _vec3(domain_hi, "domain_hi")
        if not np.all(hi > lo):
            raise ValueError(f"domain_hi must be > domain_lo, got {domain_lo}, {domain_hi}")
        if len(periodic) != 3:
            raise ValueError(f"periodic must have 3 entries, got {periodic}")
        if materials is None:
            raise ValueError("materials must be given, got None")
        if not isinstance(materials, MaterialTable):
            materials = MaterialTable(materials)  # type: ignore[arg-type]
        if dt is not None and not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        if not 0 < dt_fraction <= 1:
            raise ValueError(f"dt_fraction must be in (0, 1], got {dt_fraction}")
        if skin is not None and not skin > 0:
            raise ValueError(f"skin must be > 0, got {skin}")
        self.materials = materials
        self._pt = materials.tables()
        self._dom = np.concatenate([lo, hi, hi - lo])
        self._per = np.array([1 if p else 0 for p in periodic], np.int64)
        self._grav = _vec3(gravity, "gravity")
        self.dt_fraction = float(dt_fraction)
        self._dt: float | None = float(dt) if dt is not None else None
        self._dt_user = dt is not None
        self._dt_frozen = False
        self.skin: float | None = float(skin) if skin is not None else None
        self.seed = int(seed)
        self.pair_scheme = pair_scheme
        self.pair_chunks = int(pair_chunks or numba.config.NUMBA_NUM_THREADS)
        if self.pair_chunks < 1:
            raise ValueError(f"pair_chunks must be >= 1, got {pair_chunks}")
        #: ``"adaptive"``: choose 1 or all numba threads at run time by measured throughput
        #: (:mod:`twin_core.dem.threads`); ``"fixed"``: the caller's thread count; None: follow
        #: ``twin_core.dem.threads.adaptive_threads()``
        self.thread_policy: str | None = None
        #: the chooser of the adaptive policy (made at the first adaptive run; may be given)
        self.thread_chooser: ThreadChooser | None = None
        self._serial()
        self._step = 0
        self._next_id = 0
        self._rmax = 0.0
        self._n = 0
        self._forces_stale = True
        #: the reverse lists (two-pass scheme only) do not match the neighbour lists
        self._reverse_stale = True
        self._warned_resolution = False
        self._warned_chunks = False
        self._alloc(16, kown=8, krev=8, ktri=4)
        self._planes = np.zeros((0, _PLANE_COLS))
        self._cyls = np.zeros((0, _CYL_COLS))
        self._whist = np.zeros((16, 0, 3))
        self._tri_x0 = np.zeros((0, 9))
        self._tri_x = np.zeros((0, 9))
        self._tri_xb = np.zeros((0, 9))
        self._tri_mesh = np.zeros(0, np.int64)
        self._mesh_par = np.zeros((0, 16))
        self._meshes: list[dict] = []
        self._sinks = np.zeros((0, 6))
        self._removed = np.zeros((2, 2))
        self._counters = np.zeros(4, np.int64)
        self._factories: list[ParticleFactory] = []
        self.wall_time_s = 0.0

    # ----------------------------------------------------------------------------------------
    # storage
    # ----------------------------------------------------------------------------------------
    def _alloc(self, cap: int, kown: int, krev: int, ktri: int) -> None:
        self._cap = cap
        self._P = np.zeros((cap, NPC))
        self._F = np.zeros((cap, 6))
        self._IA = np.zeros((cap, 3), np.int64)
        self._XB = np.zeros((cap, 3))
        self._rm = np.zeros(cap, np.int64)
        self._nb = np.zeros((2, cap, kown), np.int32)
        self._hist = np.zeros((2, cap, kown, 3))
        self._nown = np.zeros((2, cap), np.int32)
        self._pf = np.zeros((cap, kown, 10))
        # pair sums of the scatter's chunks after the first (the first sums into _F)
        self._acc = np.zeros((self.pair_chunks - 1, cap, 6))
        self._bounds = np.zeros(self.pair_chunks + 1, np.int64)
        # work arrays of the batched contact law (twin_core.dem.pairs), derived each step
        self._pstart = np.zeros(cap + 1, np.int64)
        self._nbf = np.zeros((2, cap * kown), np.int32)
        self._live = np.zeros(cap * kown, np.uint8)
        self._clist = np.zeros((3, cap * kown), np.int32)
        self._work = np.zeros((self.pair_chunks, BLOCK_WORDS))
        self._rev_o = np.zeros((cap, krev), np.int32)
        self._rev_k = np.zeros((cap, krev), np.int32)
        self._nrev = np.zeros(cap, np.int32)
        self._cur = np.zeros(1, np.int64)
        self._tri_nb = np.zeros((2, cap, ktri), np.int32)
        self._thist = np.zeros((2, cap, ktri, 3))
        self._ntri = np.zeros((2, cap), np.int32)
        # work arrays of the batched mesh contacts (twin_core.dem.mesh_contacts), derived each
        # step; one block buffer per thread
        self._mcnt = np.zeros((3, cap + 1), np.int64)
        self._mint = np.zeros((MINT_ROWS, cap * ktri), np.int32)
        self._mflt = np.zeros((cap * ktri, MFLT_COLS))
        self._mwork = np.zeros((numba.config.NUMBA_NUM_THREADS, MBLOCK_WORDS))

    def _resize(
        self, cap: int | None = None, kown: int | None = None, krev: int | None = None,
        ktri: int | None = None,
    ) -> None:  # fmt: skip
        """Reallocate keeping the content (capacity and list widths only grow)."""
        cap = max(cap or self._cap, self._cap)
        kown = max(kown or self._nb.shape[2], self._nb.shape[2])
        krev = max(krev or self._rev_o.shape[1], self._rev_o.shape[1])
        ktri = max(ktri or self._tri_nb.shape[2], self._tri_nb.shape[2])
        old = {k: getattr(self, k) for k in (
            "_P", "_F", "_IA", "_XB", "_rm", "_nb", "_hist", "_nown", "_rev_o", "_rev_k",
            "_nrev", "_cur", "_tri_nb", "_thist", "_ntri")}  # fmt: skip
        oc = self._cap
        ow = self._whist
        self._alloc(cap, kown, krev, ktri)
        self._P[:oc] = old["_P"]
        self._F[:oc] = old["_F"]
        self._IA[:oc] = old["_IA"]
        self._XB[:oc] = old["_XB"]
        self._rm[:oc] = old["_rm"]
        ko = old["_nb"].shape[2]
        self._nb[:, :oc, :ko] = old["_nb"]
        self._hist[:, :oc, :ko] = old["_hist"]
        self._nown[:, :oc] = old["_nown"]
        kr = old["_rev_o"].shape[1]
        self._rev_o[:oc, :kr] = old["_rev_o"]
        self._rev_k[:oc, :kr] = old["_rev_k"]
        self._nrev[:oc] = old["_nrev"]
        self._cur[:] = old["_cur"]
        kt = old["_tri_nb"].shape[2]
        self._tri_nb[:, :oc, :kt] = old["_tri_nb"]
        self._thist[:, :oc, :kt] = old["_thist"]
        self._ntri[:, :oc] = old["_ntri"]
        self._whist = np.zeros((cap, ow.shape[1], 3))
        self._whist[:oc] = ow

    def _set_n_walls(self) -> None:
        nw = self._planes.shape[0] + self._cyls.shape[0]
        if self._whist.shape[1] != nw:
            w = np.zeros((self._cap, nw, 3))
            k = min(nw, self._whist.shape[1])
            w[:, :k] = self._whist[:, :k]
            self._whist = w
        self._forces_stale = True

    # ----------------------------------------------------------------------------------------
    # public state
    # ----------------------------------------------------------------------------------------
    @property
    def n_particles(self) -> int:
        """Number of particles."""
        return self._n

    @property
    def t(self) -> float:
        """Simulated time (s) = step count x dt."""
        return self._step * self._dt if self._dt is not None else 0.0

    @property
    def step(self) -> int:
        """Number of steps taken."""
        return self._step

    @property
    def dt(self) -> float:
        """Time step (s); fixed at the first ``run``."""
        if self._dt_frozen or self._dt_user:
            return self._dt  # type: ignore[return-value]
        return self._rayleigh_dt()

    @property
    def pos(self) -> np.ndarray:
        """Positions (n, 3), a view (writable)."""
        return self._P[: self._n, 0:3]

    @property
    def vel(self) -> np.ndarray:
        """Velocities (n, 3), a view (writable)."""
        return self._P[: self._n, 3:6]

    @property
    def omega(self) -> np.ndarray:
        """Angular velocities (n, 3) rad/s, a view (writable)."""
        return self._P[: self._n, 6:9]

    @property
    def radius(self) -> np.ndarray:
        """Radii (n,) m."""
        return self._P[: self._n, 9]

    @property
    def mass(self) -> np.ndarray:
        """Masses (n,) kg."""
        return self._P[: self._n, 10]

    @property
    def inertia(self) -> np.ndarray:
        """Moments of inertia (n,) kg m^2 (solid spheres)."""
        return 1.0 / self._P[: self._n, 12]

    @property
    def force(self) -> np.ndarray:
        """Total force (n, 3) at the current positions."""
        return self._F[: self._n, 0:3]

    @property
    def torque(self) -> np.ndarray:
        """Total torque (n, 3) at the current positions."""
        return self._F[: self._n, 3:6]

    @property
    def ids(self) -> np.ndarray:
        """Persistent particle ids (n,)."""
        return self._IA[: self._n, 0]

    @property
    def material_id(self) -> np.ndarray:
        """Material ids (n,)."""
        return self._IA[: self._n, 1]

    @property
    def type_id(self) -> np.ndarray:
        """Type (colour) ids (n,)."""
        return self._IA[: self._n, 2]

    @property
    def periodic(self) -> tuple[bool, bool, bool]:
        """Periodic axes."""
        return tuple(bool(p) for p in self._per)  # type: ignore[return-value]

    @property
    def domain(self) -> tuple[np.ndarray, np.ndarray]:
        """(domain_lo, domain_hi)."""
        return self._dom[0:3].copy(), self._dom[3:6].copy()

    @property
    def n_rebuilds(self) -> int:
        """Number of neighbour-list rebuilds so far."""
        return int(self._counters[1])

    @property
    def removed_counts(self) -> dict[str, tuple[int, float]]:
        """Removed particles so far: ``{'user'|'lost'|'sink<k>': (count, mass_kg)}``."""
        names = ["user", "lost"] + [f"sink{k}" for k in range(self._sinks.shape[0])]
        return {nm: (int(self._removed[i, 0]), float(self._removed[i, 1])) for i, nm in
                enumerate(names)}  # fmt: skip

    def kinetic_energy(self) -> float:
        """Translational plus rotational kinetic energy (J)."""
        n = self._n
        P = self._P
        et = 0.5 * np.sum(P[:n, 10] * np.sum(P[:n, 3:6] ** 2, axis=1))
        er = 0.5 * np.sum(np.sum(P[:n, 6:9] ** 2, axis=1) / P[:n, 12])
        return float(et + er)

    def potential_energy(self) -> float:
        """Gravitational potential energy ``-sum m g.x`` plus the Hertz elastic energy of contacts
        with particles and the planes and cylinders active now (J)."""
        n = self._n
        pg = -float(np.sum(self._P[:n, 10] * (self._P[:n, 0:3] @ self._grav)))
        self._ensure_lists()
        c = int(self._cur[0])
        t = self.t
        planes = self._planes[(self._planes[:, 7] <= t) & (t < self._planes[:, 8])]
        cyls = self._cyls[(self._cyls[:, 12] <= t) & (t < self._cyls[:, 13])]
        pe = elastic_energy(
            n, self._P, self._IA, self._nb[c], self._nown[c], planes, cyls,
            self._pt, self._dom, self._per,
        )  # fmt: skip
        return pg + float(pe)

    def total_energy(self) -> float:
        """Kinetic plus potential energy (J)."""
        return self.kinetic_energy() + self.potential_energy()

    def momentum(self) -> np.ndarray:
        """Total linear momentum (kg m/s)."""
        return np.sum(self._P[: self._n, 10:11] * self._P[: self._n, 3:6], axis=0)

    def solid_fraction(self, lo: Sequence[float], hi: Sequence[float]) -> float:
        """Solid fraction of the box [lo, hi] counting the spheres whose centres lie inside it."""
        lo_, hi_ = _vec3(lo, "lo"), _vec3(hi, "hi")
        x = self.pos
        inside = np.all((x >= lo_) & (x <= hi_), axis=1)
        v = np.sum(4.0 / 3.0 * np.pi * self.radius[inside] ** 3)
        return float(v / np.prod(hi_ - lo_))

    # ----------------------------------------------------------------------------------------
    # building the system
    # ----------------------------------------------------------------------------------------
    def add_particles(
        self,
        pos: np.ndarray,
        radius: float | np.ndarray,
        material_id: int | np.ndarray = 0,
        type_id: int | np.ndarray = 0,
        vel: np.ndarray | Sequence[float] | None = None,
        omega: np.ndarray | None = None,
    ) -> np.ndarray:
        """Add spheres; returns their persistent ids. Overlaps are not checked."""
        pos = np.array(pos, dtype=float, ndmin=2)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f"pos must have shape (k, 3), got {pos.shape}")
        k = pos.shape[0]
        rad = np.broadcast_to(np.asarray(radius, float), (k,)).copy()
        if not np.all(rad > 0):
            raise ValueError(f"radius must be > 0, got min {rad.min() if k else None}")
        mat = np.broadcast_to(np.asarray(material_id, np.int64), (k,)).copy()
        if k and (mat.min() < 0 or mat.max() >= self.materials.n):
            raise ValueError(f"material_id must be in [0, {self.materials.n}), got {mat}")
        typ = np.broadcast_to(np.asarray(type_id, np.int64), (k,)).copy()
        v = np.zeros((k, 3)) if vel is None else np.broadcast_to(np.asarray(vel, float), (k, 3))
        w = np.zeros((k, 3)) if omega is None else np.broadcast_to(np.asarray(omega, float), (k, 3))
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(v)) and np.all(np.isfinite(w))):
            raise ValueError("pos, vel and omega must be finite")
        lo, hi = self._dom[0:3], self._dom[3:6]
        for a in range(3):
            if self._per[a]:
                pos[:, a] = lo[a] + np.mod(pos[:, a] - lo[a], hi[a] - lo[a])
        out = np.any((pos < lo) | (pos > hi), axis=1)
        if np.any(out):
            raise ValueError(f"pos must lie inside the domain, got {pos[out][0]}")
        if k == 0:
            return np.zeros(0, np.int64)
        if self._n + k > self._cap:
            self._resize(cap=max(2 * self._cap, self._n + k))
        rho = np.array([m.density for m in self.materials.materials])[mat]
        mass = rho * 4.0 / 3.0 * np.pi * rad**3
        s = slice(self._n, self._n + k)
        P = self._P
        P[s, 0:3] = pos
        P[s, 3:6] = v
        P[s, 6:9] = w
        P[s, 9] = rad
        P[s, 10] = mass
        P[s, 11] = 1.0 / mass
        P[s, 12] = 1.0 / (0.4 * mass * rad**2)
        self._F[s] = 0.0
        ids = np.arange(self._next_id, self._next_id + k, dtype=np.int64)
        self._IA[s, 0] = ids
        self._IA[s, 1] = mat
        self._IA[s, 2] = typ
        self._XB[s] = pos
        self._rm[s] = 0
        c = int(self._cur[0])
        self._nown[c, s] = 0
        self._ntri[c, s] = 0
        self._whist[s] = 0.0
        self._next_id += k
        self._n += k
        self._rmax = max(self._rmax, float(rad.max()))
        if self.skin is None:
            self.skin = 0.5 * self._rmax
        self._check_periodic_size()
        if self._dt_frozen:
            self._check_dt()
        self._rebuild()
        self._forces_stale = True
        return ids

    def _check_periodic_size(self) -> None:
        cut = 2.0 * self._rmax + (self.skin or 0.0)
        for a in range(3):
            if self._per[a] and self._dom[6 + a] < 2.0 * cut:
                raise ValueError(
                    f"periodic length along axis {a} must be >= 2 (2 r_max + skin) = {2 * cut}, "
                    f"got {self._dom[6 + a]}"
                )

    def insert_particles(
        self,
        n: int,
        region: BoxRegion | CylinderRegion,
        radius: float | tuple[float, float],
        material_id: int = 0,
        type_id: int = 0,
        vel: Sequence[float] | None = None,
        seed: int | np.random.Generator | None = None,
        max_attempts: int = 200,
        strict: bool = True,
    ) -> np.ndarray:
        """Place ``n`` non-overlapping spheres in ``region`` (random sequential addition).

        ``radius``: float or ``(r_min, r_max)`` uniform. Raises ValueError when ``strict`` and fewer
        than n fit after ``max_attempts * n`` trials; otherwise places what fits. Returns ids.
        """
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(
            self.seed if seed is None else seed)  # fmt: skip
        radii = sample_radii(radius, n, rng)
        if n == 0:
            return np.zeros(0, np.int64)
        cs = 2.0 * max(float(radii.max()), self._rmax)
        if not np.isscalar(radius):
            cs = 2.0 * max(float(radius[1]), self._rmax)  # type: ignore[index]
        ex_pos = self.pos.copy()
        ex_r = self.radius.copy()
        placed_pos = np.zeros((0, 3))
        placed_r = np.zeros(0)
        need = n
        tried = 0
        while need and tried < max_attempts * n:
            m = max(4 * need, 256)
            cand_r = radii[:need] if m <= need else np.concatenate(
                [radii[:need], sample_radii(radius, m - need, rng)])  # fmt: skip
            cand = region.sample(rng, cand_r)
            acc = rsa_place(
                np.concatenate([ex_pos, placed_pos]), np.concatenate([ex_r, placed_r]),
                cand, cand_r, need, self._dom, self._per, cs,
            )  # fmt: skip
            tried += m
            if acc.size:
                placed_pos = np.concatenate([placed_pos, cand[acc]])
                placed_r = np.concatenate([placed_r, cand_r[acc]])
                need -= acc.size
                radii = sample_radii(radius, max(need, 1), rng)
        if need and strict:
            raise ValueError(
                f"n: only {placed_r.size} of {n} particles fit in the region after {tried} trials"
            )
        return self.add_particles(placed_pos, placed_r, material_id, type_id, vel)

    def add_factory(self, factory: ParticleFactory) -> ParticleFactory:
        """Register a particle factory; it inserts during :meth:`run`."""
        self._factories.append(factory)
        return factory

    def remove_particles(self, mask: np.ndarray) -> int:
        """Remove the particles where ``mask`` (n,) is true; returns how many."""
        mask = np.asarray(mask, bool)
        if mask.shape != (self._n,):
            raise ValueError(f"mask must have shape ({self._n},), got {mask.shape}")
        k = int(mask.sum())
        if k:
            self._rm[: self._n][mask] = 1
            self._rebuild()
            self._forces_stale = True
        return k

    def add_plane(
        self,
        point: Sequence[float],
        normal: Sequence[float],
        material_id: int = 0,
        active: tuple[float, float] = (-math.inf, math.inf),
    ) -> int:
        """Infinite plane through ``point``; particles live on the side ``normal`` points to.

        ``active=(t_on, t_off)``: the plane exerts forces only for ``t_on <= t < t_off`` (also
        :meth:`set_plane_active`). Returns the plane id."""
        p = _vec3(point, "point")
        t_on, t_off = _window(active)
        nrm = _vec3(normal, "normal")
        if not np.linalg.norm(nrm) > 0:
            raise ValueError(f"normal must be non-zero, got {normal}")
        self._check_mat(material_id)
        nrm = nrm / np.linalg.norm(nrm)
        self._planes = np.vstack([self._planes, np.r_[p, nrm, material_id, t_on, t_off][None, :]])
        # plane histories come first in the wall-history table: shift cylinder columns
        npl = self._planes.shape[0]
        w = np.zeros((self._cap, npl + self._cyls.shape[0], 3))
        w[:, : npl - 1] = self._whist[:, : npl - 1]
        w[:, npl:] = self._whist[:, npl - 1 :]
        self._whist = w
        self._forces_stale = True
        return npl - 1

    def add_box(self, lo: Sequence[float], hi: Sequence[float], material_id: int = 0) -> None:
        """Six planes enclosing the box [lo, hi] (skipping periodic axes)."""
        lo_, hi_ = _vec3(lo, "lo"), _vec3(hi, "hi")
        for a in range(3):
            if self._per[a]:
                continue
            e = np.zeros(3)
            e[a] = 1.0
            self.add_plane(lo_, e, material_id)
            self.add_plane(hi_, -e, material_id)

    def add_cylinder(
        self,
        point: Sequence[float],
        axis: Sequence[float],
        radius: float,
        material_id: int = 0,
        inside: bool = True,
        rpm: float = 0.0,
        extent: tuple[float, float] = (-math.inf, math.inf),
        active: tuple[float, float] = (-math.inf, math.inf),
    ) -> int:
        """Cylindrical wall (axis through ``point`` along ``axis``) of ``radius``.

        ``inside``: particles inside (a drum) or outside (a shaft). ``rpm``: wall rotation about the
        axis (drum; changed later with :meth:`set_cylinder_rpm`); ``extent``: axial range (from
        ``point``) where the wall exists; ``active=(t_on, t_off)``: the wall exerts forces only
        for ``t_on <= t < t_off`` (also :meth:`set_cylinder_active`). Returns the cylinder id.
        """
        t_on, t_off = _window(active)
        p = _vec3(point, "point")
        u = _vec3(axis, "axis")
        if not np.linalg.norm(u) > 0:
            raise ValueError(f"axis must be non-zero, got {axis}")
        if not radius > 0:
            raise ValueError(f"radius must be > 0, got {radius}")
        self._check_mat(material_id)
        u = u / np.linalg.norm(u)
        row = np.r_[p, u, radius, 1.0 if inside else -1.0, 2 * math.pi * rpm / 60.0, material_id,
                    extent[0], extent[1], t_on, t_off]  # fmt: skip
        self._cyls = np.vstack([self._cyls, row[None, :]])
        self._set_n_walls()
        return self._cyls.shape[0] - 1

    def set_plane_active(self, plane_id: int, active: tuple[float, float]) -> None:
        """Activation window ``(t_on, t_off)`` of plane ``plane_id`` (switch a plane on or off:
        ``(sim.t, inf)`` or ``(-inf, sim.t)``); takes effect from the next step."""
        self._planes[self._wall_row(self._planes, plane_id, "plane_id"), 7:9] = _window(active)
        self._forces_stale = True

    def set_cylinder_active(self, cylinder_id: int, active: tuple[float, float]) -> None:
        """Activation window ``(t_on, t_off)`` of cylinder ``cylinder_id``; from the next step."""
        row = self._wall_row(self._cyls, cylinder_id, "cylinder_id")
        self._cyls[row, 12:14] = _window(active)
        self._forces_stale = True

    def set_cylinder_rpm(self, cylinder_id: int, rpm: float) -> None:
        """Rotation speed (rpm, about the cylinder's axis) of cylinder ``cylinder_id`` from the
        next step on: start, change or stop a drum's rotation between runs."""
        if not math.isfinite(rpm):
            raise ValueError(f"rpm must be finite, got {rpm}")
        row = self._wall_row(self._cyls, cylinder_id, "cylinder_id")
        self._cyls[row, 8] = 2 * math.pi * rpm / 60.0
        self._forces_stale = True

    def cylinder_rpm(self, cylinder_id: int) -> float:
        """Current rotation speed (rpm) of cylinder ``cylinder_id``."""
        row = self._wall_row(self._cyls, cylinder_id, "cylinder_id")
        return float(self._cyls[row, 8] * 60.0 / (2 * math.pi))

    @staticmethod
    def _wall_row(table: np.ndarray, wall_id: int, name: str) -> int:
        if not 0 <= wall_id < table.shape[0]:
            raise ValueError(f"{name} must be in [0, {table.shape[0]}), got {wall_id}")
        return int(wall_id)

    def add_mesh(
        self,
        vertices: np.ndarray,
        triangles: np.ndarray,
        material_id: int = 0,
        motion: RotationMotion | TranslationMotion | None = None,
        active: tuple[float, float] = (-math.inf, math.inf),
    ) -> int:
        """Triangle mesh wall (two-sided). ``vertices`` (V, 3) m, ``triangles`` (T, 3) int.

        ``motion``: prescribed rotation/translation; ``active=(t_on, t_off)``: the mesh exerts forces
        only for ``t_on <= t < t_off`` (e.g. a separating plate removed at t_off).
        Returns the mesh id.
        """
        v = np.asarray(vertices, float)
        tr = np.asarray(triangles)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"vertices must have shape (V, 3), got {v.shape}")
        if tr.ndim != 2 or tr.shape[1] != 3 or not np.issubdtype(tr.dtype, np.integer):
            raise ValueError(f"triangles must be an integer array (T, 3), got {tr.shape}")
        if tr.size and (tr.min() < 0 or tr.max() >= v.shape[0]):
            raise ValueError(f"triangles must index vertices in [0, {v.shape[0]})")
        active = _window(active)
        self._check_mat(material_id)
        mid = len(self._meshes)
        mp = motion.params() if motion is not None else np.zeros(13)
        row = np.r_[mp, active[0], active[1], material_id]
        self._mesh_par = np.vstack([self._mesh_par, row[None, :]])
        tx0 = v[tr].reshape(-1, 9)
        self._tri_x0 = np.vstack([self._tri_x0, tx0])
        self._tri_mesh = np.concatenate([self._tri_mesh, np.full(tr.shape[0], mid, np.int64)])
        self._tri_x = self._tri_x0.copy()
        if len(self._tri_x):
            update_mesh(self._tri_x0, self._tri_x, self._tri_mesh, self._mesh_par, self.t)
        self._tri_xb = self._tri_x.copy()
        self._meshes.append({
            "vertices": v.tolist(), "triangles": tr.tolist(), "material_id": material_id,
            "motion": None if motion is None else motion.to_dict(), "active": list(active),
        })  # fmt: skip
        self._forces_stale = True
        if self._n:
            self._rebuild()
        return mid

    def set_mesh_active(self, mesh_id: int, active: tuple[float, float]) -> None:
        """Activation window ``(t_on, t_off)`` of mesh ``mesh_id``; from the next step."""
        if not 0 <= mesh_id < len(self._meshes):
            raise ValueError(f"mesh_id must be in [0, {len(self._meshes)}), got {mesh_id}")
        t_on, t_off = _window(active)
        self._mesh_par[mesh_id, 13:15] = (t_on, t_off)
        self._meshes[mesh_id]["active"] = [t_on, t_off]
        self._forces_stale = True

    def mesh_triangles(self, mesh_id: int) -> np.ndarray:
        """Current triangle coordinates (T, 3, 3) of a mesh."""
        return self._tri_x[self._tri_mesh == mesh_id].reshape(-1, 3, 3).copy()

    def add_outlet(self, lo: Sequence[float], hi: Sequence[float]) -> int:
        """A sink: particles whose centre enters the box [lo, hi] are removed (counted per sink in
        :attr:`removed_counts`). Returns the sink index."""
        lo_, hi_ = _vec3(lo, "lo"), _vec3(hi, "hi")
        if not np.all(hi_ > lo_):
            raise ValueError(f"hi must be > lo, got {lo}, {hi}")
        self._sinks = np.vstack([self._sinks, np.r_[lo_, hi_][None, :]])
        self._removed = np.vstack([self._removed, np.zeros((1, 2))])
        return self._sinks.shape[0] - 1

    def set_pair(
        self, a: int, b: int, friction: float, rolling_friction: float, restitution: float
    ) -> None:
        """Set the coefficients of material pair (a, b) (particle-particle or particle-wall) and
        refresh the contact tables; takes effect from the next step."""
        self.materials.set_pair(a, b, friction, rolling_friction, restitution)
        self._pt = self.materials.tables()
        self._forces_stale = True

    def _check_mat(self, material_id: int) -> None:
        if not 0 <= material_id < self.materials.n:
            raise ValueError(f"material_id must be in [0, {self.materials.n}), got {material_id}")

    # ----------------------------------------------------------------------------------------
    # time step
    # ----------------------------------------------------------------------------------------
    def rayleigh_time(self) -> float:
        """Smallest Rayleigh time over the particles present and those factories will insert."""
        best = math.inf
        n = self._n
        mats = self.materials.materials
        if n:
            for mid in np.unique(self._IA[:n, 1]):
                sel = self._IA[:n, 1] == mid
                m = mats[int(mid)]
                r = float(self._P[:n, 9][sel].min())
                best = min(best, rayleigh_time(r, m.density, m.shear_modulus, m.poisson))
        for f in self._factories:
            m = mats[f.material_id]
            best = min(best, rayleigh_time(f.r_min, m.density, m.shear_modulus, m.poisson))
        if not math.isfinite(best):
            raise ValueError("dt: no particles (or factories) to derive the Rayleigh time from")
        return best

    def _rayleigh_dt(self) -> float:
        return self.dt_fraction * self.rayleigh_time()

    def _check_dt(self) -> None:
        try:
            tr = self.rayleigh_time()
        except ValueError:
            return
        if self._dt > self.dt_fraction * tr * (1 + 1e-9):  # type: ignore[operator]
            warnings.warn(
                f"dt = {self._dt:.4g} s exceeds {self.dt_fraction:g} x Rayleigh time "
                f"({tr:.4g} s) of the smallest particle",
                RuntimeWarning,
                stacklevel=3,
            )

    def _check_resolution(self) -> None:
        """Warn (once) if a Hertz contact at the current speeds lasts fewer than 10 steps."""
        if self._warned_resolution or self._n == 0:
            return
        n = self._n
        vmax = float(np.sqrt(np.max(np.sum(self._P[:n, 3:6] ** 2, axis=1))))
        vwall = 0.0
        for mp in self._mesh_par:
            if mp[0] == 1:
                r = np.max(np.linalg.norm(self._tri_x.reshape(-1, 3) - mp[1:4], axis=1))
                vwall = max(vwall, abs(mp[7]) * r)
            elif mp[0] == 2:
                vwall = max(vwall, float(np.linalg.norm(mp[8:11])))
        for cy in self._cyls:
            vwall = max(vwall, abs(cy[8]) * cy[6])
        v = max(2.0 * vmax, vmax + vwall, 1e-3)
        i = int(np.argmin(self._P[:n, 9]))
        r, m = self._P[i, 9], self._P[i, 10]
        mat = int(self._IA[i, 1])
        tc = hertz_contact_time(0.5 * m, 0.5 * r, float(self._pt[0, mat, mat]), v)
        if tc < 10.0 * self.dt:
            self._warned_resolution = True
            warnings.warn(
                f"contacts under-resolved: a Hertz impact at {v:.3g} m/s lasts {tc:.3g} s = "
                f"{tc / self.dt:.1f} steps (< 10); reduce dt or dt_fraction",
                RuntimeWarning,
                stacklevel=3,
            )

    # ----------------------------------------------------------------------------------------
    # neighbour lists and forces
    # ----------------------------------------------------------------------------------------
    def _skin(self) -> float:
        return self.skin if self.skin is not None else 1e-3

    def _rebuild(self) -> None:
        serial = self._serial()
        while True:
            status, n_new, needed = rebuild(
                self._n, self._P, self._F, self._IA, self._XB, self._rm, self._whist,
                self._nb, self._hist, self._nown, self._rev_o, self._rev_k, self._nrev,
                self._cur, self._tri_nb, self._thist, self._ntri, self._tri_x, self._tri_xb,
                self._dom, self._per, self._skin(), max(self._rmax, 1e-12), self._removed,
                not serial,
            )  # fmt: skip
            if status == 0:
                self._n = int(n_new)
                self._counters[1] += 1
                self._reverse_stale = serial
                return
            self._grow(int(status), int(needed))

    def _ensure_reverse(self) -> None:
        """Build the reverse lists for the two-pass scheme if the lists were last rebuilt
        without them (by the scatter scheme, or loaded from a checkpoint)."""
        if self._serial() or not self._reverse_stale:
            return
        c = int(self._cur[0])
        while True:
            needed = reverse_lists(self._n, self._nb[c], self._nown[c], self._rev_o, self._rev_k,
                                   self._nrev)  # fmt: skip
            if needed <= self._rev_o.shape[1]:
                self._reverse_stale = False
                return
            self._grow(2, int(needed))

    def _grow(self, status: int, needed: int) -> None:
        extra = max(2, needed // 8)  # lists stay narrow: less memory traffic per step
        if status == 1:
            self._resize(kown=needed + extra)
        elif status == 2:
            self._resize(krev=needed + extra)
        else:
            self._resize(ktri=needed + extra)

    def _ensure_lists(self) -> None:
        if np.any(self._rm[: self._n] != 0):
            self._rebuild()

    def _serial(self) -> bool:
        """Whether the (chunked) pair scatter is used (``pair_scheme``)."""
        if self.pair_scheme not in ("auto", "scatter", "two_pass"):
            raise ValueError(
                f"pair_scheme must be 'auto', 'scatter' or 'two_pass', got {self.pair_scheme!r}"
            )
        return self.pair_scheme != "two_pass"

    def _chunk_buffers(self) -> tuple[np.ndarray, np.ndarray]:
        """The scatter's force buffers (chunks after the first) and chunk bounds, sized to
        ``pair_chunks``."""
        k = int(self.pair_chunks)
        if k < 1:
            raise ValueError(f"pair_chunks must be >= 1, got {self.pair_chunks}")
        if self._bounds.shape[0] != k + 1:
            self._acc = np.zeros((k - 1, self._cap, 6))
            self._bounds = np.zeros(k + 1, np.int64)
            self._work = np.zeros((k, BLOCK_WORDS))
        return self._acc, self._bounds

    def _compute_forces(self) -> None:
        self._chunk_buffers()
        self._ensure_reverse()
        compute_forces(
            self._n, self._P, self._F, self._IA, self._whist, self._nb, self._hist, self._nown,
            self._rev_o, self._rev_k, self._nrev, self._pstart, self._nbf, self._live, self._clist,
            self._work, self._pf,
            self._acc, self._bounds, self._cur,
            self._tri_nb, self._thist, self._ntri, self._mint, self._mflt, self._mcnt,
            self._mwork, self._tri_x, self._tri_mesh, self._mesh_par, self._planes, self._cyls,
            self._pt, self._dom, self._per,
            self._grav, self.dt, self.t, self._serial(),
        )  # fmt: skip
        self._forces_stale = False

    def _freeze_dt(self) -> float:
        if not self._dt_frozen:
            if not self._dt_user:
                self._dt = self._rayleigh_dt()
            else:
                self._check_dt()
            self._dt_frozen = True
        return self._dt  # type: ignore[return-value]

    # ----------------------------------------------------------------------------------------
    # running
    # ----------------------------------------------------------------------------------------
    def run(
        self,
        duration_s: float,
        callback: Callable[[Simulation], object] | None = None,
        callback_every_s: float | None = None,
        progress: bool = False,
    ) -> Simulation:
        """Advance by ``duration_s`` (rounded to whole steps).

        ``callback(sim)`` is called every ``callback_every_s`` of simulated time (rounded to whole
        steps; default: only at the end). ``progress`` shows a tqdm bar with the simulated time and
        the particle-steps per second.
        """
        if not duration_s >= 0:
            raise ValueError(f"duration_s must be >= 0, got {duration_s}")
        if callback_every_s is not None and not callback_every_s > 0:
            raise ValueError(f"callback_every_s must be > 0, got {callback_every_s}")
        dt = self._freeze_dt()
        self._check_chunks(numba.get_num_threads())
        nsteps = int(round(duration_s / dt))
        cb_every = nsteps if callback_every_s is None else max(1, int(round(callback_every_s / dt)))
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=round(nsteps * dt, 9), unit="s(sim)", desc="DEM", leave=True)
        done = 0
        chunk_max = 64
        self._check_resolution()
        threads0 = numba.get_num_threads()
        chooser = self._thread_chooser(threads0)
        try:
            while done < nsteps or (done == 0 and nsteps == 0):
                self._insert_due()
                if self._forces_stale:
                    self._ensure_lists()
                    self._compute_forces()
                if nsteps == 0:
                    break
                todo = nsteps - done
                to_cb = cb_every - (done % cb_every)
                chunk = min(todo, to_cb, chunk_max)
                nf = self._next_factory_step()
                if nf is not None:
                    chunk = min(chunk, max(1, nf - self._step))
                n0 = self._n
                status, k, n, el = self._advance(chunk, dt, chooser)
                self.wall_time_s += el
                self._step += int(k)
                done += int(k)
                self._n = int(n)
                if status != 0:
                    self._grow(int(status), int(self._counters[2]))
                    continue
                # adapt the chunk so that the Python loop returns about every 0.2 s
                if el > 0:
                    chunk_max = int(min(max(chunk * 0.2 / el, 1), 100000))
                if bar is not None:
                    bar.update(round(done * dt, 9) - bar.n)
                    bar.set_postfix_str(f"{n0 * k / max(el, 1e-12):.3g} particle-steps/s")
                if callback is not None and done % cb_every == 0:
                    callback(self)
                self._check_resolution()
        finally:
            numba.set_num_threads(threads0)
            if bar is not None:
                bar.close()
        return self

    def _check_chunks(self, threads: int) -> None:
        """Warn once when the pair scatter has fewer chunks than there are threads: its chunks
        run on at most ``pair_chunks`` threads (a state saved by a one-thread run keeps one chunk
        when it is resumed; :meth:`load_checkpoint` with ``pair_chunks`` re-chunks it)."""
        if self._warned_chunks or not self._serial() or threads <= self.pair_chunks:
            return
        self._warned_chunks = True
        warnings.warn(
            f"the pair forces are summed in pair_chunks={self.pair_chunks} chunk(s) and run on "
            f"at most that many of the {threads} threads; load the checkpoint with "
            f"pair_chunks={threads} (twin dem run --resume --pair-chunks {threads}) to use them "
            "all (the sums then run in another order: not bit-identical to the saved run)",
            RuntimeWarning,
            stacklevel=3,
        )

    def _advance(
        self, chunk: int, dt: float, chooser: ThreadChooser | None
    ) -> tuple[int, int, int, float]:
        """``chunk`` steps of the integrator (on the thread count the chooser picks): (status,
        steps done, particles, wall seconds)."""
        if chooser is not None:
            numba.set_num_threads(chooser.next_threads())
        n0 = self._n
        self._chunk_buffers()
        self._ensure_reverse()
        rebuilds0 = int(self._counters[1])
        t0 = time.perf_counter()
        status, k, n = advance(
            chunk, self._step, dt, self._n, self._P, self._F, self._IA, self._XB,
            self._rm, self._whist,
            self._nb, self._hist, self._nown, self._rev_o, self._rev_k, self._nrev,
            self._pstart, self._nbf, self._live, self._clist, self._work,
            self._pf, self._acc, self._bounds, self._cur, self._tri_nb, self._thist, self._ntri,
            self._mint, self._mflt, self._mcnt, self._mwork, self._tri_x0, self._tri_x,
            self._tri_xb, self._tri_mesh,
            self._mesh_par,
            bool(np.any(self._mesh_par[:, 0] != 0)) if len(self._mesh_par) else False,
            self._planes, self._cyls, self._sinks, self._pt, self._dom, self._per,
            self._grav, self._skin(), max(self._rmax, 1e-12), self._removed,
            self._counters, self._serial(),
        )  # fmt: skip
        el = time.perf_counter() - t0
        if self._serial() and int(self._counters[1]) != rebuilds0:
            self._reverse_stale = True  # rebuilt without the reverse lists
        if chooser is not None:
            chooser.record(numba.get_num_threads(), n0 * int(k), el)
        return int(status), int(k), int(n), el

    def _thread_chooser(self, max_threads: int) -> ThreadChooser | None:
        """The run's thread chooser when the thread policy is adaptive (kept across runs)."""
        policy = self.thread_policy if self.thread_policy is not None else current_policy()
        if policy not in ("adaptive", "fixed"):
            raise ValueError(f"thread_policy must be 'adaptive' or 'fixed', got {policy!r}")
        if policy != "adaptive" or max_threads < 2:
            return None
        if self.thread_chooser is None or self.thread_chooser.candidates[-1] != max_threads:
            self.thread_chooser = ThreadChooser(max_threads)
        return self.thread_chooser

    def _next_factory_step(self) -> int | None:
        best = None
        for f in self._factories:
            t = f.next_time()
            if math.isfinite(t):
                s = int(math.ceil(t / self.dt - 1e-9))
                best = s if best is None else min(best, s)
        return best

    def _insert_due(self) -> None:
        for f in self._factories:
            while not f.done and f.next_time() <= self.t + 1e-12:
                want = f.take_due(self.t)
                if want:
                    ids = self.insert_particles(
                        want, f.region, f.radius, f.material_id, f.type_id, vel=f.velocity,
                        seed=f.rng, strict=False,
                    )  # fmt: skip
                    f.n_inserted += ids.size

    # ----------------------------------------------------------------------------------------
    # checkpoints
    # ----------------------------------------------------------------------------------------
    def save_checkpoint(self, path: str | Path) -> Path:
        """Write the complete state (``.npz``) so that :meth:`load_checkpoint` continues
        bit-identically (same thread-count-independent results); written to a temporary file
        first and renamed, so a process killed while writing leaves the previous checkpoint."""
        path = Path(path)
        n = self._n
        c = int(self._cur[0])
        cfg = {
            "version": _CHECKPOINT_VERSION,
            "materials": self.materials.to_dict(),
            "dt": self._dt,
            "dt_user": self._dt_user,
            "dt_frozen": self._dt_frozen,
            "dt_fraction": self.dt_fraction,
            "skin": self.skin,
            "seed": self.seed,
            "pair_scheme": self.pair_scheme,
            "pair_chunks": self.pair_chunks,
            "step": self._step,
            "next_id": self._next_id,
            "rmax": self._rmax,
            "forces_stale": self._forces_stale,
            "warned_resolution": self._warned_resolution,
            "meshes": self._meshes,
            "factories": [f.to_dict() for f in self._factories],
        }
        arrays = {
            "P": self._P[:n], "F": self._F[:n], "IA": self._IA[:n], "XB": self._XB[:n],
            "rm": self._rm[:n], "whist": self._whist[:n],
            "nb": self._nb[c, :n], "hist": self._hist[c, :n], "nown": self._nown[c, :n],
            "rev_o": self._rev_o[:n], "rev_k": self._rev_k[:n], "nrev": self._nrev[:n],
            "tri_nb": self._tri_nb[c, :n], "thist": self._thist[c, :n], "ntri": self._ntri[c, :n],
            "tri_x0": self._tri_x0, "tri_x": self._tri_x, "tri_xb": self._tri_xb,
            "tri_mesh": self._tri_mesh, "mesh_par": self._mesh_par,
            "planes": self._planes, "cyls": self._cyls, "sinks": self._sinks,
            "removed": self._removed, "counters": self._counters,
            "dom": self._dom, "per": self._per, "grav": self._grav,
        }  # fmt: skip
        tmp = path.with_name(path.name + ".tmp")  # a run killed while writing keeps the last one
        with open(tmp, "wb") as fh:
            np.savez(fh, config=np.array(json.dumps(cfg)), **arrays)
        tmp.replace(path)
        return path

    @classmethod
    def load_checkpoint(cls, path: str | Path, *, pair_chunks: int | None = None) -> Simulation:
        """Recreate a simulation saved with :meth:`save_checkpoint`.

        ``pair_chunks``: None keeps the saved run's chunks of the pair scatter (a resumed run
        sums its forces as the run that wrote it); a number re-chunks it. The scatter runs its
        chunks on at most that many threads: a state saved by a one-thread run and continued on
        two threads needs ``pair_chunks=2`` for the pair forces (~40 % of a step) to use both.
        """
        with np.load(Path(path), allow_pickle=False) as z:
            cfg = json.loads(str(z["config"]))
            if cfg.get("version") != _CHECKPOINT_VERSION:
                raise ValueError(f"checkpoint version must be {_CHECKPOINT_VERSION}, got "
                                 f"{cfg.get('version')}")  # fmt: skip
            a = {k: z[k] for k in z.files if k != "config"}
        dom = a["dom"]
        sim = cls(
            dom[0:3], dom[3:6], periodic=tuple(bool(p) for p in a["per"]),
            gravity=a["grav"], materials=MaterialTable.from_dict(cfg["materials"]),
            dt=cfg["dt"] if cfg["dt_user"] else None, dt_fraction=cfg["dt_fraction"],
            skin=cfg["skin"], seed=cfg["seed"], pair_scheme=cfg.get("pair_scheme", "auto"),
            pair_chunks=cfg.get("pair_chunks") if pair_chunks is None else pair_chunks,
        )  # fmt: skip
        n = a["P"].shape[0]
        kown = max(a["nb"].shape[1], 1)
        krev = max(a["rev_o"].shape[1], 1)
        ktri = max(a["tri_nb"].shape[1], 1)
        sim._alloc(max(n, 16), kown, krev, ktri)
        sim._n = n
        sim._P[:n] = a["P"]
        sim._F[:n] = a["F"]
        sim._IA[:n] = a["IA"]
        sim._XB[:n] = a["XB"]
        sim._rm[:n] = a["rm"]
        sim._nb[0, :n] = a["nb"]
        sim._hist[0, :n] = a["hist"]
        sim._nown[0, :n] = a["nown"]
        sim._rev_o[:n] = a["rev_o"]
        sim._rev_k[:n] = a["rev_k"]
        sim._nrev[:n] = a["nrev"]
        sim._tri_nb[0, :n] = a["tri_nb"]
        sim._thist[0, :n] = a["thist"]
        sim._ntri[0, :n] = a["ntri"]
        sim._cur[0] = 0
        sim._planes = _with_window(a["planes"], _PLANE_COLS)
        sim._cyls = _with_window(a["cyls"], _CYL_COLS)
        sim._whist = np.zeros((sim._cap, a["whist"].shape[1], 3))
        sim._whist[:n] = a["whist"]
        sim._tri_x0 = a["tri_x0"]
        sim._tri_x = a["tri_x"]
        sim._tri_xb = a["tri_xb"]
        sim._tri_mesh = a["tri_mesh"]
        sim._mesh_par = a["mesh_par"]
        sim._meshes = cfg["meshes"]
        sim._sinks = a["sinks"]
        sim._removed = a["removed"]
        sim._counters = a["counters"].copy()
        sim._dt = cfg["dt"]
        sim._dt_frozen = cfg["dt_frozen"]
        sim._step = cfg["step"]
        sim._next_id = cfg["next_id"]
        sim._rmax = cfg["rmax"]
        sim._forces_stale = cfg["forces_stale"]
        sim._warned_resolution = cfg["warned_resolution"]
        sim._factories = [ParticleFactory.from_dict(f) for f in cfg["factories"]]
        for m in sim._meshes:
            m["motion"] = m["motion"]
        return sim

    def mesh_motion(self, mesh_id: int) -> RotationMotion | TranslationMotion | None:
        """The motion given to :meth:`add_mesh`."""
        return motion_from_dict(self._meshes[mesh_id]["motion"])
