"""Shared machinery of the DEM scenes: particle placement, engine set-up, segmented runs with
checkpoints, sensors and frames, resume.

A scene run is a sequence of simulated-time segments of ``checkpoint_interval_s``; after each
segment the engine checkpoint and the pickled scene state (sensors, flags) are written to the
run directory, so ``resume=True`` continues an interrupted run where it stopped (the frames
file is truncated to the checkpoint time and continued).
"""

from __future__ import annotations

import json
import logging
import pickle
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from twin_core.dem.frames import FrameWriter
from twin_core.scenes.geometry import SceneGeometry, TriMesh

log = logging.getLogger(__name__)

__all__ = [
    "RunState",
    "lattice_positions",
    "make_simulation",
    "mesh_clearance",
    "rayleigh_dt",
    "run_segments",
    "surface_samples",
]


def rayleigh_dt(radius: float, density: float, shear_modulus: float, poisson: float) -> float:
    """Rayleigh time T_R = pi R sqrt(rho / G) / (0.1631 nu + 0.8766) (seed Eq. 9 as corrected
    in the reading notes)."""
    return float(np.pi * radius * np.sqrt(density / shear_modulus) / (0.1631 * poisson + 0.8766))


def surface_samples(meshes: list[TriMesh], spacing: float) -> np.ndarray:
    """Points on the mesh surfaces no farther apart than about ``spacing`` (barycentric grids)."""
    pts = []
    for m in meshes:
        for tri in m.corners():
            # origin at the vertex opposite the longest edge: the two edges from it span the
            # triangle with about area / spacing^2 grid points even when it is long and thin
            edges = [np.linalg.norm(tri[(k + 2) % 3] - tri[(k + 1) % 3]) for k in range(3)]
            o = int(np.argmax(edges))
            a, b, c = tri[o], tri[(o + 1) % 3], tri[(o + 2) % 3]
            k1 = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
            k2 = max(1, int(np.ceil(np.linalg.norm(c - a) / spacing)))
            i, j = np.meshgrid(np.arange(k1 + 1), np.arange(k2 + 1), indexing="ij")
            u = i / k1
            v = j / k2
            sel = u + v <= 1 + 1e-12
            pts.append(a + u[sel][:, None] * (b - a) + v[sel][:, None] * (c - a))
    return np.vstack(pts) if pts else np.zeros((0, 3))


def mesh_clearance(points: np.ndarray, meshes: list[TriMesh], spacing: float) -> np.ndarray:
    """Approximate distance of each point to the nearest mesh surface (lower bound:
    nearest surface sample minus the sample spacing)."""
    s = surface_samples(meshes, spacing)
    if len(s) == 0:
        return np.full(len(points), np.inf)
    d, _ = cKDTree(s).query(points)
    return d - spacing


def lattice_positions(
    n: int,
    lo: Any,
    hi: Any,
    radius: float,
    inside: Callable[[np.ndarray], np.ndarray],
    rng: np.random.Generator,
    *,
    spacing_factor: float = 1.08,
    avoid: list[TriMesh] | None = None,
    jitter: float = 0.02,
    order: str = "bottom",
) -> np.ndarray:
    """``n`` non-overlapping sphere centres on a jittered cubic lattice (spacing
    ``2 radius spacing_factor``) inside the box [lo, hi], accepted by the predicate ``inside``
    (centre positions -> bool) and at least ``1.05 radius`` from the ``avoid`` meshes; the lowest
    (``order="bottom"``) lattice sites are used first. Solid fraction pi / (6 f^3) (0.42 at
    f = 1.08), loose enough to settle quickly.

    Raises ValueError if fewer than ``n`` sites are available.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    a = 2 * radius * spacing_factor
    lo = np.asarray(lo, float) + radius
    hi = np.asarray(hi, float) - radius
    axes = [np.arange(lo[k], hi[k] + 1e-12, a) for k in range(3)]
    if any(len(x) == 0 for x in axes):
        return np.zeros((0, 3)) if n == 0 else _too_few(n, 0)
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    g = g[inside(g)]
    if avoid:
        g = g[mesh_clearance(g, avoid, radius / 2) > 1.05 * radius]
    if len(g) < n:
        _too_few(n, len(g))
    key = g[:, 2] + 1e-6 * rng.random(len(g)) if order == "bottom" else rng.random(len(g))
    g = g[np.argsort(key, kind="stable")[:n]]
    amp = jitter * radius
    return g + rng.uniform(-amp, amp, g.shape)


def _too_few(n: int, have: int) -> np.ndarray:
    raise ValueError(
        f"n_particles={n} does not fit the fill region ({have} lattice sites); lower the "
        "particle count or enlarge the region"
    )


def make_simulation(
    cfg: Any, geo: SceneGeometry, *, periodic=(False, False, False), pad: float = 0.0
):
    """Engine ``Simulation`` with the scene's material, domain and meshes.

    Particle material 0 (the config's particle properties, pp_* coefficients), wall material 1
    (steel elastic constants, or the particle's with ``walls_of_particle_material``; pw_*
    coefficients for the particle-wall pair). Static meshes are
    added without motion, rotating meshes with a ``RotationMotion``, removable ones active
    until their removal time.
    """
    from twin_core.dem.materials import Material, MaterialTable
    from twin_core.dem.motion import RotationMotion
    from twin_core.dem.simulation import Simulation

    m = cfg.material
    particle = Material(
        density=m.density,
        shear_modulus=m.shear_modulus,
        poisson=m.poisson,
        friction=m.pp_friction,
        rolling_friction=m.pp_rolling_friction,
        restitution=m.pp_restitution,
        name="particle",
    )
    wall_solid = (
        (m.density, m.shear_modulus, m.poisson)
        if m.walls_of_particle_material
        else (m.wall_density, m.wall_shear_modulus, m.wall_poisson)
    )
    wall = Material(
        *wall_solid,
        friction=m.pw_friction,
        rolling_friction=m.pw_rolling_friction,
        restitution=m.pw_restitution,
        name="wall",
    )
    table = MaterialTable([particle, wall], damping=m.damping)
    table.set_pair(0, 1, m.pw_friction, m.pw_rolling_friction, m.pw_restitution)
    pad_v = pad * np.array([not p for p in periodic], float)
    lo = np.asarray(geo.info["domain_lo"], float) - pad_v
    hi = np.asarray(geo.info["domain_hi"], float) + pad_v
    dt = cfg.dt_fraction * rayleigh_dt(cfg.radius, m.density, m.shear_modulus, m.poisson)
    sim = Simulation(lo, hi, periodic=tuple(periodic), materials=table, dt=dt, seed=cfg.seed)
    pid, wid = 0, 1
    t_motion = float(geo.info.get("motion_start_s", 0.0))
    for mesh in geo.static:
        sim.add_mesh(mesh.vertices, mesh.triangles, wid)
    for mesh, pt, axis, rpm in geo.rotating:
        motion = RotationMotion(
            tuple(map(float, pt)), tuple(map(float, axis)), float(rpm), t_start=t_motion
        )
        sim.add_mesh(mesh.vertices, mesh.triangles, wid, motion=motion)
    for mesh, t_off in geo.removable:
        sim.add_mesh(mesh.vertices, mesh.triangles, wid, active=(-np.inf, float(t_off)))
    return sim, pid, wid


@dataclass
class RunState:
    """Pickled alongside each checkpoint: sensors and scene flags."""

    sensors: dict[str, Any] = field(default_factory=dict)
    flags: dict[str, Any] = field(default_factory=dict)
    wall_s: float = 0.0
    steps: int = 0
    next_frame_t: float = 0.0


def open_frames(run_dir: Path, cfg: Any, sim: Any, *, resume: bool, **meta: Any) -> FrameWriter:
    """The scene's frame file ``run_dir/frames`` at the configured precision; on resume it
    continues from the checkpoint time ``sim.t``. ``meta`` is stored in the manifest."""
    return FrameWriter(
        Path(run_dir) / "frames",
        precision=cfg.output.frame_precision,
        meta=meta,
        resume=resume,
        resume_t=sim.t,
    )


def run_segments(
    sim: Any,
    t_end: float,
    run_dir: Path,
    state: RunState,
    *,
    sensor_interval_s: float,
    on_sample: Callable[[Any, RunState], None],
    frames: FrameWriter | None = None,
    frame_interval_s: float | None = None,
    checkpoint_interval_s: float = 1.0,
    progress: bool = True,
    label: str = "dem",
) -> RunState:
    """Advance ``sim`` to ``t_end`` in checkpointed segments, calling ``on_sample(sim, state)``
    every ``sensor_interval_s`` and storing frames every ``frame_interval_s``."""
    from tqdm import tqdm

    run_dir.mkdir(parents=True, exist_ok=True)
    bar = tqdm(
        total=round(t_end, 6),
        initial=round(sim.t, 6),
        unit="s(sim)",
        disable=not progress,
        desc=label,
    )

    def cb(s: Any) -> None:
        on_sample(s, state)
        if frames is not None and frame_interval_s:
            if s.t >= state.next_frame_t - 0.5 * sensor_interval_s:
                frames.append(s)
                while state.next_frame_t <= s.t + 0.5 * sensor_interval_s:
                    state.next_frame_t += frame_interval_s

    if sim.t < 1e-12 and not state.flags.get("sampled0"):
        cb(sim)
        state.flags["sampled0"] = True
    # runs advance in whole steps (rounded): stop once less than half a step remains, or a
    # segment shorter than half a step would run no step and loop here forever
    while t_end - sim.t >= 0.5 * sim.dt:
        seg = max(min(checkpoint_interval_s, t_end - sim.t), sim.dt)
        t0 = time.perf_counter()
        steps0 = sim.step
        sim.run(seg, callback=cb, callback_every_s=sensor_interval_s)
        state.wall_s += time.perf_counter() - t0
        state.steps += sim.step - steps0
        if frames is not None:
            frames.flush()
        save_checkpoint(sim, state, run_dir)
        bar.update(round(seg, 6))
    bar.close()
    return state


def save_checkpoint(sim: Any, state: RunState, run_dir: Path) -> None:
    """The engine's checkpoint and the run's state, each written to a temporary file and
    renamed (the state's rename right after the checkpoint's), so that a run killed while
    writing resumes from the previous pair."""
    tmp = run_dir / "state.pkl.tmp"
    with tmp.open("wb") as fh:
        pickle.dump(state, fh)
    sim.save_checkpoint(run_dir / "checkpoint.npz")
    tmp.replace(run_dir / "state.pkl")


def load_checkpoint(run_dir: Path, pair_chunks: int | None = None) -> tuple[Any, RunState] | None:
    """(Simulation, RunState) of an interrupted run, or None if there is no checkpoint.
    ``pair_chunks``: None keeps the saved run's chunks of the pair scatter (the resumed run is
    bit-identical to an uninterrupted one); a number re-chunks it (``Simulation.load_checkpoint``),
    e.g. to use two threads on a run started with one."""
    from twin_core.dem.simulation import Simulation

    ck = run_dir / "checkpoint.npz"
    st = run_dir / "state.pkl"
    if not (ck.exists() and st.exists()):
        return None
    sim = Simulation.load_checkpoint(ck, pair_chunks=pair_chunks)
    with st.open("rb") as fh:
        state = pickle.load(fh)
    return sim, state


def write_json(path: Path, data: dict) -> Path:
    path.write_text(json.dumps(_jsonable(data), indent=1))
    return path


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.floating | float):
        v = float(x)
        return v if np.isfinite(v) else None
    return x
