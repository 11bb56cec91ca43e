"""DEM engine throughput: particle-steps per second on a settled bed and an agitated (drum) bed.

Case (the seed's blender parameters, docs/dem_engine.md): spheres R = 1 mm, 1500 kg/m3, G = 2e6 Pa,
nu = 0.25, mu_s = 0.5, mu_r = 0.01, e = 0.1 with Tsuji's (uncorrected) restitution mapping, as
LIGGGHTS' ``hertz`` model, dt = 20 % Rayleigh (1.8757e-5 s); box periodic in x,
80 x 80 mm cross-section; 40 mm long for 6,000 spheres and stretched along x in proportion for
larger N (50,000 spheres do not fit in 40 x 80 x 80 mm: that is a solid fraction of 0.82).

- ``bed``: planes y = 0, 80 mm and z = 0, 80 mm; the spheres start on a loose lattice near the floor,
  settle, then the settled bed is timed.
- ``drum``: a cylinder of radius 40 mm around the x axis rotating at 30 rpm (contacts keep
  changing), timed after one settling phase.

Reports the numba compile time (first call, cold cache only if the cache is empty) apart from the
run time, with 1 and 2 threads. Usage::

    python benchmarks/dem_throughput.py [--n 6000 50000] [--steps 2000] [--threads 1 2]
"""

from __future__ import annotations

import argparse
import math
import time

import numba
import numpy as np

from twin_core.dem import Material, MaterialTable, Simulation

R = 1e-3
MAT = Material(1500.0, 2e6, 0.25, friction=0.5, rolling_friction=0.01, restitution=0.1)
DT = 1.8757e-5


def box_length(n: int) -> float:
    """Periodic length along x: 40 mm for 6,000 spheres, in proportion above."""
    return 0.04 * max(1.0, n / 6000.0)


def lattice(n: int, lx: float, case: str, spacing: float = 2.05e-3) -> np.ndarray:
    """Loose simple-cubic start positions, lowest layers first (inside the drum for ``drum``)."""
    xs = np.arange(0.5 * spacing, lx - 0.5 * spacing + 1e-12, spacing)
    ys = np.arange(1.2e-3, 0.08 - 1.1e-3, spacing)
    zs = np.arange(1.2e-3, 0.08 - 1.1e-3, spacing)
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    p = np.c_[X.ravel(), Y.ravel(), Z.ravel()]
    if case == "drum":
        rr = np.hypot(p[:, 1] - 0.04, p[:, 2] - 0.04)
        p = p[rr < 0.04 - 1.2e-3]
    p = p[np.lexsort((p[:, 1], p[:, 0], p[:, 2]))]
    if p.shape[0] < n:
        raise ValueError(f"n: only {p.shape[0]} lattice sites, got {n}")
    return p[:n]


def make_sim(
    n: int, case: str, skin: float | None = None, seed: int = 0, damping: str = "tsuji"
) -> Simulation:
    """The benchmark system (not yet settled). ``damping="tsuji"`` (default): the uncorrected
    restitution-to-dashpot mapping of LIGGGHTS' ``hertz`` model, so that the two codes run the
    same contact law; ``"corrected"``: the engine's default (docs/dem_engine.md)."""
    lx = box_length(n)
    sim = Simulation(
        (0, 0, 0), (lx, 0.08, 0.08), periodic=(True, False, False),
        materials=MaterialTable([MAT], damping=damping), dt=DT, skin=skin,
    )  # fmt: skip
    if case == "bed":
        sim.add_box((0, 0, 0), (lx, 0.08, 0.08))
    else:
        sim.add_cylinder((0, 0.04, 0.04), (1, 0, 0), 0.04, rpm=30.0)
    rng = np.random.default_rng(seed)
    pos = lattice(n, lx, case)
    sim.add_particles(pos, R, type_id=(pos[:, 0] > lx / 2).astype(int),
                      vel=rng.normal(0.0, 0.02, pos.shape))  # fmt: skip
    return sim


def measure(sim: Simulation, steps: int) -> float:
    """Particle-steps per second over ``steps`` steps."""
    t0 = time.perf_counter()
    sim.run(steps * sim.dt)
    el = time.perf_counter() - t0
    return sim.n_particles * steps / el


def main(argv: list[str] | None = None) -> int:
    from twin_core.dem.threads import prefer_openmp

    prefer_openmp()  # before the first parallel region (twin_core.dem.threads)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, nargs="+", default=[6000, 50000])
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--settle", type=int, default=4000, help="settling steps before timing")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--cases", nargs="+", default=["bed", "drum"])
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    warm = make_sim(200, "bed")
    warm.run(5 * DT)
    print(f"compile/first call (cache-dependent): {time.perf_counter() - t0:.2f} s")
    for n in args.n:
        for case in args.cases:
            numba.set_num_threads(max(args.threads))
            sim = make_sim(n, case)
            t0 = time.perf_counter()
            sim.run(args.settle * DT)
            ke = sim.kinetic_energy()
            print(f"N={n} {case}: settled {args.settle} steps in {time.perf_counter() - t0:.1f} s, "
                  f"KE {ke:.3g} J, rebuilds {sim.n_rebuilds}")  # fmt: skip
            for th in args.threads:
                numba.set_num_threads(th)
                r0 = sim.n_rebuilds
                rate = measure(sim, args.steps)
                every = args.steps / max(sim.n_rebuilds - r0, 1)
                print(f"  threads={th}: {rate / 1e6:.3f} M particle-steps/s "
                      f"(rebuild every {every:.0f} steps)")  # fmt: skip
    _ = math
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
