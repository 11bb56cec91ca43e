"""Measurement sensors for DEM runs, fed with successive particle states.

Every sensor has ``update(state)``, where ``state`` is anything with the engine's attribute
names (``t, ids, type_id, radius, pos, vel`` and optionally ``omega``) or a
:class:`twin_core.dem.frames.Frame`. Pass it from the run callback
(``sim.run(T, callback=sensor.update, callback_every_s=dt)``) or replay stored frames. Particles
are matched between states by id, so insertion and removal are handled; periodic axes are
handled through the minimum-image (unwrapped) displacement between two states, which is exact
as long as a particle moves less than half a period between updates.

Sensors:

* :class:`PlaneFlowSensor` - mass flow through a plane (optionally a window of it), by type and
  direction, from crossing events timed by linear interpolation.
* :class:`BoxFlowSensor` - entries/exits of an axis-aligned box per type and its content.
* :class:`GridFieldSensor` - per-cell counts, time-averaged velocity, solid fraction and face
  crossings between neighbouring cells (voxel traversal of each displacement), written in the
  compartment-model ``.npz`` field format.
* :class:`ContactSensor` / :func:`contacts_by_type` - contacts by type pair (AA/AB/BB) from
  positions, with overlaps.
* :class:`ResidenceTimeSensor` - entry/exit times across two planes and residence times.
* :class:`PeriodicTransitSensor` - transit times across a periodic length (the section RTD).
* :class:`EnergySensor` - kinetic, rotational and potential energy.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

__all__ = [
    "BoxFlowSensor",
    "ContactSensor",
    "EnergySensor",
    "GridFieldSensor",
    "PeriodicTransitSensor",
    "PlaneFlowSensor",
    "ResidenceTimeSensor",
    "State",
    "bin_events",
    "contacts_by_type",
    "particle_masses",
    "state_view",
]


@dataclass
class State:
    """Read-only view of a particle state (arrays are not copied)."""

    t: float
    ids: np.ndarray
    types: np.ndarray
    radii: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    omega: np.ndarray | None = None


def _attr(obj: Any, *names: str, default: Any = AttributeError) -> Any:
    for n in names:
        if hasattr(obj, n):
            return getattr(obj, n)
    if default is AttributeError:
        raise AttributeError(f"state has none of the attributes {names}")
    return default


def state_view(state: Any) -> State:
    """Adapt an engine ``Simulation``, a ``Frame`` or a ``State`` to :class:`State`."""
    if isinstance(state, State):
        return state
    return State(
        t=float(_attr(state, "t")),
        ids=np.asarray(_attr(state, "ids")),
        types=np.asarray(_attr(state, "type_id", "types")),
        radii=np.asarray(_attr(state, "radius", "radii"), dtype=float),
        pos=np.asarray(_attr(state, "pos", "positions"), dtype=float),
        vel=np.asarray(_attr(state, "vel", "velocities"), dtype=float),
        omega=_attr(state, "omega", default=None),
    )


def particle_masses(radii: np.ndarray, types: np.ndarray, density: float | dict) -> np.ndarray:
    """m = 4/3 pi r^3 rho, with ``density`` a number or a mapping type -> kg/m^3."""
    r = np.asarray(radii, float)
    if isinstance(density, dict):
        rho = np.array([density[int(k)] for k in np.asarray(types)], dtype=float)
    else:
        if density <= 0:
            raise ValueError(f"density must be > 0, got {density}")
        rho = float(density)
    return 4.0 / 3.0 * np.pi * r**3 * rho


def _periodic_lengths(periodic_lengths: Any) -> np.ndarray:
    if periodic_lengths is None:
        return np.zeros(3)
    L = np.asarray(periodic_lengths, float).reshape(3)
    if np.any(L < 0):
        raise ValueError(f"periodic_lengths must be >= 0 (0 = not periodic), got {L.tolist()}")
    return L


def _match_ids(sorted_ids: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position of each of ``ids`` in the ascending array ``sorted_ids`` and whether it is there
    (positions of absent ids are clipped into range and meaningless)."""
    k = np.searchsorted(sorted_ids, ids)
    k = np.clip(k, 0, max(len(sorted_ids) - 1, 0))
    ok = (sorted_ids[k] == ids) if len(sorted_ids) else np.zeros(len(ids), bool)
    return k, ok


class _Tracker:
    """Keeps the previous state and matches particles by id."""

    def __init__(self, periodic_lengths: Any = None) -> None:
        self.L = _periodic_lengths(periodic_lengths)
        self.prev: State | None = None
        self._order: np.ndarray | None = None

    def step(self, s: State) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
        """Return (index into current, start positions, unwrapped end positions, previous t)
        for particles present in both the previous and the current state; None on the first
        call."""
        out = None
        if self.prev is not None:
            p = self.prev
            if s.t < p.t:
                raise ValueError(f"state t must not go backwards: {s.t} < {p.t}")
            k, ok = _match_ids(p.ids[self._order], s.ids)
            cur = np.nonzero(ok)[0]
            prev_idx = self._order[k[ok]]
            a = p.pos[prev_idx]
            d = s.pos[cur] - a
            per = self.L > 0
            if per.any():
                d[:, per] -= self.L[per] * np.round(d[:, per] / self.L[per])
            out = (cur, a, a + d, p.t)
        self.prev = State(
            s.t, s.ids.copy(), s.types.copy(), s.radii.copy(), s.pos.copy(), s.vel.copy()
        )
        self._order = np.argsort(self.prev.ids, kind="stable")
        return out


def bin_events(
    times: np.ndarray,
    weights: np.ndarray,
    bin_s: float,
    t0: float = 0.0,
    t1: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Histogram weighted events into bins of ``bin_s``; returns (bin centres, sum / bin_s)."""
    if bin_s <= 0:
        raise ValueError(f"bin_s must be > 0, got {bin_s}")
    times = np.asarray(times, float)
    if t1 is None:
        t1 = float(times.max()) if len(times) else t0 + bin_s
    n = max(1, int(np.ceil((t1 - t0) / bin_s - 1e-9)))
    edges = t0 + bin_s * np.arange(n + 1)
    h, _ = np.histogram(times, bins=edges, weights=weights)
    return 0.5 * (edges[1:] + edges[:-1]), h / bin_s


class PlaneFlowSensor:
    """Mass flow through the plane (x - point) . normal = 0, by particle type and direction.

    A crossing is a sign change of the signed distance between two successive states (of the
    unwrapped path when ``periodic_lengths`` is given; with a plane normal to a periodic axis all
    images x0 + kL of the plane count). Its time is interpolated linearly between the two
    states, and, if ``window=(lo, hi)`` is given, the interpolated crossing point must lie in
    that axis-aligned box (e.g. an orifice's bounding square, or use ``radius`` for a disc of
    that radius about ``point``). Events are stored; :meth:`flow` bins them.
    """

    def __init__(
        self,
        point: Any,
        normal: Any,
        density: float | dict,
        *,
        window: tuple[Any, Any] | None = None,
        radius: float | None = None,
        periodic_lengths: Any = None,
    ) -> None:
        self.point = np.asarray(point, float).reshape(3)
        n = np.asarray(normal, float).reshape(3)
        if np.linalg.norm(n) == 0:
            raise ValueError("normal must be non-zero")
        self.normal = n / np.linalg.norm(n)
        self.density = density
        self.window = None if window is None else (np.asarray(window[0]), np.asarray(window[1]))
        self.radius = radius
        self._tr = _Tracker(periodic_lengths)
        L = self._tr.L
        ax = np.nonzero(np.isclose(np.abs(self.normal), 1.0))[0]
        self.period = float(L[ax[0]]) if len(ax) and L[ax[0]] > 0 else 0.0
        self._ev: list[tuple[np.ndarray, ...]] = []

    def update(self, state: Any) -> None:
        s = state_view(state)
        m = self._tr.step(s)
        if m is None:
            return
        cur, a, b, t_prev = m
        da = (a - self.point) @ self.normal
        db = (b - self.point) @ self.normal
        if self.period > 0:
            ka = np.floor(da / self.period)
            kb = np.floor(db / self.period)
            ncross = (kb - ka).astype(np.int64)
            level = np.where(ncross > 0, kb, ka) * self.period  # plane image crossed (nearest)
        else:
            ncross = (db > 0).astype(np.int64) - (da > 0).astype(np.int64)
            level = np.zeros(len(da))
        sel = np.nonzero(ncross != 0)[0]
        if len(sel):
            frac = np.clip((level[sel] - da[sel]) / (db[sel] - da[sel]), 0.0, 1.0)
            xc = a[sel] + frac[:, None] * (b[sel] - a[sel])
            keep = np.ones(len(sel), bool)
            if self.window is not None:
                keep &= np.all((xc >= self.window[0]) & (xc <= self.window[1]), axis=1)
            if self.radius is not None:
                rel = xc - self.point
                rel -= np.outer(rel @ self.normal, self.normal)
                keep &= np.linalg.norm(rel, axis=1) <= self.radius
            sel, frac = sel[keep], frac[keep]
            if len(sel):
                idx = cur[sel]
                tc = t_prev + frac * (s.t - t_prev)
                mass = particle_masses(s.radii[idx], s.types[idx], self.density)
                self._ev.append(
                    (
                        tc,
                        s.ids[idx].astype(np.int64),
                        s.types[idx].astype(np.int64),
                        mass,
                        ncross[sel],
                    )
                )

    @property
    def events_(self) -> dict[str, np.ndarray]:
        """Crossing events: ``t, id, type, mass, n`` (n = +k / -k crossings along the normal)."""
        if not self._ev:
            return {
                "t": np.zeros(0),
                "id": np.zeros(0, np.int64),
                "type": np.zeros(0, np.int64),
                "mass": np.zeros(0),
                "n": np.zeros(0, np.int64),
            }
        cols = list(zip(*self._ev))
        return {k: np.concatenate(c) for k, c in zip(("t", "id", "type", "mass", "n"), cols)}

    def flow(
        self, bin_s: float, t0: float = 0.0, t1: float | None = None, *, types: Any = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Net mass flow rate (kg/s, + along the normal) in bins: returns (t, flow) where flow
        has one column per entry of ``types`` (default: the types seen) plus a last total column."""
        ev = self.events_
        if types is None:
            types = np.unique(ev["type"]) if len(ev["type"]) else np.zeros(0, np.int64)
        cols = []
        tc = None
        for ty in types:
            m = ev["type"] == ty
            tc, f = bin_events(ev["t"][m], ev["mass"][m] * ev["n"][m], bin_s, t0, t1)
            cols.append(f)
        tc, tot = bin_events(ev["t"], ev["mass"] * ev["n"], bin_s, t0, t1)
        return tc, np.column_stack([*cols, tot])

    def total_mass(self) -> float:
        ev = self.events_
        return float(np.sum(ev["mass"] * ev["n"]))


def _in_box(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.all((p >= lo) & (p < hi), axis=1)


class BoxFlowSensor:
    """Entries into / exits from an axis-aligned box [lo, hi) per type, and its content.

    An entry (exit) is recorded when a tracked particle's centre goes from outside (inside) to
    inside (outside) between two states, at the mid time of the two states. Particles appearing
    or disappearing (insertion, removal) are counted in ``content_`` but not as flow.
    """

    def __init__(self, lo: Any, hi: Any, density: float | dict, *, periodic_lengths: Any = None):
        self.lo = np.asarray(lo, float).reshape(3)
        self.hi = np.asarray(hi, float).reshape(3)
        if np.any(self.hi <= self.lo):
            raise ValueError(
                f"box hi must exceed lo, got lo={self.lo.tolist()}, hi={self.hi.tolist()}"
            )
        self.density = density
        self._tr = _Tracker(periodic_lengths)
        self._entries: list[tuple[np.ndarray, ...]] = []
        self._exits: list[tuple[np.ndarray, ...]] = []
        self.content_t_: list[float] = []
        self.content_: list[dict[int, tuple[int, float]]] = []

    def update(self, state: Any) -> None:
        s = state_view(state)
        inside = _in_box(s.pos, self.lo, self.hi)
        masses = particle_masses(s.radii, s.types, self.density)
        content = {}
        for ty in np.unique(s.types):
            m = inside & (s.types == ty)
            content[int(ty)] = (int(m.sum()), float(masses[m].sum()))
        self.content_t_.append(s.t)
        self.content_.append(content)
        m = self._tr.step(s)
        if m is not None:
            cur, a, _, t_prev = m
            was = _in_box(a, self.lo, self.hi)
            now = inside[cur]
            tm = 0.5 * (t_prev + s.t)
            for store, sel in ((self._entries, ~was & now), (self._exits, was & ~now)):
                idx = cur[sel]
                if len(idx):
                    store.append(
                        (np.full(len(idx), tm), s.types[idx].astype(np.int64), masses[idx])
                    )

    @staticmethod
    def _cat(store: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if not store:
            return np.zeros(0), np.zeros(0, np.int64), np.zeros(0)
        t, ty, m = zip(*store)
        return np.concatenate(t), np.concatenate(ty), np.concatenate(m)

    def inflow(
        self, bin_s: float, t0: float = 0.0, t1: float | None = None, *, type_id: int | None = None
    ):
        """Binned entering mass rate (kg/s): returns (t, rate)."""
        t, ty, m = self._cat(self._entries)
        sel = np.ones(len(t), bool) if type_id is None else ty == type_id
        return bin_events(t[sel], m[sel], bin_s, t0, t1)

    def outflow(
        self, bin_s: float, t0: float = 0.0, t1: float | None = None, *, type_id: int | None = None
    ):
        """Binned leaving mass rate (kg/s): returns (t, rate)."""
        t, ty, m = self._cat(self._exits)
        sel = np.ones(len(t), bool) if type_id is None else ty == type_id
        return bin_events(t[sel], m[sel], bin_s, t0, t1)

    def content_series(
        self, type_id: int | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t, count, mass) of particles inside the box at each update (one type or all)."""
        t = np.asarray(self.content_t_)
        cnt = np.zeros(len(t), np.int64)
        mass = np.zeros(len(t))
        for i, c in enumerate(self.content_):
            for ty, (n, mm) in c.items():
                if type_id is None or ty == type_id:
                    cnt[i] += n
                    mass[i] += mm
        return t, cnt, mass


@njit(cache=True)
def _face_coord(edges: np.ndarray, n: int, period: float, k: int, direction: int) -> float:
    if period > 0:
        q = k // n
        r = k - q * n
        return edges[r] + q * period
    if 0 <= k <= n:
        return edges[k]
    return np.inf if direction > 0 else -np.inf


@njit(cache=True)
def _unwrapped_index(edges: np.ndarray, n: int, period: float, x: float) -> int:
    if period > 0:
        q = int(np.floor((x - edges[0]) / period))
        xl = x - q * period
        loc = np.searchsorted(edges, xl, side="right") - 1
        loc = min(max(loc, 0), n - 1)
        return q * n + loc
    return np.searchsorted(edges, x, side="right") - 1


@njit(cache=True)
def _wrap_valid(k: int, n: int, period: float) -> int:
    if period > 0:
        return k % n
    if 0 <= k < n:
        return k
    return -1


@njit(cache=True)
def _traverse(
    a: np.ndarray,
    b: np.ndarray,
    ex: np.ndarray,
    ey: np.ndarray,
    ez: np.ndarray,
    periods: np.ndarray,
    cx: np.ndarray,
    cy: np.ndarray,
    cz: np.ndarray,
) -> None:
    """Voxel traversal of segments a[i] -> b[i]; counts face crossings into cx, cy, cz
    (shape (nx, ny, nz, 2): [..., 0] + direction, [..., 1] - direction, at the + face of
    the cell)."""
    nn = np.array([len(ex) - 1, len(ey) - 1, len(ez) - 1])
    idx = np.zeros(3, np.int64)
    for p in range(a.shape[0]):
        for ax in range(3):
            e = ex if ax == 0 else (ey if ax == 1 else ez)
            idx[ax] = _unwrapped_index(e, nn[ax], periods[ax], a[p, ax])
        for _guard in range(10000):
            best = 2.0
            best_ax = -1
            for ax in range(3):
                d = b[p, ax] - a[p, ax]
                if d == 0.0:
                    continue
                e = ex if ax == 0 else (ey if ax == 1 else ez)
                direction = 1 if d > 0 else -1
                k = idx[ax] + 1 if direction > 0 else idx[ax]
                f = _face_coord(e, nn[ax], periods[ax], k, direction)
                tf = (f - a[p, ax]) / d
                if tf < best:
                    best = tf
                    best_ax = ax
            if best_ax < 0 or best > 1.0:
                break
            d = b[p, best_ax] - a[p, best_ax]
            if d > 0:
                lower = idx[best_ax]  # crossing the + face of this cell, + direction
                col = 0
                idx[best_ax] += 1
            else:
                lower = idx[best_ax] - 1
                col = 1
                idx[best_ax] -= 1
            n_ax = nn[best_ax]
            li = _wrap_valid(lower, n_ax, periods[best_ax])
            if li < 0 or (periods[best_ax] == 0 and li == n_ax - 1):
                continue
            i0 = li if best_ax == 0 else _wrap_valid(idx[0], nn[0], periods[0])
            i1 = li if best_ax == 1 else _wrap_valid(idx[1], nn[1], periods[1])
            i2 = li if best_ax == 2 else _wrap_valid(idx[2], nn[2], periods[2])
            if i0 < 0 or i1 < 0 or i2 < 0:
                continue
            if best_ax == 0:
                cx[i0, i1, i2, col] += 1
            elif best_ax == 1:
                cy[i0, i1, i2, col] += 1
            else:
                cz[i0, i1, i2, col] += 1


class GridFieldSensor:
    """Per-cell statistics on a rectilinear grid (edges per axis, metres).

    Averaged over updates with t >= ``t_start``: ``occupancy`` (mean particle count per cell),
    ``velocity`` (mean particle velocity per cell, 0 where no particle was seen),
    ``solid_fraction`` (mean of sum of particle volumes whose centre is in the cell / cell
    volume - a centre-counting estimate, biased low in cells cut by walls), and crossings of the
    faces between neighbouring cells counted by a voxel traversal of each particle's
    (unwrapped) straight displacement between updates - updates must be frequent enough that
    the straight path is a fair approximation (a displacement of less than a cell).
    ``crossings_a[i, j, k, 0]`` counts + direction crossings of the + face of cell (i, j, k)
    along axis a, ``[..., 1]`` - direction; periodic axes wrap, the last face of a closed axis
    stays 0. :meth:`save_npz` writes the compartment-model field format.
    """

    def __init__(
        self,
        x_edges: Any,
        y_edges: Any,
        z_edges: Any,
        density: float | dict,
        *,
        periodic: tuple[bool, bool, bool] = (False, False, False),
        t_start: float = 0.0,
    ) -> None:
        self.edges = [np.asarray(e, float) for e in (x_edges, y_edges, z_edges)]
        for name, e in zip("xyz", self.edges):
            if e.ndim != 1 or len(e) < 2 or np.any(np.diff(e) <= 0):
                raise ValueError(f"{name}_edges must be increasing with >= 2 entries")
        self.periodic = tuple(bool(p) for p in periodic)
        self.periods = np.array(
            [e[-1] - e[0] if p else 0.0 for e, p in zip(self.edges, self.periodic)]
        )
        self.shape = tuple(len(e) - 1 for e in self.edges)
        self.density = density
        self.t_start = t_start
        self._tr = _Tracker(self.periods)
        self.n_samples = 0
        self.t_first: float | None = None
        self.t_last: float | None = None
        self.count_sum = np.zeros(self.shape)
        self.vel_sum = np.zeros((*self.shape, 3))
        self.vol_sum = np.zeros(self.shape)
        self.crossings = [np.zeros((*self.shape, 2), np.int64) for _ in range(3)]
        self._mass_sum = 0.0
        self._mass_n = 0
        dv = [np.diff(e) for e in self.edges]
        self.cell_volume = dv[0][:, None, None] * dv[1][None, :, None] * dv[2][None, None, :]

    def cell_index(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell index (n, 3) of each position (periodic axes wrapped) and validity mask."""
        idx = np.empty((len(pos), 3), np.int64)
        ok = np.ones(len(pos), bool)
        for ax in range(3):
            e = self.edges[ax]
            x = pos[:, ax]
            if self.periods[ax] > 0:
                x = e[0] + np.mod(x - e[0], self.periods[ax])
            k = np.searchsorted(e, x, side="right") - 1
            if self.periods[ax] > 0:
                k = np.clip(k, 0, self.shape[ax] - 1)
            ok &= (k >= 0) & (k < self.shape[ax])
            idx[:, ax] = k
        return idx, ok

    def update(self, state: Any) -> None:
        s = state_view(state)
        m = self._tr.step(s)
        if s.t < self.t_start - 1e-12:
            return
        if self.t_first is None:
            self.t_first = s.t
        else:
            if m is not None:
                _, a, b, _ = m
                _traverse(
                    np.ascontiguousarray(a),
                    np.ascontiguousarray(b),
                    *self.edges,
                    self.periods,
                    *self.crossings,
                )
        self.t_last = s.t
        idx, ok = self.cell_index(s.pos)
        flat = np.ravel_multi_index(idx[ok].T, self.shape)
        size = int(np.prod(self.shape))
        self.count_sum += np.bincount(flat, minlength=size).reshape(self.shape)
        for c in range(3):
            self.vel_sum[..., c] += np.bincount(flat, weights=s.vel[ok, c], minlength=size).reshape(
                self.shape
            )
        vol = 4.0 / 3.0 * np.pi * s.radii[ok] ** 3
        self.vol_sum += np.bincount(flat, weights=vol, minlength=size).reshape(self.shape)
        masses = particle_masses(s.radii, s.types, self.density)
        self._mass_sum += float(masses.sum())
        self._mass_n += len(masses)
        self.n_samples += 1

    def fields(self) -> dict[str, np.ndarray]:
        """The field dictionary of the compartment ``.npz`` format."""
        if self.n_samples == 0:
            raise ValueError("GridFieldSensor has no samples (t_start never reached?)")
        with np.errstate(invalid="ignore", divide="ignore"):
            vel = np.where(
                self.count_sum[..., None] > 0, self.vel_sum / self.count_sum[..., None], 0.0
            )
        return {
            "x_edges": self.edges[0],
            "y_edges": self.edges[1],
            "z_edges": self.edges[2],
            "velocity": vel,
            "solid_fraction": self.vol_sum / self.n_samples / self.cell_volume,
            "occupancy": self.count_sum / self.n_samples,
            "crossings_x": self.crossings[0].copy(),
            "crossings_y": self.crossings[1].copy(),
            "crossings_z": self.crossings[2].copy(),
            "duration_s": np.float64((self.t_last or 0.0) - (self.t_first or 0.0)),
            "particle_mass_kg": np.float64(self._mass_sum / max(self._mass_n, 1)),
            "periodic": np.array(self.periodic, dtype=bool),
        }

    def save_npz(self, path: str | Path) -> Path:
        path = Path(path)
        np.savez_compressed(path, **self.fields())
        return path


def contacts_by_type(
    pos: np.ndarray,
    radii: np.ndarray,
    types: np.ndarray,
    *,
    box: tuple[Any, Any] | None = None,
    periodic: tuple[bool, bool, bool] = (False, False, False),
    tolerance: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Particle pairs in contact, |x_i - x_j| < (r_i + r_j)(1 + tolerance), with the
    minimum-image distance on periodic axes of ``box=(lo, hi)``.

    Returns (pairs (m, 2) indices, overlap delta = r_i + r_j - |x_i - x_j| (m,), and the
    type-pair count matrix C[a, b] over the sorted unique types (symmetric, contacts between
    types a != b counted once in both C[a, b] and C[b, a]).
    """
    pos = np.asarray(pos, float)
    radii = np.asarray(radii, float)
    types = np.asarray(types)
    utypes = np.unique(types)
    if len(pos) < 2:
        return np.zeros((0, 2), np.int64), np.zeros(0), np.zeros((len(utypes),) * 2, np.int64)
    cutoff = 2 * radii.max() * (1 + tolerance)
    if any(periodic):
        if box is None:
            raise ValueError("box=(lo, hi) is required with periodic axes")
        lo = np.asarray(box[0], float)
        hi = np.asarray(box[1], float)
        ext = np.ptp(pos, axis=0)
        boxsize = np.where(periodic, hi - lo, 4 * (ext + cutoff) + 1.0)
        shifted = pos - np.where(periodic, lo, pos.min(axis=0) - cutoff)
        shifted = np.where(periodic, np.mod(shifted, boxsize), shifted)
        shifted = np.minimum(shifted, np.nextafter(boxsize, 0))
        tree = cKDTree(shifted, boxsize=boxsize)
    else:
        shifted = pos
        boxsize = None
        tree = cKDTree(pos)
    pairs = tree.query_pairs(cutoff, output_type="ndarray")
    if len(pairs) == 0:
        return pairs.reshape(0, 2), np.zeros(0), np.zeros((len(utypes),) * 2, np.int64)
    d = shifted[pairs[:, 0]] - shifted[pairs[:, 1]]
    if boxsize is not None:
        d -= boxsize * np.round(d / boxsize)
    dist = np.linalg.norm(d, axis=1)
    rsum = radii[pairs[:, 0]] + radii[pairs[:, 1]]
    keep = dist < rsum * (1 + tolerance)
    pairs, dist, rsum = pairs[keep], dist[keep], rsum[keep]
    ti = np.searchsorted(utypes, types[pairs[:, 0]])
    tj = np.searchsorted(utypes, types[pairs[:, 1]])
    C = np.zeros((len(utypes), len(utypes)), np.int64)
    np.add.at(C, (ti, tj), 1)
    C = C + C.T - np.diag(np.diag(C))
    return pairs, rsum - dist, C


class ContactSensor:
    """Contacts by type pair at each update (e.g. AA, AB, BB for two types) and overlap
    statistics (max and mean overlap / radius of the smaller particle of the pair)."""

    def __init__(
        self,
        *,
        box: tuple[Any, Any] | None = None,
        periodic: tuple[bool, bool, bool] = (False, False, False),
        tolerance: float = 0.0,
    ) -> None:
        self.box = box
        self.periodic = periodic
        self.tolerance = tolerance
        self.t_: list[float] = []
        self.counts_: list[dict[str, int]] = []
        self.max_overlap_: list[float] = []
        self.mean_overlap_: list[float] = []

    @staticmethod
    def label(a: int, b: int) -> str:
        letters = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"
        return letters[a] + letters[b]

    def update(self, state: Any) -> None:
        s = state_view(state)
        pairs, delta, C = contacts_by_type(
            s.pos, s.radii, s.types, box=self.box, periodic=self.periodic, tolerance=self.tolerance
        )
        counts = {}
        for i in range(C.shape[0]):
            for j in range(i, C.shape[0]):
                counts[self.label(i, j)] = int(C[i, j])
        self.t_.append(s.t)
        self.counts_.append(counts)
        if len(pairs):
            rmin = np.minimum(s.radii[pairs[:, 0]], s.radii[pairs[:, 1]])
            rel = np.maximum(delta, 0) / rmin
            self.max_overlap_.append(float(rel.max()))
            self.mean_overlap_.append(float(rel.mean()))
        else:
            self.max_overlap_.append(0.0)
            self.mean_overlap_.append(0.0)


class ResidenceTimeSensor:
    """Entry and exit times of particles across two planes (first + crossing of each, exits
    only after an entry); ``residence_times_`` = exit - entry for particles that did both."""

    def __init__(
        self, entry: tuple[Any, Any], exit: tuple[Any, Any], *, periodic_lengths: Any = None
    ):
        self._in = PlaneFlowSensor(entry[0], entry[1], 1.0, periodic_lengths=periodic_lengths)
        self._out = PlaneFlowSensor(exit[0], exit[1], 1.0, periodic_lengths=periodic_lengths)

    def update(self, state: Any) -> None:
        self._in.update(state)
        self._out.update(state)

    @staticmethod
    def _first(ev: dict[str, np.ndarray]) -> dict[int, float]:
        first: dict[int, float] = {}
        for t, i, n in zip(ev["t"], ev["id"], ev["n"]):
            if n > 0 and int(i) not in first:
                first[int(i)] = float(t)
        return first

    @property
    def entry_times_(self) -> dict[int, float]:
        return self._first(self._in.events_)

    @property
    def exit_times_(self) -> dict[int, float]:
        entry = self.entry_times_
        out: dict[int, float] = {}
        ev = self._out.events_
        for t, i, n in zip(ev["t"], ev["id"], ev["n"]):
            i = int(i)
            if n > 0 and i in entry and t >= entry[i] and i not in out:
                out[i] = float(t)
        return out

    @property
    def residence_times_(self) -> np.ndarray:
        entry = self.entry_times_
        return np.array(sorted(t - entry[i] for i, t in self.exit_times_.items()))


class PeriodicTransitSensor:
    """Transit times across a periodic length (particle RTD of a periodic section).

    Tracks each particle's unwrapped coordinate u along ``axis`` (minimum-image displacements);
    every time direction * (u - u_ref) first reaches a new multiple of the ``length`` the
    passage time is recorded (linear interpolation). A transit time is the time between two
    successive first passages of the same particle - the time it needs to advance one period
    net, backflow included. Passages before ``t_start`` are not recorded.
    """

    def __init__(
        self,
        axis: int,
        length: float,
        *,
        direction: int = 1,
        u_ref: float = 0.0,
        t_start: float = 0.0,
    ) -> None:
        if axis not in (0, 1, 2):
            raise ValueError(f"axis must be 0, 1 or 2, got {axis}")
        if length <= 0:
            raise ValueError(f"length must be > 0, got {length}")
        if direction not in (1, -1):
            raise ValueError(f"direction must be +1 or -1, got {direction}")
        self.axis, self.length, self.direction = axis, length, direction
        self.u_ref, self.t_start = u_ref, t_start
        L = np.zeros(3)
        L[axis] = length
        self._tr = _Tracker(L)
        # tracked particles: ids (sorted), unwrapped coordinate and the period index reached
        self._ids = np.zeros(0, np.int64)
        self._u = np.zeros(0)
        self._best = np.zeros(0, np.int64)
        self._last_pass: dict[int, float] = {}
        self.passages_: list[tuple[int, float]] = []
        self.transits_: list[float] = []

    def __setstate__(self, state: dict) -> None:
        """Unpickle, converting the per-particle dictionaries of earlier versions to arrays (a
        run checkpointed by them resumes)."""
        if isinstance(state.get("_u"), dict):
            ids = np.array(sorted(state["_u"]), np.int64)
            state["_ids"] = ids
            state["_best"] = np.array([state["_best"][int(i)] for i in ids], np.int64)
            state["_u"] = np.array([state["_u"][int(i)] for i in ids], float)
        self.__dict__.update(state)

    def _levels(self, u: np.ndarray) -> np.ndarray:
        """Period index reached at unwrapped coordinates u: ``floor(direction (u - u_ref) / L)``."""
        return np.floor(self.direction * (u - self.u_ref) / self.length).astype(np.int64)

    def _track(self, ids: np.ndarray, x: np.ndarray) -> None:
        """Start tracking the particles ``ids`` (not tracked yet) at coordinates x."""
        if not len(ids):
            return
        ids_all = np.concatenate([self._ids, ids])
        u_all = np.concatenate([self._u, x])
        best_all = np.concatenate([self._best, self._levels(x)])
        order = np.argsort(ids_all, kind="stable")
        self._ids, self._u, self._best = ids_all[order], u_all[order], best_all[order]

    def _record_passages(
        self, pid: int, u0: float, u1: float, best: int, lvl: int, t_prev: float, t: float
    ) -> None:
        """Passages (and transits) of particle ``pid`` moving from u0 to u1 between t_prev and t,
        from period index ``best`` up to ``lvl`` (times linearly interpolated)."""
        while lvl > best:
            best += 1
            target = self.u_ref + self.direction * best * self.length
            frac = (target - u0) / (u1 - u0) if u1 != u0 else 1.0
            tp = t_prev + min(max(frac, 0.0), 1.0) * (t - t_prev)
            if tp >= self.t_start:
                self.passages_.append((pid, tp))
                if pid in self._last_pass:
                    self.transits_.append(tp - self._last_pass[pid])
                self._last_pass[pid] = tp

    def update(self, state: Any) -> None:
        s = state_view(state)
        m = self._tr.step(s)
        ax = self.axis
        ids = np.asarray(s.ids, np.int64)
        rows, tracked = _match_ids(self._ids, ids)
        if m is not None:
            cur, a, b, t_prev = m
            ok = tracked[cur]
            cur, k = cur[ok], rows[cur[ok]]
            xa, xb = a[ok, ax], b[ok, ax]
            u0 = self._u[k]
            u1 = u0 + (xb - xa)
            self._u[k] = u1
            lvl = self._levels(u1)
            best = self._best[k]
            for q in np.nonzero(lvl > best)[0]:  # a few particles per update: in index order
                self._record_passages(
                    int(ids[cur[q]]), u0[q], u1[q], int(best[q]), int(lvl[q]), t_prev, s.t
                )
            self._best[k] = np.maximum(best, lvl)
        self._track(ids[~tracked], np.asarray(s.pos[~tracked, ax], float))

    @property
    def transit_times_(self) -> np.ndarray:
        return np.asarray(self.transits_)


class EnergySensor:
    """Kinetic (sum m v^2 / 2), rotational (sum I w^2 / 2, I = 2/5 m r^2 for spheres, when the
    state has ``omega``) and potential (sum m g . (x_ref - x)) energy at each update (J)."""

    def __init__(self, density: float | dict, *, gravity: Any = (0.0, 0.0, -9.81)) -> None:
        self.density = density
        self.g = np.asarray(gravity, float).reshape(3)
        self.t_: list[float] = []
        self.kinetic_: list[float] = []
        self.rotational_: list[float] = []
        self.potential_: list[float] = []

    def update(self, state: Any) -> None:
        s = state_view(state)
        m = particle_masses(s.radii, s.types, self.density)
        self.t_.append(s.t)
        self.kinetic_.append(float(0.5 * np.sum(m * np.einsum("ij,ij->i", s.vel, s.vel))))
        if s.omega is not None and len(np.asarray(s.omega)) == len(m):
            w = np.asarray(s.omega, float)
            inertia = 0.4 * m * s.radii**2
            self.rotational_.append(float(0.5 * np.sum(inertia * np.einsum("ij,ij->i", w, w))))
        else:
            self.rotational_.append(0.0)
        self.potential_.append(float(-np.sum(m * (s.pos @ self.g))))
