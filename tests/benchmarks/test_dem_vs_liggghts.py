"""The LIGGGHTS input of ``benchmarks/dem_vs_liggghts.py --case blender`` says what our state is.

Checked without LIGGGHTS: the data file holds our particles (ids, radii, positions, velocities,
spins) in our domain; the STL files round-trip (``twin_core.dem.stl.read_stl``) to the triangles
our meshes have now (the rotor at its current angle, so both codes turn the blades from the same
phase); the material variables are the engine's (``E = 2 G (1 + nu)``, the scene's pair
coefficients, dt, skin, blade period ``60 / rpm``); every variable ``in.blender`` uses is given.
The escape count and the readers of LIGGGHTS' output are checked on constructed inputs.
"""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from twin_core.dem.stl import read_stl
from twin_core.scenes import blender

ROOT = Path(__file__).resolve().parents[2]
BENCH = ROOT / "benchmarks" / "dem_vs_liggghts.py"


@pytest.fixture(scope="module")
def bench():
    """The benchmark script as a module (it imports its sibling ``dem_throughput``)."""
    if not BENCH.exists():
        pytest.skip(f"{BENCH.name} not in this checkout")
    sys.path.insert(0, str(BENCH.parent))
    spec = importlib.util.spec_from_file_location("dem_vs_liggghts", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass resolves annotations through sys.modules
    spec.loader.exec_module(module)
    return module


def _section(lines: list[str], title: str, n: int) -> np.ndarray:
    k = lines.index(title) + 2
    return np.array([line.split() for line in lines[k : k + n]], float)


def test_blender_inputs_hold_our_particles_meshes_and_materials(bench, tmp_path):
    cfg = bench.blender_config("blender_small")
    rpm = 100.0
    sim, geo = blender.build(cfg, rpm)
    values = bench.blender_liggghts_vars(sim, geo, tmp_path, nwarm=10, nrun=20, nthermo=5)

    lines = Path(values["datafile"]).read_text().splitlines()
    n = sim.n_particles
    assert f"{n} atoms" in lines and "2 atom types" in lines
    lo, hi = sim.domain
    for k, ax in enumerate("xyz"):
        row = next(line for line in lines if line.endswith(f"{ax}lo {ax}hi")).split()
        assert [float(row[0]), float(row[1])] == [lo[k], hi[k]]
    order = np.argsort(sim.ids)
    atoms = _section(lines, "Atoms", n)
    np.testing.assert_array_equal(atoms[:, 0], np.arange(1, n + 1))
    np.testing.assert_array_equal(atoms[:, 1], 1.0)  # particle material; walls are type 2
    np.testing.assert_array_equal(atoms[:, 2], 2 * sim.radius[order])
    np.testing.assert_array_equal(atoms[:, 3], cfg.material.density)
    np.testing.assert_array_equal(atoms[:, 4:7], sim.pos[order])
    vel = _section(lines, "Velocities", n)
    np.testing.assert_array_equal(vel[:, 1:4], sim.vel[order])
    np.testing.assert_array_equal(vel[:, 4:7], sim.omega[order])

    for name, mesh_id in (("trough", 0), ("rotor", 1)):
        v, t = read_stl(values[name])
        ours = sim.mesh_triangles(mesh_id)
        assert len(t) == len(ours) > 0
        np.testing.assert_allclose(v[t], ours, rtol=0, atol=1e-10)

    m = cfg.material
    # Rayleigh time pi R sqrt(rho / G) / (0.1631 nu + 0.8766) (seed Eq. 9 corrected)
    rayleigh = (
        np.pi * cfg.radius * np.sqrt(m.density / m.shear_modulus) / (0.1631 * m.poisson + 0.8766)
    )
    expected = {
        "ym1": 2 * m.shear_modulus * (1 + m.poisson),
        "ym2": 2 * m.wall_shear_modulus * (1 + m.wall_poisson),
        "pr1": m.poisson, "pr2": m.wall_poisson,
        "e_pp": m.pp_restitution, "e_pw": m.pw_restitution,
        "mu_pp": m.pp_friction, "mu_pw": m.pw_friction,
        "mur_pp": m.pp_rolling_friction, "mur_pw": m.pw_rolling_friction,
        "dt": cfg.dt_fraction * rayleigh, "skin": 0.5 * cfg.radius,
        "ox": 0.0, "oy": 0.0, "oz": cfg.geometry.width / 2,
        "ax": 1.0, "ay": 0.0, "az": 0.0, "period": 60.0 / rpm,
    }  # fmt: skip
    got = {k: float(values[k]) for k in expected}
    assert got == pytest.approx(expected, rel=1e-12, abs=1e-15)
    used = set(re.findall(r"\$\{(\w+)\}", (BENCH.parent / "liggghts" / "in.blender").read_text()))
    assert used == set(values)


def test_state_of_another_speed_or_before_the_plate_removal_is_refused(bench):
    cfg = bench.blender_config("blender_small")
    sim, geo = blender.build(cfg, 100.0)
    with pytest.raises(ValueError, match="rpm must be 50"):
        bench.check_state(sim, cfg, blender.build_geometry(cfg, 50.0), 50.0)
    with pytest.raises(ValueError, match="t must be >= settle_s"):
        bench.check_state(sim, cfg, geo, 100.0)


def test_outside_section_counts_centres_beyond_the_trough(bench):
    geo = blender.build_geometry(bench.blender_config("blender_small"), 100.0)
    radius, zc = geo.info["radius"], geo.info["axis_point"][2]
    height = geo.info["domain_hi"][2]
    eps = 1e-6
    c45 = np.sqrt(0.5)
    pos = np.array([
        [0.01, 0.0, zc],  # on the axis
        [0.01, 0.0, zc - radius + eps],  # just above the trough bottom
        [0.01, 0.0, zc - radius - eps],  # through the bottom
        [0.01, c45 * (radius + eps), zc - c45 * (radius + eps)],  # through the curved wall
        [0.01, radius - eps, zc + 0.01],  # beside the vertical wall
        [0.01, -radius - eps, zc + 0.01],  # through the vertical wall
        [0.01, 0.0, height + eps],  # through the lid
    ])  # fmt: skip
    np.testing.assert_array_equal(
        bench.outside_section(pos, geo), [False, False, True, True, False, True, True]
    )


def test_last_dump_snapshot_and_thermo_mean_are_read(bench, tmp_path):
    def snapshot(step: int, rows: list[str]) -> str:
        return (f"ITEM: TIMESTEP\n{step}\nITEM: NUMBER OF ATOMS\n{len(rows)}\n"
                "ITEM: BOX BOUNDS pp ff ff\n0 1\n0 1\n0 1\nITEM: ATOMS id x vx\n"
                + "\n".join(rows) + "\n")  # fmt: skip

    dump = tmp_path / "final.dump"
    dump.write_text(snapshot(0, ["1 0.5 9", "2 0.6 9", "3 0.7 9"]) + snapshot(40, ["1 0.1 2"]))
    last = bench.read_last_dump(dump)
    assert set(last) == {"id", "x", "vx"}
    np.testing.assert_array_equal(last["x"], [0.1])
    thermo = "Step Atoms KinEng\n 0 3 9.0\n 10 3 1.0\n 20 3 2.0e-1\n 30 2 3.0\n"
    assert bench.thermo_ke_mean(thermo, 0, 20) == pytest.approx(0.6)
