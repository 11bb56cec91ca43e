"""Wall time of the seed-size DEM scenes on this machine, extrapolated to the seed's runs.

For each seed-size config (twin_core/scenes/configs/{blender,drawdown,feeder}.yaml) the scene
is built (particles on the fill lattice) and advanced for a short simulated time; the rate in
particle-steps per second is extrapolated to the seed's simulated duration and compared with
the seed's EDEM wall times (drawdown 3.5 h on 6 cores, feeder 17 h on 8 cores, periodic section
8 h on 4 cores; seed 3.2.2, 3.2.3, 4.2).

Caveats printed with the numbers: the measured window starts from the loose fill lattice (few
contacts while the particles fall), so the rate is optimistic for a packed bed; particle
numbers stay constant here while in the real runs they fall as the powder discharges.

Usage: python benchmarks/dem_scenes_timing.py [--steps N] [--threads 1,2] [--scenes blender,drawdown,feeder]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numba

from schemas.dem_scene import load_scene

CONFIGS = Path(__file__).resolve().parents[1] / "twin_core" / "scenes" / "configs"
SEED = {  # simulated seconds, EDEM wall hours, EDEM cores
    "blender": (20.5, 8.0, 4),
    "drawdown": (11.0, 3.5, 6),
    "feeder": (21.0, 17.0, 8),
}


def build(name: str):
    from twin_core.scenes import blender, drawdown, feeder

    cfg = load_scene(CONFIGS / f"{name}.yaml")
    if name == "blender":
        sim, _ = blender.build(cfg, cfg.rpms[-1])
    elif name == "drawdown":
        sim, _ = drawdown.build(cfg)
    else:
        sim, _ = feeder.build(cfg)
    return cfg, sim


def main() -> None:
    from twin_core.dem.threads import prefer_openmp

    prefer_openmp()  # before the first parallel region (twin_core.dem.threads)
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--scenes", default="blender,drawdown,feeder")
    ap.add_argument(
        "--settle", type=float, default=0.0, help="simulated seconds run (untimed) before measuring"
    )
    a = ap.parse_args()
    threads = [int(t) for t in a.threads.split(",")]
    print(f"numba threads available: {numba.config.NUMBA_NUM_THREADS}")
    for name in a.scenes.split(","):
        t0 = time.perf_counter()
        cfg, sim = build(name)
        t_build = time.perf_counter() - t0
        t0 = time.perf_counter()
        sim.run(5 * sim.dt)  # compile (cached after the first call) + first neighbour lists
        t_first = time.perf_counter() - t0
        if a.settle > 0:
            t0 = time.perf_counter()
            sim.run(a.settle)
            print(f"{name}: settled {a.settle:g} s simulated in {time.perf_counter() - t0:.1f} s")
        n = sim.n_particles
        dur, hours, cores = SEED[name]
        print(
            f"\n{name}: N = {n}, dt = {sim.dt:.3e} s, build {t_build:.1f} s, "
            f"first steps (compile/lists) {t_first:.1f} s"
        )
        for th in threads:
            numba.set_num_threads(min(th, numba.config.NUMBA_NUM_THREADS))
            s0 = sim.step
            t0 = time.perf_counter()
            sim.run(a.steps * sim.dt)
            el = time.perf_counter() - t0
            steps = sim.step - s0
            rate = n * steps / el
            total_steps = dur / sim.dt
            est_h = total_steps * n / rate / 3600
            print(
                f"  threads {th}: {steps} steps in {el:.2f} s -> {rate / 1e6:.2f} M particle-steps/s; "
                f"{dur:g} s simulated ~ {total_steps:.3g} steps ~ {est_h:.1f} h "
                f"(seed EDEM: {hours:g} h on {cores} cores; ratio {est_h / hours:.2f})"
            )


if __name__ == "__main__":
    main()
