"""Side-by-side throughput of our DEM engine and LIGGGHTS (single process) on the same case.

Both run the same contact law (Hertz-Mindlin, Tsuji damping from the same restitution:
``make_sim`` gives our side ``damping="tsuji"``, not the engine's corrected default) and start
from the same loose lattice (``benchmarks/dem_throughput.py``), settle for the same
number of steps (not timed), then run ``--steps`` timed steps: LIGGGHTS' own "Loop time" of its
second ``run`` against our wall time of the same number of steps, one numba thread (and
optionally two), with each pair scheme asked for (``Simulation.pair_scheme``: ``auto`` picks the
serial scatter on one thread; ``two_pass`` is the parallel buffer-and-gather scheme). Runs
alternate (LIGGGHTS, ours, LIGGGHTS, ours...) so that the load of the shared machine hits both
alike. Needs the ``liggghts`` executable (Debian package ``liggghts``).

    python benchmarks/dem_vs_liggghts.py [--n 6000] [--case bed|drum] [--repeat 2]
        [--threads 1] [--schemes auto two_pass]
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import dem_throughput as bench  # noqa: E402


def write_data(path: Path, pos: np.ndarray, vel: np.ndarray, lx: float) -> None:
    """LIGGGHTS data file (atom_style granular: id type diameter density x y z)."""
    n = pos.shape[0]
    lines = ["LIGGGHTS data file (dem_vs_liggghts.py)", "", f"{n} atoms", "1 atom types", "",
             f"0 {float(lx)!r} xlo xhi", "0 0.08 ylo yhi", "0 0.08 zlo zhi", "", "Atoms", ""]  # fmt: skip
    for i, p in enumerate(pos):
        x, y, z = (float(c) for c in p)
        lines.append(f"{i + 1} 1 {2 * bench.R!r} 1500.0 {x!r} {y!r} {z!r}")
    lines += ["", "Velocities", ""]
    for i, v in enumerate(vel):
        vx, vy, vz = (float(c) for c in v)
        lines.append(f"{i + 1} {vx!r} {vy!r} {vz!r} 0 0 0")
    path.write_text("\n".join(lines) + "\n")


def run_liggghts(exe: str, n: int, case: str, settle: int, steps: int, skin: float) -> float:
    """Particle-steps/s of LIGGGHTS' timed run (its own Loop time)."""
    sim = bench.make_sim(n, case)
    lx = bench.box_length(n)
    with tempfile.TemporaryDirectory() as td:
        data = Path(td) / "bed.data"
        write_data(data, sim.pos[np.argsort(sim.ids)], sim.vel[np.argsort(sim.ids)], lx)
        cmd = [exe, "-in", str(HERE / "liggghts" / "in.bed"), "-log", str(Path(td) / "log"),
               "-var", "datafile", str(data), "-var", "drum", "1" if case == "drum" else "0",
               "-var", "rpm", "30", "-var", "skin", repr(skin), "-var", "nsettle", str(settle),
               "-var", "nrun", str(steps)]  # fmt: skip
        env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
                   OMPI_MCA_mpi_yield_when_idle="1")  # fmt: skip
        out = subprocess.run(cmd, capture_output=True, text=True, cwd=td, check=False, env=env)
    loops = re.findall(r"Loop time of ([0-9.eE+-]+) on (\d+) procs for (\d+) steps with (\d+) atoms",
                       out.stdout)  # fmt: skip
    if len(loops) < 2:
        raise RuntimeError(f"liggghts failed:\n{out.stdout[-3000:]}\n{out.stderr[-2000:]}")
    t, _, k, na = loops[-1]
    return int(na) * int(k) / float(t)


def run_ours(
    n: int, case: str, settle: int, steps: int, threads: int, scheme: str = "auto"
) -> float:
    """Particle-steps/s of our engine on the same case."""
    numba.set_num_threads(threads)
    sim = bench.make_sim(n, case)
    sim.pair_scheme = scheme
    sim.run(settle * bench.DT)
    return bench.measure(sim, steps)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=6000)
    ap.add_argument("--case", default="bed", choices=["bed", "drum"])
    ap.add_argument("--settle", type=int, default=3000)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--threads", type=int, nargs="+", default=[1])
    ap.add_argument("--schemes", nargs="+", default=["auto"],
                    choices=["auto", "scatter", "two_pass"])  # fmt: skip
    ap.add_argument("--liggghts", default=shutil.which("liggghts") or "liggghts")
    args = ap.parse_args(argv)
    if shutil.which(args.liggghts) is None:
        print("liggghts not found (apt-get install -y liggghts)")
        return 1
    skin = 0.5 * bench.R  # our default skin, used for both
    t0 = time.perf_counter()
    bench.make_sim(200, "bed").run(5 * bench.DT)
    print(f"numba compile/first call: {time.perf_counter() - t0:.2f} s (not in the rates)")
    res: dict[str, list[float]] = {"liggghts": []}
    runs = [(th, sc) for th in args.threads for sc in args.schemes]
    for th, sc in runs:
        res[f"ours {th}t {sc}"] = []
    for rep in range(args.repeat):
        r = run_liggghts(args.liggghts, args.n, args.case, args.settle, args.steps, skin)
        res["liggghts"].append(r)
        print(f"[{rep}] LIGGGHTS 1 process : {r / 1e6:.3f} M particle-steps/s", flush=True)
        for th, sc in runs:
            o = run_ours(args.n, args.case, args.settle, args.steps, th, sc)
            res[f"ours {th}t {sc}"].append(o)
            print(f"[{rep}] ours {th} thread(s) {sc}: {o / 1e6:.3f} M particle-steps/s "
                  f"(ratio to this LIGGGHTS run {o / r:.2f})", flush=True)  # fmt: skip
    lg = float(np.median(res["liggghts"]))
    print(f"\nN={args.n} case={args.case} steps={args.steps} (medians of {args.repeat})")
    print(f"LIGGGHTS 1 process: {lg / 1e6:.3f} M particle-steps/s")
    for th, sc in runs:
        o = float(np.median(res[f"ours {th}t {sc}"]))
        print(f"ours {th} thread(s) {sc}: {o / 1e6:.3f} M particle-steps/s, ratio ours/LIGGGHTS = "
              f"{o / lg:.2f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
