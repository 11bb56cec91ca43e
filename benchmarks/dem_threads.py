"""Benchmark: the thread count chosen at run time (``twin dem run --threads auto``) against one
and two fixed threads, on an idle machine and beside busy processes.

The 6,000-sphere settled bed of ``dem_throughput.py`` (same law as the LIGGGHTS comparison),
run with one thread (serial scatter), two threads (two-pass) and the adaptive policy
(``twin_core.dem.threads``), alternating the three ``--repeat`` times, first alone and then with
``--hogs`` busy processes started beside it. Rates are particle-steps per wall second; the
machine's load is printed with each phase. Numba compile time is reported apart.

Run: ``python benchmarks/dem_threads.py [--steps 3000] [--repeat 3] [--hogs 1]``
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dem_throughput import make_sim  # noqa: E402
from machine import describe  # noqa: E402

HOG = "while True: pass\n"


def rate(sim, steps: int, policy: str) -> float:
    """Particle-steps per wall second of ``steps`` steps under a thread policy."""
    if policy == "1":
        numba.set_num_threads(1)
        sim.thread_policy = "fixed"
    elif policy == "2":
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        sim.thread_policy = "fixed"
    else:
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        sim.thread_policy = "adaptive"
    t0 = time.perf_counter()
    sim.run(steps * sim.dt)
    return sim.n_particles * steps / (time.perf_counter() - t0)


def phase(label: str, sim, steps: int, repeat: int) -> dict[str, float]:
    rates: dict[str, list[float]] = {"1": [], "2": [], "auto": []}
    for _ in range(repeat):
        for policy in rates:
            rates[policy].append(rate(sim, steps, policy))
    med = {k: float(np.median(v)) for k, v in rates.items()}
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"{label} (load average {load}):")
    for k, v in rates.items():
        print(
            f"  {k:>4} thread(s): median {med[k] / 1e6:.2f} M/s  ({', '.join(f'{x / 1e6:.2f}' for x in v)})"
        )
    print(f"  auto / best fixed = {med['auto'] / max(med['1'], med['2']):.2f}")
    return med


def main() -> int:
    from twin_core.dem.threads import prefer_openmp

    prefer_openmp()  # before the first parallel region (twin_core.dem.threads)
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=6000)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--hogs", type=int, default=1)
    args = ap.parse_args()
    print(describe())
    sim = make_sim(args.n, "bed")
    t0 = time.perf_counter()
    sim.run(2000 * sim.dt)  # settle; includes the compile
    print(
        f"numba compile + 2000 settling steps: {time.perf_counter() - t0:.1f} s (not in the rates)"
    )
    phase("idle", sim, args.steps, args.repeat)
    hogs = [subprocess.Popen([sys.executable, "-c", HOG]) for _ in range(args.hogs)]
    try:
        time.sleep(2.0)
        phase(f"beside {args.hogs} busy process(es)", sim, args.steps, args.repeat)
    finally:
        for h in hogs:
            h.kill()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
