"""T95 mixing times (seed Eq. 29/30) and the index feature table (seed Figure 4.4)."""

import numpy as np
import pytest

from twin_core.mixing import fit_t95, index_properties, select_indices, t95_time
from twin_core.mixing.seed_tables import SEED_T95

TABLE_8_2, TABLE_8_3, TABLE_8_4 = (SEED_T95[r] for r in (100.0, 75.0, 50.0))


@pytest.mark.parametrize(
    "table", [TABLE_8_2, TABLE_8_3, TABLE_8_4], ids=["100rpm", "75rpm", "50rpm"]
)
def test_seed_tables_t95_reproduce_from_a_and_gamma(table):
    """Seed Tables 8.2-8.4: T95 = ln(20 A)/gamma from the printed (4-digit) A and gamma."""
    for name, (a, gamma, t95) in table.items():
        assert t95_time(a, gamma) == pytest.approx(t95, rel=2e-3), name


def test_t95_falls_with_blade_speed_in_seed_tables():
    for name in TABLE_8_3:
        assert TABLE_8_2[name][2] < TABLE_8_3[name][2] < TABLE_8_4[name][2] or name == "MSI"


@pytest.mark.parametrize("seed", range(5))
def test_exponential_fit_recovers_known_parameters(seed):
    """Curves of Eq. (29) with known A, gamma plus white noise: the fit recovers them."""
    rng = np.random.default_rng(seed)
    a, gamma = rng.uniform(0.5, 2.5), rng.uniform(0.2, 1.0)
    t = np.arange(0, 20, 0.1)
    m = 1 - a * np.exp(-gamma * t) + rng.normal(0, 0.02, t.size)
    fit = fit_t95(t, m, "exp")
    assert fit.A == pytest.approx(a, rel=0.05)
    assert fit.gamma == pytest.approx(gamma, rel=0.05)
    assert fit.t95 == pytest.approx(np.log(20 * a) / gamma, rel=0.05)
    assert fit.r2 > 0.95


def test_oscillating_fit_recovers_known_parameters():
    rng = np.random.default_rng(1)
    t = np.arange(0, 20, 0.1)
    m = 1 - 0.8 * np.exp(-0.5 * t) * np.cos(1.7 * t) + rng.normal(0, 0.01, t.size)
    fit = fit_t95(t, m, "osc", smooth_window=None)
    assert fit.A == pytest.approx(0.8, rel=0.05)
    assert fit.gamma == pytest.approx(0.5, rel=0.05)
    assert fit.w == pytest.approx(1.7, rel=0.03)


def test_fit_errors():
    with pytest.raises(ValueError, match="model must be"):
        fit_t95(np.arange(10.0), np.zeros(10), "poly")
    with pytest.raises(ValueError, match="at least 5 finite"):
        fit_t95(np.arange(3.0), np.zeros(3))
    with pytest.raises(ValueError, match="gamma must be > 0"):
        t95_time(1.0, 0.0)


def test_feature_table_matches_figure_4_4():
    p = index_properties()
    assert p.shape[0] == 16 and p["seed"].sum() == 15 and not p.loc["SSI", "seed"]
    sm = p.loc["SM"]
    assert sm["computational_complexity"] and sm["direction"] and sm["parameter_dependency"]
    assert not sm["color_dependency"] and not sm["grid_dependency"]
    assert not p.loc["LI", ["computational_complexity", "direction", "size"]].any()
    assert p["grid_dependency"].sum() == 8 and p.loc["VBBC", "color_dependency"] == False  # noqa: E712
    assert not p.loc["SSI", ["grid_dependency", "size", "parameter_dependency"]].any()


def test_selection_helper():
    assert set(select_indices(polydisperse=True)) == {
        "LI", "RSD", "VRR", "VBBC", "ESI", "ME", "DM", "MSI", "AH", "SSI",
    }  # fmt: skip
    assert select_indices(need_direction=True) == ["SM", "AH", "NDM"]
    assert "CN" not in select_indices(bulk_stays_intact=False)
    assert "VBBC" not in select_indices(n_components=3)
    with pytest.raises(ValueError, match="n_components"):
        select_indices(n_components=1)


@pytest.mark.parametrize("t0", [0.0, 2.0, 4.0])
def test_delayed_onset_fit_recovers_the_filling_time(t0):
    """M = 0 until t0, then Eq. (29) in t - t0 (A = 1, gamma = 0.8), white noise 0.02: the
    delayed fit recovers t0 and T95 = t0 + ln(20)/gamma; Eq. (29) fitted from the first sample
    reads the flat start as slower mixing (smaller gamma, later T95) once there is one."""
    from twin_core.mixing.t95 import delayed_model, fit_delayed_onset

    rng = np.random.default_rng(int(10 * t0))
    t = np.arange(0, 15, 0.1)
    m = delayed_model(t, 1.0, 0.8, t0) + rng.normal(0, 0.02, t.size)
    fit = fit_delayed_onset(t, m)
    assert fit.t0 == pytest.approx(t0, abs=0.2)
    assert fit.gamma == pytest.approx(0.8, rel=0.06)
    assert fit.t95 == pytest.approx(t0 + np.log(20) / 0.8, rel=0.03)
    assert fit.r2 > 0.99
    plain = fit_t95(t, m)
    if t0 > 0:
        assert plain.gamma < 0.6 and plain.t95 > fit.t95 + 1.0 and plain.r2 < fit.r2


def test_delayed_onset_fit_of_an_oscillating_curve():
    from twin_core.mixing.t95 import delayed_model, fit_delayed_onset

    rng = np.random.default_rng(2)
    t = np.arange(0, 20, 0.1)
    m = delayed_model(t, 0.8, 0.5, 3.0, 1.7) + rng.normal(0, 0.01, t.size)
    fit = fit_delayed_onset(t, m, "osc", smooth_window=None)
    assert fit.t0 == pytest.approx(3.0, abs=0.2)
    assert fit.gamma == pytest.approx(0.5, rel=0.1) and fit.w == pytest.approx(1.7, rel=0.05)
    with pytest.raises(ValueError, match="at least 8 finite"):
        fit_delayed_onset(t[:5], m[:5])
