"""T95 mixing times (seed Eq. 29/30) and the index feature table (seed Figure 4.4)."""

import numpy as np
import pytest

from twin_core.mixing import fit_t95, index_properties, select_indices, t95_time

# Seed Tables 8.2-8.4: (A, gamma, T95) per index and blade speed, fitted with Eq. (29).
# AH at 75/50 rpm is excluded: its A ~ 1e-3 with T95 ~ 10-20 s cannot come from Eq. (29) or the
# envelope of Eq. (30) -- it depends on the unreported frequency w.
TABLE_8_2 = {
    "DM": (0.6968, 0.3469, 7.5948), "VBBC": (2.6007, 1.0127, 3.9020), "ME": (6.4894, 0.9724, 5.0042),
    "VRR": (1.0721, 0.4407, 6.9552), "MSI": (0.4265, 0.4833, 4.4355), "ESI": (1.2514, 0.5038, 6.3915),
    "RSD": (1.2906, 0.4833, 6.7268), "LI": (2.2095, 1.0508, 3.6053), "CN": (1.8814, 0.4437, 8.1758),
    "SI": (1.9524, 0.5819, 6.2980), "NNM": (1.0453, 0.4234, 7.1799), "PS": (0.6447, 0.2639, 9.6891),
    "AH": (-0.8400, 0.6071, 4.6475), "SM": (0.9998, 2.9268, 1.0235), "NDM": (0.9763, 0.5023, 5.9165),
}  # fmt: skip
TABLE_8_3 = {
    "DM": (0.6666, 0.2378, 10.8918), "VBBC": (1.6018, 0.5531, 6.2675), "ME": (1.6174, 0.5852, 5.9412),
    "VRR": (0.9379, 0.3473, 8.4402), "MSI": (0.4717, 0.4832, 4.6445), "ESI": (1.2089, 0.3837, 8.3010),
    "RSD": (1.3132, 0.4030, 8.1100), "LI": (1.2171, 0.5683, 5.6170), "CN": (1.6061, 0.2905, 11.9429),
    "SI": (1.5099, 0.3703, 9.2033), "NNM": (1.1115, 0.3192, 9.7151),
}  # fmt: skip
TABLE_8_4 = {
    "DM": (0.5941, 0.1725, 14.3492), "VBBC": (1.3663, 0.3788, 8.7326), "ME": (1.2852, 0.3956, 8.2073),
    "VRR": (0.7970, 0.2259, 12.2566), "MSI": (0.3765, 0.3147, 6.4148), "ESI": (1.0740, 0.2615, 11.7292),
    "RSD": (1.3288, 0.3147, 10.4225), "LI": (0.9122, 0.3700, 7.8488), "CN": (1.3962, 0.1904, 17.4830),
    "SI": (1.3295, 0.2667, 12.3011), "NNM": (1.0891, 0.2287, 13.4705),
}  # fmt: skip


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
