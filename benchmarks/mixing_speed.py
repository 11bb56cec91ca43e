"""Speed of the mixing indices on one thread: a 17,850-particle polydisperse bed (issue target:
every index but the exact O(N^2) Siiria index in under 50 ms per frame).

The bed (``mixing_beds``): 10 radius classes of a log-normal distribution (median 1 mm), packed
in a vertical cylinder of radius 35 mm, the lower half by height the tracer; frames are
progressively shuffled (2 % of each size class exchange positions per frame), sampled on
cylindrical bins 8 x 4 x 8. The cost of the indices does not depend on where the positions
come from.

Each measurement runs in a fresh process on one thread (``NUMBA_NUM_THREADS=1``,
``OPENBLAS_NUM_THREADS=1``) with an empty numba cache, so the first call on a tiny bed measures
the compile time (later runs load it from the cache). ``--before REF`` measures the code of the
git revision ``REF`` (its ``twin_core`` exported to a temporary directory) on the same bed in
the same run, beside the working tree's. Reported per frame: the median wall time and the CPU
time of the process (the CPU time is what one core spends; the wall time also holds what other
jobs on a shared machine took from it, see the load average printed with the results).

Run: ``python benchmarks/mixing_speed.py --before main`` (a few minutes; ``--frames`` and
``--exact-frames`` set the run length).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ONE_THREAD = {"NUMBA_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
os.environ.update(ONE_THREAD)

import numpy as np  # noqa: E402
from machine import describe  # noqa: E402
from mixing_beds import CylinderBed, lognormal_radii, packed_cylinder, shuffled_frames  # noqa: E402

N_PARTICLES = 17_850
GRID_SHAPE = (8, 4, 8)
ALL_BUT_SM = "LI RSD VRR VBBC ESI ME DM MSI AH NDM NNM PS CN SI SSI".split()


def make_bed(path: Path, seed: int = 0) -> CylinderBed:
    """The packed polydisperse bed, saved to ``path`` for the measuring processes."""
    rng = np.random.default_rng(seed)
    bed = packed_cylinder(lognormal_radii(N_PARTICLES, rng), rng)
    np.savez(path, positions=bed.positions, radii=bed.radii, radius=bed.radius, height=bed.height)
    return bed


def load_bed(path: Path) -> CylinderBed:
    d = np.load(path)
    return CylinderBed(d["positions"], d["radii"], float(d["radius"]), float(d["height"]))


def timed_rows(compute, frames) -> tuple[np.ndarray, np.ndarray]:
    """Wall and CPU seconds ``compute`` spends on each frame: the frames are handed over by a
    generator that notes the clocks each time the next frame is taken."""
    marks = []

    def feed():
        for f in frames:
            marks.append((time.perf_counter(), time.process_time()))
            yield f

    compute(feed())
    marks.append((time.perf_counter(), time.process_time()))
    m = np.asarray(marks)
    return np.diff(m[:, 0]), np.diff(m[:, 1])


def measure(bed_path: Path, n_frames: int, exact_frames: int) -> dict:
    """All timings of the ``twin_core`` this process imports (one thread)."""
    from twin_core.mixing import CylindricalGrid, MixingConfig, compute_indices

    bed = load_bed(bed_path)
    rng = np.random.default_rng(1)
    types = (bed.positions[:, 2] > np.median(bed.positions[:, 2])).astype(np.int64)
    frames = shuffled_frames(bed, types, n_frames, rng)
    grid = CylindricalGrid((0.0, 0.0), bed.radius, 0.0, bed.height, GRID_SHAPE)

    def config(**kw):
        return MixingConfig(grid=grid, **kw)

    tiny = _small_bed(bed, 400)
    tiny_types = (tiny.positions[:, 2] > np.median(tiny.positions[:, 2])).astype(np.int64)
    small = shuffled_frames(tiny, tiny_types, 2, rng)
    t0 = time.perf_counter()
    compute_indices(small, "all", config())
    compute_indices(small, "all", config(sm_pairs=1000))
    compile_s = time.perf_counter() - t0

    out: dict = {"compile_s": compile_s}
    wall, cpu = timed_rows(lambda fr: compute_indices(fr, ALL_BUT_SM, config()), frames)
    out["all_but_sm"] = _summary(wall, cpu)
    wall, cpu = timed_rows(
        lambda fr: compute_indices(fr, ALL_BUT_SM, config(weight="volume")), frames
    )
    out["all_but_sm_volume"] = _summary(wall, cpu)
    out["per_index"] = {}
    for name in ALL_BUT_SM:
        wall, cpu = timed_rows(lambda fr, name=name: compute_indices(fr, [name], config()), frames)
        out["per_index"][name] = _summary(wall, cpu)
    wall, cpu = timed_rows(lambda fr: compute_indices(fr, ["SM"], config(sm_pairs=20_000)), frames)
    out["sm_sampled"] = _summary(wall, cpu)
    wall, cpu = timed_rows(
        lambda fr: compute_indices(fr, ["SM"], config()), frames[: max(exact_frames, 1)]
    )
    out["sm_exact"] = _summary(wall, cpu)
    return out


def _small_bed(bed: CylinderBed, n: int) -> CylinderBed:
    """The ``n`` lowest particles of the bed: a tiny input that runs every kernel once."""
    keep = np.argsort(bed.positions[:, 2])[:n]
    return CylinderBed(bed.positions[keep], bed.radii[keep], bed.radius, bed.height)


def _summary(wall: np.ndarray, cpu: np.ndarray) -> dict:
    return {
        "wall_median_ms": float(np.median(wall) * 1e3),
        "wall_mean_ms": float(np.mean(wall) * 1e3),
        "cpu_median_ms": float(np.median(cpu) * 1e3),
        "frames": len(wall),
    }


def run_measure(bed_path: Path, args, source: Path | None) -> dict:
    """:func:`measure` in a fresh one-thread process with an empty numba cache; ``source``: a
    directory holding the ``twin_core`` to measure instead of the installed one."""
    env = {**os.environ, **ONE_THREAD}
    with tempfile.TemporaryDirectory() as cache:
        env["NUMBA_CACHE_DIR"] = cache
        if source is not None:
            env["PYTHONPATH"] = os.pathsep.join([str(source), env.get("PYTHONPATH", "")])
        cmd = [sys.executable, __file__, "--measure", str(bed_path), "--frames", str(args.frames),
               "--exact-frames", str(args.exact_frames)]  # fmt: skip
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"measurement failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def export_revision(ref: str, dest: Path) -> str:
    """``twin_core`` of the git revision ``ref`` into ``dest``; returns its short hash."""
    root = Path(__file__).resolve().parent.parent
    rev = subprocess.run(["git", "rev-parse", "--short", ref], cwd=root, capture_output=True,
                         text=True, check=True).stdout.strip()  # fmt: skip
    archive = subprocess.run(["git", "archive", rev, "twin_core"], cwd=root, capture_output=True,
                             check=True).stdout  # fmt: skip
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return rev


def report(results: dict[str, dict]) -> None:
    """Side-by-side table of the measurements (``label -> measure()`` output)."""
    labels = list(results)
    head = f"{'':44s}" + "".join(f"{lab:>26s}" for lab in labels)
    print(head)

    def line(text, get):
        print(f"{text:44s}" + "".join(f"{get(results[lab]):>26s}" for lab in labels))

    def cell(s):
        return f"{s['wall_median_ms']:8.1f} wall {s['cpu_median_ms']:7.1f} cpu"

    line("numba compile, first call, empty cache (s)", lambda r: f"{r['compile_s']:.1f}")
    line("all but SM, ms/frame (median)", lambda r: cell(r["all_but_sm"]))
    line("all but SM, volume weighting", lambda r: cell(r["all_but_sm_volume"]))
    for name in ALL_BUT_SM:
        line(f"  {name} alone", lambda r, name=name: cell(r["per_index"][name]))
    line("SM sampled (20,000 pairs) alone", lambda r: cell(r["sm_sampled"]))
    line("SM exact (O(N^2)) alone", lambda r: cell(r["sm_exact"]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--exact-frames", type=int, default=3, help="frames for the exact Siiria")
    ap.add_argument("--before", metavar="REF", help="also measure this git revision")
    ap.add_argument("--measure", metavar="BED", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.measure:
        print(json.dumps(measure(Path(args.measure), args.frames, args.exact_frames)))
        return
    print(describe())
    print("load average (1, 5, 15 min) at start: {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))
    with tempfile.TemporaryDirectory() as tmp:
        bed_path = Path(tmp) / "bed.npz"
        bed = make_bed(bed_path)
        radii = np.unique(bed.radii)
        print(
            f"bed: {len(bed.radii)} particles, {len(radii)} radii {radii[0] * 1e3:.2f}-"
            f"{radii[-1] * 1e3:.2f} mm (log-normal), cylinder radius {bed.radius * 1e3:.0f} mm, "
            f"height {bed.height * 1e3:.1f} mm; {args.frames} frames; cylindrical bins "
            f"{'x'.join(map(str, GRID_SHAPE))}; one thread"
        )
        results = {}
        if args.before:
            src = Path(tmp) / "before"
            src.mkdir()
            rev = export_revision(args.before, src)
            results[f"before ({rev})"] = run_measure(bed_path, args, src)
        results["after (working tree)"] = run_measure(bed_path, args, None)
    print("load average (1, 5, 15 min) at end:   {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))
    report(results)


if __name__ == "__main__":
    main()
