"""Speed of the mixing indices: 6,000 particles over 200 frames (issue target: seconds).

Synthetic frames (a random dense bed that is progressively shuffled) stand in for DEM output;
the cost of the indices does not depend on where the positions come from. Numba compile time
of the exact Siiria kernel is measured apart (first call on a tiny input).
"""

from __future__ import annotations

import os
import time

import numpy as np

from twin_core.dem.frames import Frame
from twin_core.mixing import GridSpec, MixingConfig, compute_indices
from twin_core.mixing.distance_indices import siiria_index


def frames(n=6000, n_frames=200, seed=0):
    rng = np.random.default_rng(seed)
    box = np.array([0.04, 0.08, 0.04])
    # jittered simple-cubic bed with spacing ~ one diameter so that contacts exist
    side = np.ceil((n / (box / box.min()).prod()) ** (1 / 3)).astype(int)
    g = np.stack(np.meshgrid(*[np.arange(side * k) for k in (1, 2, 1)], indexing="ij"), -1)
    pos0 = (g.reshape(-1, 3)[:n] + 0.5) * 2.0e-3
    types = (pos0[:, 1] < np.median(pos0[:, 1])).astype(int)
    ids = np.arange(n)
    radii = np.full(n, 1.0e-3)
    out, pos = [], pos0.copy()
    for k in range(n_frames):
        out.append(Frame(0.1 * k, ids, types, radii, pos.copy(), np.zeros_like(pos)))
        sel = rng.choice(n, n // 50, replace=False)
        pos[sel] = pos[rng.permutation(sel)]
    return out, box


def main() -> None:
    fr, box = frames()
    grid = GridSpec((0, 0, 0), tuple(box * [1, 1, 1.0]), (1, 8, 8))
    t0 = time.perf_counter()
    siiria_index(np.zeros((3, 3)), np.ones((3, 3)), 0.87, 1.0)
    compile_s = time.perf_counter() - t0
    print(f"machine: {os.cpu_count()} cores; N = {len(fr[0].ids)}, frames = {len(fr)}")
    print(f"numba compile (Siiria kernel, first call): {compile_s:.2f} s")
    cheap = [n for n in ("LI RSD VRR VBBC ESI ME DM MSI AH NDM NNM PS CN SI").split()]
    for label, names, cfg in [
        ("all but SM", cheap, MixingConfig(grid=grid, box=(0.04, np.inf, np.inf))),
        ("all, SM sampled (20k pairs)", "all",
         MixingConfig(grid=grid, box=(0.04, np.inf, np.inf), sm_pairs=20_000)),
        ("all, SM exact (O(N^2))", "all", MixingConfig(grid=grid, box=(0.04, np.inf, np.inf))),
    ]:  # fmt: skip
        t0 = time.perf_counter()
        df = compute_indices(fr, names, cfg)
        dt = time.perf_counter() - t0
        print(
            f"{label:32s} {dt:7.2f} s  ({dt / len(fr) * 1e3:6.1f} ms/frame, {df.shape[1] - 1} columns)"
        )


if __name__ == "__main__":
    main()
