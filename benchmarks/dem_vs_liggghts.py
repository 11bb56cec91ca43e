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

``--case blender``: the seed-size blender section (``twin_core/scenes/configs/blender.yaml``, or
``--scene blender_small``; 2 x 3,000 spheres, trough and rotor meshes, blades at ``--rpm``,
default the scene's fastest) with the scene's materials (steel walls as LIGGGHTS atom type 2,
the particle-wall pair coefficients), Tsuji damping, dt and skin. Our engine settles it with the
plate (``settle_s``) and turns the blades for ``--spin`` s (not timed; the checkpoint is kept in
``--state-dir``); both codes then start from that state (LIGGGHTS: ``liggghts/in.blender`` with
the particles, their velocities and spins as a data file, the meshes as ASCII STL at the current
blade angle, ``move/mesh`` with the same axis and period), run ``--warm`` untimed steps and
``--steps`` timed ones. Each run reports, besides its rate, the mean translational kinetic
energy over the timed steps (sampled every ``--thermo`` steps), the mean speed at the end and
the particles that left the section through a wall (lost, or centre beyond the trough).

    python benchmarks/dem_vs_liggghts.py [--n 6000] [--case bed|drum|blender] [--repeat 2]
        [--threads 1] [--schemes auto two_pass] [--steps 2000]
        [--scene blender] [--rpm 100] [--spin 0.2] [--warm 100] [--thermo 500]
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numba
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import dem_throughput as bench  # noqa: E402

from schemas.dem_scene import BlenderScene, load_scene  # noqa: E402
from twin_core.dem import Simulation  # noqa: E402
from twin_core.dem.stl import write_stl  # noqa: E402
from twin_core.scenes import blender, common  # noqa: E402
from twin_core.scenes.geometry import SceneGeometry  # noqa: E402
from twin_core.scenes.presets import PRESETS  # noqa: E402

LOOP = re.compile(r"Loop time of ([0-9.eE+-]+) on (\d+) procs for (\d+) steps with (\d+) atoms")


def write_data(
    path: Path,
    pos: np.ndarray,
    vel: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    radius: np.ndarray | float = bench.R,
    density: float = 1500.0,
    omega: np.ndarray | None = None,
    n_types: int = 1,
) -> None:
    """LIGGGHTS data file (atom_style granular: id type diameter density x y z; velocities
    vx vy vz wx wy wz), every atom of type 1; ``n_types`` atom types are declared (the walls
    take type 2 in the blender case)."""
    n = pos.shape[0]
    rad = np.broadcast_to(np.asarray(radius, float), (n,))
    om = np.zeros_like(vel) if omega is None else omega
    box = [f"{float(a)!r} {float(b)!r} {ax}lo {ax}hi" for a, b, ax in zip(lo, hi, "xyz")]
    lines = ["LIGGGHTS data file (dem_vs_liggghts.py)", "", f"{n} atoms",
             f"{n_types} atom types", "", *box, "", "Atoms", ""]  # fmt: skip
    for i, (p, r) in enumerate(zip(pos, rad)):
        x, y, z = (float(c) for c in p)
        lines.append(f"{i + 1} 1 {2 * float(r)!r} {float(density)!r} {x!r} {y!r} {z!r}")
    lines += ["", "Velocities", ""]
    for i, (v, w) in enumerate(zip(vel, om)):
        vals = " ".join(repr(float(c)) for c in (*v, *w))
        lines.append(f"{i + 1} {vals}")
    path.write_text("\n".join(lines) + "\n")


def run_liggghts(exe: str, n: int, case: str, settle: int, steps: int, skin: float) -> float:
    """Particle-steps/s of LIGGGHTS' timed run (its own Loop time)."""
    sim = bench.make_sim(n, case)
    lx = bench.box_length(n)
    with tempfile.TemporaryDirectory() as td:
        data = Path(td) / "bed.data"
        order = np.argsort(sim.ids)
        write_data(data, sim.pos[order], sim.vel[order], (0.0, 0.0, 0.0), (lx, 0.08, 0.08))
        cmd = [exe, "-in", str(HERE / "liggghts" / "in.bed"), "-log", str(Path(td) / "log"),
               "-var", "datafile", str(data), "-var", "drum", "1" if case == "drum" else "0",
               "-var", "rpm", "30", "-var", "skin", repr(skin), "-var", "nsettle", str(settle),
               "-var", "nrun", str(steps)]  # fmt: skip
        out = subprocess.run(cmd, capture_output=True, text=True, cwd=td, check=False,
                             env=liggghts_env())  # fmt: skip
    loops = LOOP.findall(out.stdout)
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


@dataclass
class BlenderRun:
    """One timed run of the blender case: rate and what the state looked like after it."""

    rate: float  # particle-steps/s of the timed steps
    ke_mean: float  # translational kinetic energy, mean of the samples over the timed steps (J)
    mean_speed: float  # mean particle speed at the end (m/s)
    escaped: int  # particles removed as lost or with the centre beyond a wall at the end


def blender_config(name: str = "blender") -> BlenderScene:
    """A packaged blender scene configuration (``twin_core/scenes/configs/<name>.yaml``)."""
    return load_scene(PRESETS / f"{name}.yaml")


def blender_state(cfg: BlenderScene, rpm: float, spin_s: float, cache: Path) -> Path:
    """Checkpoint of the section after the scene's settling with the plate (``settle_s``) and
    ``spin_s`` of blade rotation, run with our engine (not timed); reused when present."""
    path = cache / f"{cfg.name}_n{2 * cfg.n_per_type}_{rpm:g}rpm_{spin_s:g}s.npz"
    if not path.exists():
        cache.mkdir(parents=True, exist_ok=True)
        sim, _ = blender.build(cfg, rpm)
        t0 = time.perf_counter()
        sim.run(cfg.settle_s + spin_s, progress=True)
        print(f"state: {sim.n_particles} particles at t = {sim.t:.3f} s after "
              f"{time.perf_counter() - t0:.0f} s (not timed) -> {path}", flush=True)  # fmt: skip
        sim.save_checkpoint(path)
    return path


def check_state(sim: Any, cfg: BlenderScene, geo: SceneGeometry, rpm: float) -> None:
    """Raise ValueError unless the checkpointed ``sim`` is this scene's section at ``rpm``:
    particle count, time step, mesh triangle counts, blade speed, after the plate's removal."""
    n_static = len(geo.static)
    expected = {
        "particles": 2 * cfg.n_per_type,
        "dt": cfg.dt_fraction
        * common.rayleigh_dt(
            cfg.radius, cfg.material.density, cfg.material.shear_modulus, cfg.material.poisson
        ),
        "triangles": [len(m.triangles) for m in geo.static] + [len(geo.rotating[0][0].triangles)],
        "rpm": rpm,
    }
    got = {
        "particles": sim.n_particles + sim.removed_counts["lost"][0],
        "dt": sim.dt,
        "triangles": [len(sim.mesh_triangles(k)) for k in range(n_static + 1)],
        "rpm": sim.mesh_motion(n_static).rpm,
    }
    for key, want in expected.items():
        same = np.isclose(got[key], want, rtol=1e-9) if key == "dt" else got[key] == want
        if not same:
            raise ValueError(f"state: {key} must be {want} for {cfg.name} at {rpm:g} rpm, "
                             f"got {got[key]}")  # fmt: skip
    if sim.t < cfg.settle_s:
        raise ValueError(f"state: t must be >= settle_s = {cfg.settle_s} s, got {sim.t:.3f} s")


def outside_section(pos: np.ndarray, geo: SceneGeometry) -> np.ndarray:
    """Centres beyond the section's walls (escaped through one): below the axis farther than R
    from it, above it with |y| > R, or above the lid (``blender_section``'s trough)."""
    radius = geo.info["radius"]
    zc = geo.info["axis_point"][2]
    y, z = pos[:, 1], pos[:, 2]
    beyond = np.where(z < zc, y**2 + (z - zc) ** 2 > radius**2, np.abs(y) > radius)
    return beyond | (z > geo.info["domain_hi"][2])


def write_triangles_stl(path: Path, corners: np.ndarray, name: str) -> Path:
    """ASCII STL (LIGGGHTS' ``fix mesh/surface`` reads it) of triangles given by their corners
    (T, 3, 3)."""
    tri = np.arange(3 * len(corners)).reshape(-1, 3)
    return write_stl(path, corners.reshape(-1, 3), tri, binary=False, name=name)


def blender_liggghts_vars(
    sim: Any, geo: SceneGeometry, workdir: Path, nwarm: int, nrun: int, nthermo: int
) -> dict[str, str]:
    """Write the state of ``sim`` for ``benchmarks/liggghts/in.blender`` into ``workdir``: the
    particles (data file, ordered by id), the static meshes (``trough.stl``) and the rotating
    mesh at its current angle (``rotor.stl``); return the ``-var`` values: materials (Young's
    modulus ``E = 2 G (1 + nu)``), pair coefficients, dt, skin and the blade rotation."""
    mats = sim.materials
    if mats.damping != "tsuji" or mats.n != 2:
        raise ValueError(f"blender case needs 2 materials with damping 'tsuji', got "
                         f"{mats.n} with {mats.damping!r}")  # fmt: skip
    if len(geo.rotating) != 1:
        raise ValueError(f"blender case needs one rotating mesh, got {len(geo.rotating)}")
    order = np.argsort(sim.ids)
    lo, hi = sim.domain
    data = workdir / "blender.data"
    write_data(data, sim.pos[order], sim.vel[order], lo, hi, radius=sim.radius[order],
               density=mats.materials[0].density, omega=sim.omega[order], n_types=2)  # fmt: skip
    n_static = len(geo.static)
    trough = np.concatenate([sim.mesh_triangles(k) for k in range(n_static)])
    rotor = sim.mesh_triangles(n_static)
    motion = sim.mesh_motion(n_static)
    axis = np.asarray(motion.axis_dir, float) * np.sign(motion.rpm)
    axis /= np.linalg.norm(axis)
    (mu_pp, mur_pp, e_pp), (mu_pw, mur_pw, e_pw) = mats.pair(0, 0), mats.pair(0, 1)
    values = {
        "datafile": data,
        "trough": write_triangles_stl(workdir / "trough.stl", trough, "trough"),
        "rotor": write_triangles_stl(workdir / "rotor.stl", rotor, "rotor"),
        "ym1": mats.materials[0].young_modulus, "ym2": mats.materials[1].young_modulus,
        "pr1": mats.materials[0].poisson, "pr2": mats.materials[1].poisson,
        "e_pp": e_pp, "e_pw": e_pw, "mu_pp": mu_pp, "mu_pw": mu_pw,
        "mur_pp": mur_pp, "mur_pw": mur_pw, "dt": sim.dt, "skin": sim.skin,
        "ox": motion.axis_point[0], "oy": motion.axis_point[1], "oz": motion.axis_point[2],
        "ax": axis[0], "ay": axis[1], "az": axis[2], "period": 60.0 / abs(motion.rpm),
        "nwarm": nwarm, "nrun": nrun, "nthermo": nthermo, "dumpfile": workdir / "final.dump",
    }  # fmt: skip
    return {k: str(v) if isinstance(v, (Path, int)) else repr(float(v)) for k, v in values.items()}


def liggghts_env() -> dict[str, str]:
    """Environment of a single-process LIGGGHTS run (Open MPI as root, no busy polling)."""
    return dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
                OMPI_MCA_mpi_yield_when_idle="1")  # fmt: skip


def read_last_dump(path: Path) -> dict[str, np.ndarray]:
    """Columns of the last snapshot of a LAMMPS/LIGGGHTS ``dump custom`` file."""
    text = path.read_text().split("ITEM: TIMESTEP")[-1].splitlines()
    k = next(i for i, line in enumerate(text) if line.startswith("ITEM: ATOMS"))
    names = text[k].split()[2:]
    rows = np.array([line.split() for line in text[k + 1 :] if line.strip()], float)
    rows = rows.reshape(-1, len(names))
    return {nm: rows[:, j] for j, nm in enumerate(names)}


def run_liggghts_blender(
    exe: str, state: Path, geo: SceneGeometry, nwarm: int, steps: int, nthermo: int
) -> BlenderRun:
    """LIGGGHTS on the saved blender state: the rate of its timed run (its own Loop time), the
    mean of its thermo ``ke`` over that run, and the escaped particles at the end."""
    sim = Simulation.load_checkpoint(state)
    n0 = sim.n_particles
    with tempfile.TemporaryDirectory() as td:
        values = blender_liggghts_vars(sim, geo, Path(td), nwarm, steps, nthermo)
        cmd = [exe, "-in", str(HERE / "liggghts" / "in.blender"), "-log", str(Path(td) / "log")]
        for k, v in values.items():
            cmd += ["-var", k, v]
        out = subprocess.run(cmd, capture_output=True, text=True, cwd=td, check=False,
                             env=liggghts_env())  # fmt: skip
        loops = LOOP.findall(out.stdout)
        if len(loops) < 3:
            raise RuntimeError(f"liggghts failed:\n{out.stdout[-3000:]}\n{out.stderr[-2000:]}")
        final = read_last_dump(Path(td) / "final.dump")
    for warning in sorted({line for line in out.stdout.splitlines() if "WARNING" in line}):
        print(f"  LIGGGHTS: {warning.strip()}", flush=True)
    t, _, k, na = loops[1]
    pos = np.c_[final["x"], final["y"], final["z"]]
    speed = np.linalg.norm(np.c_[final["vx"], final["vy"], final["vz"]], axis=1)
    return BlenderRun(
        rate=int(na) * int(k) / float(t),
        ke_mean=thermo_ke_mean(out.stdout, nwarm, nwarm + steps),
        mean_speed=float(speed.mean()),
        escaped=n0 - len(pos) + int(outside_section(pos, geo).sum()),
    )


def thermo_ke_mean(stdout: str, step_lo: int, step_hi: int) -> float:
    """Mean of the ``ke`` thermo column (``thermo_style custom step atoms ke``) over the
    samples with ``step_lo < step <= step_hi``."""
    rows = re.findall(r"^\s*(\d+)\s+(\d+)\s+([0-9.eE+-]+)\s*$", stdout, flags=re.M)
    ke = [float(e) for s, _, e in rows if step_lo < int(s) <= step_hi]
    return float(np.mean(ke)) if ke else float("nan")


def translational_ke(sim: Any) -> float:
    """Translational kinetic energy sum(m v^2) / 2 (J), LIGGGHTS' thermo ``ke``."""
    return float(0.5 * np.sum(sim.mass * np.sum(sim.vel**2, axis=1)))


def run_ours_blender(
    state: Path, geo: SceneGeometry, nwarm: int, steps: int, nthermo: int, threads: int,
    scheme: str,
) -> BlenderRun:  # fmt: skip
    """Our engine on the saved blender state, ``nwarm`` untimed steps then ``steps`` timed
    (wall time, translational KE sampled every ``nthermo`` steps as LIGGGHTS' thermo)."""
    numba.set_num_threads(threads)
    # as many scatter chunks as the machine's threads, whatever run saved the state
    sim = Simulation.load_checkpoint(state, pair_chunks=numba.config.NUMBA_NUM_THREADS)
    sim.pair_scheme = scheme
    sim.thread_policy = "fixed"
    n0 = sim.n_particles
    lost0 = sim.removed_counts["lost"][0]
    sim.run(nwarm * sim.dt)
    ke: list[float] = []
    t0 = time.perf_counter()
    sim.run(steps * sim.dt, callback=lambda s: ke.append(translational_ke(s)),
            callback_every_s=nthermo * sim.dt)  # fmt: skip
    el = time.perf_counter() - t0
    lost = sim.removed_counts["lost"][0] - lost0
    return BlenderRun(
        rate=n0 * steps / el,
        ke_mean=float(np.mean(ke)),
        mean_speed=float(np.linalg.norm(sim.vel, axis=1).mean()),
        escaped=lost + int(outside_section(sim.pos, geo).sum()),
    )


def blender_main(args: argparse.Namespace) -> int:
    """The blender case: state, then alternating timed runs, then medians and the check that
    both codes did the same physics (mean KE, mean speed, escaped particles)."""
    cfg = blender_config(args.scene)
    rpm = args.rpm if args.rpm is not None else max(cfg.rpms)
    geo = blender.build_geometry(cfg, rpm)
    if args.state is not None:
        state = Path(args.state)
    else:
        state = blender_state(cfg, rpm, args.spin, Path(args.state_dir))
    sim = Simulation.load_checkpoint(state)
    check_state(sim, cfg, geo, rpm)
    print(f"blender {cfg.name}: N = {sim.n_particles}, {rpm:g} rpm, t0 = {sim.t:.3f} s, "
          f"dt = {sim.dt:.4e} s, skin = {sim.skin:.2e} m; {args.warm} untimed + "
          f"{args.steps} timed steps", flush=True)  # fmt: skip
    runs = [(th, sc) for th in args.threads for sc in args.schemes]
    res: dict[str, list[BlenderRun]] = {
        "liggghts": [],
        **{f"ours {th}t {sc}": [] for th, sc in runs},
    }
    for rep in range(args.repeat):
        lg = run_liggghts_blender(args.liggghts, state, geo, args.warm, args.steps, args.thermo)
        res["liggghts"].append(lg)
        print(f"[{rep}] LIGGGHTS 1 process: {describe(lg)}", flush=True)
        for th, sc in runs:
            o = run_ours_blender(state, geo, args.warm, args.steps, args.thermo, th, sc)
            res[f"ours {th}t {sc}"].append(o)
            print(f"[{rep}] ours {th} thread(s) {sc}: {describe(o)} "
                  f"(ratio to this LIGGGHTS run {o.rate / lg.rate:.2f})", flush=True)  # fmt: skip
    print(f"\nN={sim.n_particles} case=blender rpm={rpm:g} steps={args.steps} "
          f"(medians of {args.repeat})")  # fmt: skip
    lg_rate = float(np.median([r.rate for r in res["liggghts"]]))
    for name, rs in res.items():
        rate = float(np.median([r.rate for r in rs]))
        ke = float(np.median([r.ke_mean for r in rs]))
        print(f"{name}: {rate / 1e6:.3f} M particle-steps/s, ratio to LIGGGHTS "
              f"{rate / lg_rate:.2f}; mean KE {ke:.4g} J, escaped {[r.escaped for r in rs]}")  # fmt: skip
    return 0


def describe(r: BlenderRun) -> str:
    """One line of a blender run's numbers."""
    return (f"{r.rate / 1e6:.3f} M particle-steps/s, mean KE {r.ke_mean:.4g} J, mean speed "
            f"{r.mean_speed:.4g} m/s, escaped {r.escaped}")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    from twin_core.dem.threads import prefer_openmp

    prefer_openmp()  # before the first parallel region (twin_core.dem.threads)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=6000)
    ap.add_argument("--case", default="bed", choices=["bed", "drum", "blender"])
    ap.add_argument("--settle", type=int, default=3000)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--threads", type=int, nargs="+", default=[1])
    ap.add_argument("--schemes", nargs="+", default=["auto"],
                    choices=["auto", "scatter", "two_pass"])  # fmt: skip
    ap.add_argument("--liggghts", default=shutil.which("liggghts") or "liggghts")
    ap.add_argument("--scene", default="blender", help="blender case: packaged scene config")
    ap.add_argument("--rpm", type=float, default=None, help="blender case: blade speed "
                    "(default: the scene's fastest)")  # fmt: skip
    ap.add_argument(
        "--spin",
        type=float,
        default=0.2,
        help="blender case: s of blade rotation after settling, before the state",
    )
    ap.add_argument("--warm", type=int, default=100, help="blender case: untimed steps")
    ap.add_argument("--thermo", type=int, default=500, help="blender case: KE sample interval")
    ap.add_argument(
        "--state-dir",
        default=str(Path(tempfile.gettempdir()) / "dem_vs_liggghts"),
        help="blender case: where the settled state is kept between invocations",
    )
    ap.add_argument(
        "--state",
        default=None,
        help="blender case: start from this checkpoint of the scene's run at --rpm (e.g. a "
        "'twin dem run' checkpoint.npz) instead of settling one",
    )
    args = ap.parse_args(argv)
    if shutil.which(args.liggghts) is None:
        print("liggghts not found (apt-get install -y liggghts)")
        return 1
    if args.case == "blender":
        return blender_main(args)
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
