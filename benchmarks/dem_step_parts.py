"""Where a DEM step's time goes, part by part, on one thread (docs/dem_engine.md, "The contact
law vectorised").

On a saved state (``--state``: a run directory or checkpoint of ``twin dem run``, e.g. the seed
blender section at t = 20.5 s) or, without one, a settled 6,000-sphere drum (the case of
``dem_throughput.py``), it times each part in a loop of its own, on the same lists:

- the pair scatter's parts: finding the contacts, copying their inputs into the blocks, the
  contact law over the blocks, the springs written back and the forces added; and the whole
  scatter (``pair_scatter``: the parts plus what they cost together);
- the mesh contacts (``mesh_pass``), the force pass (``gather_pass``: the sums and the half
  kick) and the first half kick with the drift (``kick_drift``: with the largest displacement
  and wall excursion), all with dt = 0 so that repeated calls leave the state;
- one neighbour rebuild, and a plain run for the step time and the rebuild interval.

Reports the numba compile time apart (first calls). Usage::

    python benchmarks/dem_step_parts.py [--state RUN_DIR] [--repeat 300] [--steps 3000]
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numba
import numpy as np
from numba import njit

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from machine import describe  # noqa: E402


def _timed(f: Callable[[], object], repeat: int) -> float:
    """Mean microseconds of ``f()`` over ``repeat`` calls after one untimed call."""
    f()
    t0 = time.perf_counter()
    for _ in range(repeat):
        f()
    return (time.perf_counter() - t0) / repeat * 1e6


def _load(state: str | None):
    from twin_core.dem import Simulation

    if state:
        path = Path(state)
        sim = Simulation.load_checkpoint(
            path / "checkpoint.npz" if path.is_dir() else path, pair_chunks=1
        )
    else:
        from dem_throughput import DT, make_sim

        sim = make_sim(6000, "drum")
        sim.run(2000 * DT, progress=False)
        sim.pair_chunks = 1
    sim.thread_policy = "fixed"
    return sim


def _part_kernels():
    """njit loops that run one part of the pair scatter over all contacts of one chunk."""
    from twin_core.dem import pairs as pa
    from twin_core.dem.space import FMA

    @njit(fastmath=FMA)
    def find(n, P, nbf, pstart, hist, live, dom, per, clist):
        return pa.find_contacts(0, n, P, nbf, pstart, hist, live, dom, per, clist)

    @njit(fastmath=FMA)
    def blocks(m, stage, P, IA, hist, pt, dom, per, clist, w, a, dt):
        for q0 in range(0, m, pa.BLOCK):
            nq = min(pa.BLOCK, m - q0)
            if stage & 1:
                pa._load_block(clist, q0, nq, P, IA, hist, pt, dom, per, w)
            if stage & 2:
                pa.contact_block(nq, w, dt)
            if stage & 4:
                pa._store_springs(clist, q0, nq, hist, w)
                pa._scatter_block(clist, q0, nq, w, a)

    return find, blocks


def main(argv: list[str] | None = None) -> int:
    from twin_core.dem.threads import prefer_openmp

    prefer_openmp()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--state", default=None, help="run directory or checkpoint (default: drum)")
    ap.add_argument("--repeat", type=int, default=300)
    ap.add_argument("--steps", type=int, default=3000)
    args = ap.parse_args(argv)
    if args.state and not (
        Path(args.state).is_file() or (Path(args.state) / "checkpoint.npz").is_file()
    ):
        ap.error(f"--state: no checkpoint at {args.state}")
    print(describe())
    numba.set_num_threads(1)
    t0 = time.perf_counter()
    sim = _load(args.state)
    sim.run(100 * sim.dt, progress=False)
    from twin_core.dem.integrator import gather_pass, kick_drift
    from twin_core.dem.mesh_contacts import flatten_triangles, mesh_pass
    from twin_core.dem.pairs import flatten_pairs, pair_scatter

    find, blocks = _part_kernels()
    s, c, n = sim, sim._cur[0], sim._n
    nb, nown, hist = s._nb[c], s._nown[c], s._hist[c].copy()
    forces = s._F.copy()  # the state's forces, restored before the run below
    sums = np.zeros_like(s._F)  # a target for the blocks' forces
    flatten_pairs(n, nb, nown, hist, s._pstart, s._nbf, s._live)
    nbf, pstart = s._nbf, s._pstart
    m = find(n, s._P, nbf, pstart, hist, s._live, s._dom, s._per, s._clist)
    blocks(m, 7, s._P, s._IA, hist, s._pt, s._dom, s._per, s._clist, s._work[0], sums, s.dt)
    print(f"load and compile (first calls): {time.perf_counter() - t0:.1f} s")
    print(f"particles {n}, listed pairs {int(nown[:n].sum())}, in contact {m}, "
          f"candidate triangles {int(s._ntri[c][:n].sum())}")  # fmt: skip
    bl = (s._P, s._IA, hist, s._pt, s._dom, s._per, s._clist, s._work[0], sums, s.dt)
    t = {
        "find the contacts": _timed(
            lambda: find(n, s._P, nbf, pstart, hist, s._live, s._dom, s._per, s._clist),
            args.repeat,
        ),
        "copy inputs into the blocks": _timed(lambda: blocks(m, 1, *bl), args.repeat),
        "contact law (SIMD)": _timed(lambda: blocks(m, 2, *bl), args.repeat),
        "springs back, forces added": _timed(lambda: blocks(m, 4, *bl), args.repeat),
    }
    t["pair scatter (whole)"] = _timed(
        lambda: pair_scatter(
            n,
            s._P,
            s._IA,
            nbf,
            pstart,
            nown,
            hist,
            s._live,
            s._clist,
            s._work,
            s._F,
            s._acc,
            s._bounds,
            s._pt,
            s._dom,
            s._per,
            s.dt,
        ),  # fmt: skip
        args.repeat,
    )
    # the mesh contacts and the force pass with dt = 0 (their half kick then leaves the state)
    flatten_triangles(n, s._ntri[c], s._tri_nb[c], s._thist[c], s._mcnt, s._mint)
    mesh_args = (n, s._P, s._IA, s._thist[c], s._tri_x, s._tri_mesh, s._mesh_par, s._pt,
                 s._dom, s._per, 0.0, s.t, s._mint, s._mflt, s._mcnt, s._mwork)  # fmt: skip
    t["mesh contacts (batched)"] = _timed(lambda: mesh_pass(*mesh_args), args.repeat)
    gather_args = (n, s._P, s._F, s._IA, nown, s._pf, s._nrev, s._rev_o, s._rev_k, True,
                   s._acc, s._bounds, s._planes, s._cyls, s._whist, s._mint, s._mflt, s._mcnt,
                   s._pt, s._dom, s._per, s._grav, 0.0, s.t)  # fmt: skip
    t["force pass (sums, half kick)"] = _timed(lambda: gather_pass(*gather_args), args.repeat)
    drift_args = (n, s._P, s._F, s._XB, s._dom, s._per, 0.0)
    t["first half kick, drift, skin and wall check"] = _timed(
        lambda: kick_drift(*drift_args), args.repeat
    )
    for k, us in t.items():
        per = f", {us / m * 1e3:.1f} ns per contact" if k in (
            "copy inputs into the blocks", "contact law (SIMD)", "springs back, forces added"
        ) else ""  # fmt: skip
        print(f"  {k}: {us:.0f} us{per}")
    s._F[:] = forces
    r0, w0 = sim.n_rebuilds, sim.wall_time_s
    sim.run(args.steps * sim.dt, progress=False)
    step = (sim.wall_time_s - w0) / args.steps * 1e6
    nreb = sim.n_rebuilds - r0
    t_rb = _timed(sim._rebuild, 20)
    print(f"run of {args.steps} steps: {step:.0f} us per step ({n / step:.2f} M particle-steps/s), "
          f"a rebuild every {args.steps / max(nreb, 1):.0f} steps, {t_rb:.0f} us each "
          f"({t_rb * nreb / args.steps:.0f} us per step)")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
