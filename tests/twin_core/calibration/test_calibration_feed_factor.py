"""Feed-factor response surfaces (seed Eqs. 14-16 from Tables 3.2 and 8.1) and the feeder
configured from DEM material parameters."""

from __future__ import annotations

import numpy as np
import pytest

from twin_core.calibration import ResponseSurface, load_seed_table
from twin_core.calibration.feed_factor import (
    SEED_EQ14_TERMS,
    config_from_material,
    feed_factor_parameters,
    fit_feed_factor_surfaces,
    parity_table,
)
from twin_core.feeder import LossInWeightFeeder


@pytest.fixture(scope="module")
def ff_table():
    return load_seed_table("feed_factor")


@pytest.fixture(scope="module")
def surfaces(ff_table):
    return fit_feed_factor_surfaces(ff_table)


def test_eq_14_ff_max_terms_and_coefficients(ff_table, surfaces):
    """Seed Eq. (14): stepwise (p values) selects PP_SF, PP_RF, PW_SF, (PP_SF-0.35)^2,
    (PP_SF-0.35)(PP_RF-0.05287), (PW_SF-0.35)^2; coefficients agree with the printed ones to
    1 % (0.06856, -0.050247, -0.131, -0.0303, 0.1176, -0.1723, 0.1182)."""
    s = surfaces["FF_max"]
    got = {"*".join(sorted(t)) for t in s.model_.terms_}
    assert got == {"*".join(sorted(t.split("*"))) for t in SEED_EQ14_TERMS}
    m = ResponseSurface(terms=SEED_EQ14_TERMS).fit(ff_table, "FF_max")
    expected = [0.06856, -0.050247, -0.131, -0.0303, 0.1176, -0.1723, 0.1182]
    assert m.coef_.to_numpy() == pytest.approx(expected, rel=0.01)
    assert m.anova_.loc["Model", "Prob > F"] < 1e-4  # "probability < 0.0001" (section 3.3.2.4)


def test_ff_min_and_beta_significant_factors(surfaces):
    """Section 3.3.2.4: PP_SF and PW_SF drive FF_min; PP_SF, PP_RF, PP_COR, PW_SF drive beta.
    All three models significant (Prob > F < 1e-4 for FF_max and beta, < 1e-3 for FF_min)."""
    assert set(surfaces["FF_min"].main_effects_) == {"PP_SF", "PW_SF"}
    assert set(surfaces["beta"].main_effects_) == {"PP_SF", "PP_RF", "PP_COR", "PW_SF"}
    assert surfaces["FF_max"].model_.anova_.loc["Model", "Prob > F"] < 1e-4
    assert surfaces["beta"].model_.anova_.loc["Model", "Prob > F"] < 1e-4
    assert surfaces["FF_min"].model_.anova_.loc["Model", "Prob > F"] < 1e-3
    for name, lo in (("FF_max", 0.9), ("FF_min", 0.7), ("beta", 0.9)):
        assert surfaces[name].model_.r2_ > lo
        p = parity_table(surfaces[name])
        assert len(p) == 21 and np.allclose(p.actual - p.predicted, p.residual)


def test_feeder_from_verification_run_material(surfaces):
    """Table 3.5 verification run 1 (PR/SM rows corrected) -> FF parameters -> a feeder that
    holds its set point and shows a refill surge of FF(W_high)/FF(W_low)."""
    ver = load_seed_table("verification")
    material = ver.iloc[0].drop("run").astype(float).to_dict()
    p = feed_factor_parameters(surfaces, material)
    assert 0 <= p["FF_min"] < p["FF_max"] and p["beta"] > 0
    cfg = config_from_material(
        material,
        surfaces,
        mass_scale=5.0,
        setpoint_kg_h=12.0,
        flow_noise_rel=0.0,
        load_cell_noise_kg=0.0,
        initial_mass_kg=2.0,
    )
    assert cfg.ff_max_g_rev == pytest.approx(1000 * p["FF_max"])
    tr = LossInWeightFeeder(cfg).simulate(400.0, 0.1, seed=0)
    assert len(tr.refills) == 1
    assert tr.mass_flow_kg_h[-1] == pytest.approx(12.0, rel=0.01)
    with pytest.raises(ValueError, match="material lacks"):
        feed_factor_parameters(surfaces, {"PP_SF": 0.3})
