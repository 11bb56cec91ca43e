"""Compiling the engine's numba kernels ahead of the first step (``twin dem warmup``).

The kernels are compiled with ``cache=True``: the first process after an install (or after a
kernel's source changed) compiles them into numba's cache, later ones load them (about 0.5 s).
Without a warm cache that compilation happens silently inside the first calls, while a run's
progress bar stands at 0 %. :func:`compile_kernels` runs a tiny scene that calls every kernel a
DEM run calls (mesh motion, insertion, neighbour lists, the step loop with planes, cylinders,
static and rotating meshes, an outlet and a factory, the elastic energy and the grid sensor),
phase by phase, telling ``report`` what it compiles before each phase and how long it took.
Numba compiles one specialisation per argument-type signature, and the tiny scene passes the
same types as any scene, so what it compiles is what a real run uses.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from types import ModuleType

import numpy as np
from numba.core.dispatcher import Dispatcher

from . import (
    contact,
    energy,
    insertion,
    integrator,
    mesh_contacts,
    meshes,
    pairs,
    partition,
    sensors,
    walls,
)
from .insertion import BoxRegion, ParticleFactory
from .materials import Material
from .motion import RotationMotion
from .simulation import Simulation

__all__ = ["compile_kernels", "kernel_cache_counts"]

_KERNEL_MODULES: tuple[ModuleType, ...] = (
    contact, meshes, partition, pairs, walls, mesh_contacts, integrator, energy, insertion,
    sensors,
)  # fmt: skip


def kernel_cache_counts() -> tuple[int, int]:
    """(loaded from cache, compiled) specialisations of the engine's kernels in this process."""
    hits = misses = 0
    for module in _KERNEL_MODULES:
        for obj in vars(module).values():
            if isinstance(obj, Dispatcher):
                hits += sum(obj.stats.cache_hits.values())
                misses += sum(obj.stats.cache_misses.values())
    return hits, misses


def _tiny_scene() -> Simulation:
    """10 x 10 x 10 mm box, periodic in x, two materials, a floor plane, a drum cylinder."""
    powder = Material(1500.0, 2e6, 0.25, friction=0.5, rolling_friction=0.01, restitution=0.5)
    steel = Material(7800.0, 7e10, 0.3)
    sim = Simulation((0, 0, 0), (0.01, 0.01, 0.01), periodic=(True, False, False),
                     materials=[powder, steel])  # fmt: skip
    sim.add_plane((0, 0, 0), (0, 0, 1), material_id=1, active=(-math.inf, math.inf))
    sim.add_cylinder((0, 0.005, 0.005), (1, 0, 0), 0.005, material_id=1, rpm=10.0)
    return sim


def _add_meshes(sim: Simulation) -> None:
    """A static ramp and a rotating paddle (Rodrigues update of the triangles)."""
    v = np.array([[0, 0, 0.001], [0.01, 0, 0.001], [0.01, 0.01, 0.002], [0, 0.01, 0.002]])
    sim.add_mesh(v, np.array([[0, 1, 2], [0, 2, 3]]), material_id=1)
    paddle = np.array([[0.004, 0.005, 0.004], [0.006, 0.005, 0.004], [0.006, 0.005, 0.007]])
    sim.add_mesh(paddle, np.array([[0, 1, 2]]), material_id=1,
                 motion=RotationMotion((0, 0.005, 0.005), (1, 0, 0), rpm=60.0))  # fmt: skip


def _insert(sim: Simulation) -> None:
    sim.insert_particles(20, BoxRegion((0, 0.002, 0.004), (0.01, 0.008, 0.009)), 4e-4, seed=1)
    sim.add_factory(ParticleFactory(BoxRegion((0, 0.002, 0.008), (0.01, 0.008, 0.0095)), 4,
                                    rate=2000.0, radius=(3e-4, 4e-4), seed=2))  # fmt: skip
    sim.add_outlet((0, 0, 0), (0.01, 0.001, 0.001))


def _steps(sim: Simulation) -> None:
    sim.run(0.002)


def _energy(sim: Simulation) -> None:
    sim.potential_energy()


def _sensor(sim: Simulation) -> None:
    edges = [np.linspace(0, 0.01, 3)] * 3
    grid = sensors.GridFieldSensor(*edges, 1500.0, periodic=(True, False, False))
    for _ in range(2):
        grid.update(sim)
        sim.run(2 * sim.dt)


_PHASES: tuple[tuple[str, Callable[[Simulation], None]], ...] = (
    ("mesh motion (update_mesh)", _add_meshes),
    ("insertion and neighbour lists (rsa_place, rebuild)", _insert),
    ("force pass and step loop (compute_forces, advance: pairs, walls, meshes)", _steps),
    ("elastic energy (elastic_energy)", _energy),
    ("grid field sensor (voxel traversal)", _sensor),
)


def compile_kernels(report: Callable[[str], object] | None = None) -> dict[str, float]:
    """Compile (or load from numba's cache) every kernel of a DEM run on a tiny scene.

    ``report(message)`` is called before each phase with what it compiles and after it with the
    time taken and whether it compiled or loaded from the cache. Returns the wall seconds per
    phase (phase name -> s).
    """
    say = report or (lambda message: None)
    sim = _tiny_scene()
    times: dict[str, float] = {}
    for k, (name, phase) in enumerate(_PHASES, 1):
        say(f"DEM kernels {k}/{len(_PHASES)}: {name} ...")
        hits0, misses0 = kernel_cache_counts()
        t0 = time.perf_counter()
        phase(sim)
        times[name] = time.perf_counter() - t0
        hits, misses = kernel_cache_counts()
        how = f"compiled {misses - misses0}" if misses > misses0 else "loaded from cache"
        say(f"DEM kernels {k}/{len(_PHASES)}: {times[name]:.1f} s ({how}, "
            f"{hits - hits0} cache loads)")  # fmt: skip
    return times
