"""Benchmark: the engine under numba's threading layers (OpenMP, TBB), one and two threads.

The layer is fixed per process, so each (layer, threads) pair runs in its own process
(``NUMBA_THREADING_LAYER``), alternating the pairs ``--repeat`` times on the same state: a
``twin dem run`` checkpoint (``--state``, e.g. the seed-size blender section) or, without one,
the settled 6,000-sphere bed of ``dem_throughput.py``. Rates are particle-steps per wall second
of ``--steps`` timed steps after ``--warm`` untimed ones (compile excluded, cache warm); the
load average is printed with each. ``twin_core.dem.threads.prefer_openmp`` follows from this.

Run: ``python benchmarks/dem_threading_layers.py [--state CKPT] [--steps 3000] [--repeat 4]``
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT))


def one(state: str, steps: int, warm: int, threads: int) -> None:
    """Child: time ``steps`` steps of the state with ``threads`` threads; print one line."""
    import numba
    from dem_throughput import make_sim

    from twin_core.dem.simulation import Simulation

    numba.set_num_threads(threads)
    # as many scatter chunks as the machine's threads, whatever run saved the state
    chunks = numba.config.NUMBA_NUM_THREADS
    sim = Simulation.load_checkpoint(state, pair_chunks=chunks) if state else make_sim(6000, "bed")
    sim.thread_policy = "fixed"
    sim.run(warm * sim.dt)
    t0 = time.perf_counter()
    sim.run(steps * sim.dt)
    el = time.perf_counter() - t0
    print(f"{numba.threading_layer()} {threads} {sim.n_particles * steps / el:.6e}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--state", default="", help="checkpoint .npz (default: the settled bed)")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--warm", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=4)
    ap.add_argument("--layers", nargs="+", default=["omp", "tbb"])
    ap.add_argument("--child", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        one(args.state, args.steps, args.warm, args.child)
        return 0
    from machine import describe

    print(describe())
    rates: dict[tuple[str, int], list[float]] = {}
    for _ in range(args.repeat):
        for layer in args.layers:
            for th in (1, 2):
                env = dict(os.environ, NUMBA_THREADING_LAYER=layer)
                cmd = [sys.executable, __file__, "--state", args.state, "--steps",
                       str(args.steps), "--warm", str(args.warm), "--child", str(th)]  # fmt: skip
                out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
                if out.returncode != 0:
                    print(f"{layer} x{th}: failed: {out.stderr.strip().splitlines()[-1:]}")
                    continue
                got, _, rate = out.stdout.strip().splitlines()[-1].split()
                rates.setdefault((got, th), []).append(float(rate))
                print(f"{got:>9} x{th}: {float(rate) / 1e6:.2f} M/s  (load {os.getloadavg()[0]:.2f})",
                      flush=True)  # fmt: skip
    print("medians (M particle-steps/s) and two threads / one:")
    for layer in sorted({k[0] for k in rates}):
        m1 = np.median(rates.get((layer, 1), [np.nan]))
        m2 = np.median(rates.get((layer, 2), [np.nan]))
        print(
            f"  {layer:>9}: 1 thread {m1 / 1e6:.2f}, 2 threads {m2 / 1e6:.2f}, ratio {m2 / m1:.2f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
