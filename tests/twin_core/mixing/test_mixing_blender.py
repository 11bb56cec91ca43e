"""Axial flow and mixing in the DEM blender section, on an ensemble of scene seeds.

References: the rigid-body kinematics of a pitched blade (the net axial flow has the sign of the
blades' leading-face normal and grows with blade speed), and seed Table 4.2 / Figure 4.7 with
the literature it cites (Gao et al.): in the periodic section of a convective blender mixing is
faster and the T95 mixing time shorter at a higher blade speed.

The section is the small variant (``blender_small``: 2 x 300 particles, 1.2 s of mixing at 50
and 100 rpm), run through ``twin dem run`` and ``twin mixing blender`` for ``N_SEEDS`` scene
seeds (particle placement) derived from ``TWIN_TEST_SEED``. A run of a few hundred particles is
one sample of chaotic dynamics (another CPU gives another sample), so every claim below is a
claim about the distribution, sized on 12 seeds (0-11, one core each): the spread is written in
each test's docstring with the resulting false-failure probability.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from services.cli.main import main

SCENE = (
    Path(__file__).resolve().parents[3] / "twin_core" / "scenes" / "configs" / "blender_small.yaml"
)
N_SEEDS = 3

pytestmark = [pytest.mark.slow, pytest.mark.dem_trend]


def _run_seed(seed: int, root: Path) -> Path:
    """``twin dem run`` and ``twin mixing blender`` of the small section with scene ``seed``;
    returns the run directory (``rpm_50``, ``rpm_100``, ``mixing``)."""
    cfg = yaml.safe_load(SCENE.read_text())
    cfg["seed"] = seed
    cfg.setdefault("output", {})["figures"] = False
    scene = root / f"blender_seed{seed}.yaml"
    scene.write_text(yaml.safe_dump(cfg))
    out = root / f"seed{seed}"
    dem = ["dem", "run", str(scene), "--out", str(out), "--threads", "1", "--no-progress"]
    assert main(dem) == 0
    mixing = ["mixing", "blender", str(scene), "--runs", str(out), "--out", str(out / "mixing")]
    assert main(mixing) == 0
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory, dem_seeds) -> list[Path]:
    import numba

    root = tmp_path_factory.mktemp("blender")
    n = numba.get_num_threads()
    try:
        return [_run_seed(seed, root) for seed in dem_seeds(N_SEEDS)]
    finally:
        numba.set_num_threads(n)


def _results(run: Path, rpm: int) -> dict:
    return json.loads((run / f"rpm_{rpm}" / "results.json").read_text())


def _lacey(run: Path, rpm: int) -> tuple[np.ndarray, np.ndarray]:
    with np.load(run / f"rpm_{rpm}" / "mixing.npz") as z:
        return z["t"], z["lacey"]


def _t95_table(run: Path) -> pd.DataFrame:
    return pd.read_csv(run / "mixing" / "t95_by_speed.csv", index_col=0)


def test_axial_flow_follows_the_blade_push_and_grows_with_speed(runs):
    """In every run the net axial flow through the mid plane has the sign of the blades'
    leading-face normal, and it is larger at 100 rpm than at 50 rpm.

    Spread on 12 seeds: |flow| 0.0262 +- 0.0019 kg/s at 50 rpm (min 0.0230), 0.0561 +- 0.0020 at
    100 rpm; the sign agreed in all 24 runs (13.7 sd from zero); |flow_100| - |flow_50| =
    0.0298 +- 0.0025 kg/s (min 0.0257), 11.9 sd. False failure over the ensemble < 1e-20 for a
    normal spread; the margins leave room for much heavier tails. Whole-section transits in the
    1.2 s window: 116-191 per run at 100 rpm, but 0-9 at 50 rpm (most transits there are longer
    than the window: seeds 0-2 on one machine gave 9, 5, 0), so only the 100 rpm count is a
    per-run claim."""
    for run in runs:
        r50, r100 = _results(run, 50), _results(run, 100)
        for r in (r50, r100):
            assert r["blade_push_sign_x"] != 0
            assert r["net_axial_flow_sign"] == r["blade_push_sign_x"], run
        assert r100["transit_count"] > 0, run
        assert abs(r100["net_axial_flow_kg_s"]) > abs(r50["net_axial_flow_kg_s"]), run


def test_mixing_proceeds_faster_at_the_higher_blade_speed(runs):
    """Lacey's index (1 x 8 x 8 grid, seed 4.4.1) starts segregated (< 0.3) and, half-way
    through the run, is higher at 100 rpm than at 50 rpm on the ensemble mean.

    Spread on 12 seeds: Lacey at the start -0.043 +- 0.002 (max -0.040); the difference
    100 - 50 rpm at half the run 0.221 +- 0.043 per seed (min 0.154), so the mean of 3 seeds is
    8.9 standard errors above zero (false failure ~1e-18 for a normal spread)."""
    diffs = []
    for run in runs:
        (t50, m50), (t100, m100) = _lacey(run, 50), _lacey(run, 100)
        assert m50[0] < 0.3 and m100[0] < 0.3, run  # segregated start
        half = min(t50[-1], t100[-1]) / 2
        diffs.append(np.interp(half, t100, m100) - np.interp(half, t50, m50))
    assert np.mean(diffs) > 0, diffs


def test_t95_falls_as_blade_speed_rises(runs):
    """T95 of the 15 mixing indices (seed Eq. 29/30 fits, ``twin mixing blender``) is shorter
    at 100 rpm than at 50 rpm: over the ensemble, the mean of each seed's median (over indices)
    of ln(T95_50 / T95_100) is positive, and on average most indices show the fall.

    The 1.2 s runs are far shorter than the seed's 20 s ones and the effect is small (T95 falls
    by ~20 %), so one run decides nothing: seed 10 alone gives the fall for 10 of 15 indices
    only (the issue's 9 of 15 on another CPU). Spread on 12 seeds: median log ratio
    0.203 +- 0.062 per seed (min 0.112), 5.7 standard errors for the mean of 3 (false failure
    ~1e-8 for a normal spread); fraction of indices that fall 0.92 +- 0.09 per seed (min 0.67),
    the mean of 3 is 8 standard errors above 1/2."""
    medians, falls = [], []
    for run in runs:
        table = _t95_table(run)
        assert list(table.columns) == ["100 rpm", "50 rpm"]
        both = table.dropna()
        assert len(both) >= 12, table
        assert np.all(both.to_numpy() > 0), table
        log_ratio = np.log(both["50 rpm"] / both["100 rpm"])
        medians.append(float(np.median(log_ratio)))
        falls.append(float((log_ratio > 0).mean()))
    assert np.mean(medians) > 0, medians
    assert np.mean(falls) > 0.5, falls


def test_blender_outputs_follow_their_contracts(runs):
    """The field file has the compartment contract's keys and a 10x20x20 grid; the mixing CLI
    writes its table and figures."""
    run = runs[0]
    with np.load(run / "rpm_100" / "fields.npz") as f:
        assert f["velocity"].shape == (10, 20, 20, 3)
        for k in ("solid_fraction", "occupancy"):
            assert f[k].shape == (10, 20, 20)
        for k in ("crossings_x", "crossings_y", "crossings_z"):
            assert f[k].shape == (10, 20, 20, 2)
        assert list(f["periodic"]) == [True, False, False]
        assert f["crossings_z"][:, :, -1].sum() == 0
        assert f["duration_s"] > 0 and f["particle_mass_kg"] > 0
    assert (run / "mixing" / "t95_by_speed.png").stat().st_size > 5_000
    assert (run / "mixing" / "rpm_100" / "mixing_indices.png").exists()
    assert (run / "mixing" / "rpm_100" / "velocity.png").exists()
