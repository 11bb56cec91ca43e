"""The DEM drawdown scene as a campaign run function: factor mapping and configuration (the
DEM run itself is exercised by the scenes' own tests; one here would exceed the time budget)."""

from __future__ import annotations

import pickle

import pytest

from twin_core.calibration import SEED_FACTORS, load_seed_table
from twin_core.calibration.scenes import SEED_TO_MATERIAL, DrawdownRunner, material_update


def test_every_seed_factor_maps_to_a_material_field():
    """Table 3.1 names -> MaterialConfig fields, one to one."""
    from schemas.dem_scene import MaterialConfig

    assert set(SEED_TO_MATERIAL) == set(SEED_FACTORS)
    assert set(SEED_TO_MATERIAL.values()) <= set(MaterialConfig.model_fields)
    assert len(set(SEED_TO_MATERIAL.values())) == len(SEED_TO_MATERIAL)


def test_runner_config_for_every_seed_design_run(tmp_path):
    """Each Table 3.2 run gives a valid DrawdownScene with its material values (PR 0.5 capped
    at 0.499, the scene's contact law needing nu < 0.5), a distinct, reproducible run dir."""
    runner = DrawdownRunner({"n_particles": 2000}, run_root=tmp_path)
    design = load_seed_table("dsd")
    dirs = set()
    for _, row in design.iterrows():
        params = {f: float(row[f]) for f in SEED_FACTORS}
        cfg = runner.config(params, seed=7)
        m = cfg.material
        assert m.pp_friction == params["PP_SF"] and m.pw_rolling_friction == params["PW_RF"]
        assert m.shear_modulus == params["SM"]
        assert m.poisson == min(params["PR"], 0.499)
        assert cfg.n_particles == 2000 and cfg.seed == 7 and not cfg.output.figures
        dirs.add(runner.run_dir(params, 7))
        assert runner.run_dir(params, 7) == runner.run_dir(dict(reversed(params.items())), 7)
    assert len(dirs) == 21
    # picklable for process pools and Dask
    clone = pickle.loads(pickle.dumps(runner))
    assert clone.config(params, 7) == runner.config(params, 7)


def test_bad_factor_names_and_values(tmp_path):
    with pytest.raises(ValueError, match="not DEM material factors"):
        material_update({"PP_SF": 0.3, "bogus": 1.0})
    runner = DrawdownRunner(run_root=tmp_path)
    with pytest.raises(ValueError, match="pp_restitution"):
        runner.config({"PP_COR": 1.5}, seed=0)
