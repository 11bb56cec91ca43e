"""DEM scenes of the seed on their small variants (engine runs of a few hundred particles).

Each test names its reference: Beverloo's law, the main effects of the seed's drawdown DOE
(Table 3.3 / Eqs. 10-13) and the feed-factor decay of seed Eq. (2). The blender section's axial
flow and mixing are in ``test_mixing_blender.py``.

A run of a few hundred particles is one sample of chaotic dynamics (numba compiles for the host
CPU, so another machine gives another sample): the trend tests (marker ``dem_trend``) run an
ensemble of scene seeds derived from ``TWIN_TEST_SEED`` and compare ensemble means. Each states
the spread of its quantity measured on 12 seeds (0-11, one core each) and the resulting margin
in standard errors of the ensemble mean.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from schemas.dem_scene import load_scene

CONFIGS = Path(__file__).resolve().parents[3] / "twin_core" / "scenes" / "configs"

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_numba_thread")]


def _cfg(name: str, seed: int = 0, **material) -> dict:
    d = yaml.safe_load((CONFIGS / f"{name}.yaml").read_text())
    d.setdefault("material", {}).update(material)
    d["seed"] = seed
    return d


SILO_SEEDS = 4


@pytest.mark.dem_trend
def test_silo_matches_beverloo(tmp_path, dem_seeds):
    """Flat-bottomed silo discharge rate within 15 % of Beverloo's law
    W = C rho_b sqrt(g) (D0 - k d)^2.5 with C = 0.58, k = 1.5 (Beverloo et al. 1961;
    Nedderman 1992), rho_b measured from the settled bed, D0 = 6.5 d, no rolling friction; on
    the mean of SILO_SEEDS runs.

    Spread on 12 seeds: W / W_Beverloo = 0.911 +- 0.025 per run (min 0.869, max 0.950), so a
    single run is only 2.4 sd from the 0.85 bound; the mean of 4 runs is 4.9 standard errors
    inside it (false failure ~5e-7 for a normal spread). Recycled particles 0.954 +- 0.005 of
    the discharged ones (bound 0.5)."""
    from twin_core.scenes import silo

    ratios = []
    for seed in dem_seeds(SILO_SEEDS):
        out = tmp_path / f"silo_{seed}"
        res = silo.run(load_scene(_cfg("silo_small", seed)), out, progress=False)
        assert res["recycled"] > 0.5 * res["discharged_particles"]
        assert json.loads((out / "results.json").read_text())["scene"] == "silo"
        ratios.append(res["ratio_to_beverloo"])
    assert 0.85 < np.mean(ratios) < 1.15, ratios


def test_silo_poured_into_primitive_cylinder_of_particle_material(tmp_path):
    """The silo options of the scene YAML: a poured fill (every particle inserted by the end of
    pour_s), the engine's primitive cylinder as side wall (no wall mesh; it confines the bed:
    no centre farther from the axis than R - r plus a small overlap, none lost), walls with the
    particle's elastic constants and the discharge-rate fit over the chosen window."""
    from twin_core.scenes import silo

    d = _cfg("silo_small")
    d.update(n_particles=300, settle_s=0.2, pour_s=0.1, discharge_s=0.15, fill="poured",
             wall="cylinder", fit_window_s=[0.05, 0.15])  # fmt: skip
    d["material"]["walls_of_particle_material"] = True
    cfg = load_scene(d)
    sim, geo = silo.build(cfg)
    assert [m.name for m in geo.static] == ["bottom"]
    particle, wall = sim.materials.materials
    assert (wall.density, wall.shear_modulus, wall.poisson) == (
        particle.density, particle.shear_modulus, particle.poisson,
    )  # fmt: skip
    sim.run(0.15)
    assert sim.n_particles == 300
    inside = sim.pos[:, 2] > 0
    rho = np.hypot(sim.pos[inside, 0], sim.pos[inside, 1])
    assert rho.max() < cfg.silo_radius - 0.9 * cfg.radius
    assert sim.removed_counts["lost"][0] == 0
    res = silo.run(cfg, tmp_path / "silo", progress=False)
    assert res["fit_window_s"] == [0.05, 0.15]
    assert res["discharged_particles"] > 0 and res["discharge_rate_kg_s"] > 0
    with pytest.raises(ValueError, match="fit_window_s"):
        load_scene({**d, "fit_window_s": [0.1, 0.2]})


DRAWDOWN_SEEDS = 3
# the small frame with a 30 mm (6 d) slot: with the config's 20 mm (4 d) slot the high-friction
# bed clogged in 2 of 24 seeds and its maximum flow tied the low-friction one in 2 more
DRAWDOWN_SLOT = {"opening_width": 0.03}
LOW_FRICTION = {
    "pp_friction": 0.1,
    "pp_rolling_friction": 0.01,
    "pw_friction": 0.1,
    "pw_rolling_friction": 0.01,
}
HIGH_FRICTION = {
    "pp_friction": 0.6,
    "pp_rolling_friction": 0.1,
    "pw_friction": 0.6,
    "pw_rolling_friction": 0.1,
}


def _drawdowns(tmp_path, seeds: list[int], material: dict) -> list[dict]:
    """Drawdown runs of the small frame with the 6 d slot and ``material``, one per seed."""
    from twin_core.scenes import drawdown

    runs = []
    for seed in seeds:
        cfg = _cfg("drawdown_small", seed, **material)
        cfg["geometry"].update(DRAWDOWN_SLOT)
        tag = "_".join(f"{k}{v:g}" for k, v in material.items())
        runs.append(drawdown.run(load_scene(cfg), tmp_path / f"{tag}_{seed}", progress=False))
    return runs


def _mean(runs: list[dict], key: str) -> float:
    return float(np.mean([r[key] for r in runs]))


@pytest.mark.dem_trend
def test_drawdown_main_effects(tmp_path, dem_seeds):
    """Seed 3.3.1: more static and rolling friction gives a steeper angle of repose, less mass
    in the lower container and a lower maximum flow rate (signs of Eqs. 11-13 and of the
    regression on Tables 3.2/3.3); compared on the means of DRAWDOWN_SEEDS low- and
    high-friction runs.

    The maximum flow is a count of particles per 0.05 s bin, and single pairs tied on another
    CPU (the issue's failure): the means must differ by at least one particle per bin.
    Spread on 24 seeds (0-23; 6 d slot, per low/high pair): angle of repose hi - lo
    33.1 +- 7.7 deg (min 19.8), so the mean of 3 is 5.2 standard errors above 10; lower-container
    mass hi / lo 0.537 +- 0.034 (max 0.608), 13.5 standard errors below 0.8; maximum flow
    lo - hi 14.6 +- 4.6 particles per bin (min 3), 5.1 standard errors above one particle. False
    failure < 1e-6 for normal spreads. With the config's 4 d slot the single-pair test failed on
    6 of the same 24 seeds: max-flow ties (seeds 13, 18) and a reversal (17); angle differences
    below 10 deg (6, 13) and a clogged high-friction bed (11, 23)."""
    seeds = dem_seeds(DRAWDOWN_SEEDS)
    lo = _drawdowns(tmp_path, seeds, LOW_FRICTION)
    hi = _drawdowns(tmp_path, seeds, HIGH_FRICTION)
    for r in lo + hi:
        assert r["lost_particles"] == 0
        assert 0 < r["mass_lower_kg"] < r["mass_total_kg"]
        assert np.isfinite(r["shear_angle_deg"])
    assert _mean(hi, "angle_of_repose_deg") > _mean(lo, "angle_of_repose_deg") + 10
    assert _mean(hi, "mass_lower_kg") < 0.8 * _mean(lo, "mass_lower_kg")
    particle_kg = lo[0]["mass_total_kg"] / lo[0]["n_particles"]
    quantum = particle_kg / load_scene(_cfg("drawdown_small")).flow_bin_s
    assert _mean(hi, "max_flow_kg_s") <= _mean(lo, "max_flow_kg_s") - quantum


FEEDER_SEEDS = 2


@pytest.mark.dem_trend
def test_feeder_feed_factor_decays(tmp_path, dem_seeds):
    """Seed 3.3.2.1 / Eq. (2): during run-out the feed factor falls as the hopper empties and
    FF = FF_max - (FF_max - FF_min) exp(-beta W) fits with R^2 > 0.8 (mean of FEEDER_SEEDS
    runs); every particle that left the feeder crossed the outlet (mass balance, exact).

    Spread on 12 seeds: R^2 0.894 +- 0.023 per run (min 0.854), so the mean of 2 is 5.8
    standard errors above 0.8 (a single run would be 4.1 sd); mean FF over the fuller half of
    the run-out minus the emptier half 5.25 +- 0.45 g/rev (min 4.76), 11.6 sd per run;
    discharged particles 688 of 700 in every seed (bound 350)."""
    from twin_core.scenes import feeder

    r2 = []
    for seed in dem_seeds(FEEDER_SEEDS):
        res = feeder.run(load_scene(_cfg("feeder_small", seed)), tmp_path / f"f{seed}",
                         progress=False)  # fmt: skip
        assert res["checks"]["mass_balance_ok"]
        assert res["checks"]["discharged_particles"] > 0.5 * res["n_particles_in"]
        ffc = res["feed_factor"]
        fit = ffc["fit"]
        assert fit["ff_max"] > fit["ff_min"] >= 0
        w, ff = np.asarray(ffc["w_active_kg"]), np.asarray(ffc["ff_g_rev"])
        full = ff[w > np.median(w)].mean()
        empty = ff[w <= np.median(w)].mean()
        assert full > empty
        r2.append(fit["r2"])
    assert np.mean(r2) > 0.8, r2


def test_blender_resume_continues(tmp_path):
    """An interrupted run resumed from its checkpoint ends at the same simulated time with the
    frames continued (no duplicates, times increasing)."""
    from twin_core.dem.frames import FrameReader
    from twin_core.scenes import blender

    d = _cfg("blender_small")
    d.update(mix_s=0.3, settle_s=0.1, steady_after_s=0.1, n_per_type=100)
    d["output"] = {"checkpoint_interval_s": 0.2}
    short = load_scene({**d, "mix_s": 0.1})
    blender.run(short, 100.0, tmp_path / "r", progress=False)  # "interrupted" at t = 0.2
    res = blender.run(load_scene(d), 100.0, tmp_path / "r", resume=True, progress=False)
    assert res["sim_s"] == pytest.approx(0.4)
    t = FrameReader(tmp_path / "r" / "frames").times
    assert np.all(np.diff(t) > 0) and t[-1] == pytest.approx(0.4, abs=0.02)
