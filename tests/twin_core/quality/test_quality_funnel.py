"""Funnel plots, OOS fractions, ANOVA/Tukey letters and the synthetic campaign."""

import numpy as np
import pytest
from scipy import stats

from twin_core.quality.funnel import (
    compare_funnels,
    funnel,
    funnel_brute_force,
    funnel_gain,
    max_window_fraction,
    oos_fraction,
)
from twin_core.rtd.models import axial_dispersion_open, cstr
from twin_core.rtd.stats import compare_groups, letters_from_pvalues
from twin_core.rtd.synthetic import TABLE_6_2, generate_campaign


def test_funnel_matches_brute_force():
    """Closed form h max_t (F(t) - F(t-d)) equals the time-domain simulation of every pulse
    convolved with E (seed Eq. 6) on a 0.05 s grid, to 0.3 % of the intensity."""
    t = np.arange(0.0, 200.0, 0.05)
    e = axial_dispersion_open(t, 11.92, 16.37, 7.67)
    d = np.arange(0.0, 60.0, 5.0)
    h = np.array([1.0, 10.0, 40.0])
    a = funnel(t, e, d, h)
    b = funnel_brute_force(t, e, d, h)
    np.testing.assert_allclose(a.max_dev, b.max_dev, atol=3e-3 * h.max())
    np.testing.assert_array_equal(a.feasible[1:], b.feasible[1:])


def test_funnel_gain_on_the_tick_grid_agrees_with_the_discrete_pulse_response():
    """The funnel gain of the diverter, M(m dt) of the piecewise-linear F (seed Table 6.2's E(t)
    on a 1 s tick), against the exact peak of the discrete convolution of an m-tick rectangular
    pulse with the normalised E (numpy.convolve): within 0.03 of the mass for every m; exact at
    m = 0 and for a pulse longer than E; non-decreasing."""
    dt = 1.0
    tk = np.arange(300) * dt
    e = axial_dispersion_open(tk, 11.92, 16.37, 7.67)
    g = funnel_gain(e, dt)
    en = e / (dt * e.sum())
    peaks = [0.0] + [float((dt * np.convolve(np.ones(m), en)).max()) for m in range(1, e.size + 1)]
    assert g.shape == (e.size + 1,)
    np.testing.assert_allclose(g, peaks, atol=0.03)
    assert g[0] == 0.0 and g[-1] == pytest.approx(1.0)
    assert np.all(np.diff(g) >= 0)
    np.testing.assert_array_equal(
        g, np.maximum.accumulate(max_window_fraction(tk, e, np.arange(e.size + 1) * dt))
    )
    with pytest.raises(ValueError, match="dt must be > 0"):
        funnel_gain(e, 0.0)


def test_funnel_cstr_closed_form():
    """CSTR: M(d) = 1 - exp(-d/tau) (Levenspiel 1999), so h_crit(d) = limit / (1 - e^(-d/tau))."""
    t = np.arange(0.0, 400.0, 0.01)
    d = np.array([2.0, 5.0, 10.0, 30.0])
    f = funnel(t, cstr(t, 10.0), d, np.linspace(0, 100, 11), limit=5.0)
    np.testing.assert_allclose(f.m, 1 - np.exp(-d / 10.0), atol=2e-3)
    np.testing.assert_allclose(f.h_crit, 5.0 / (1 - np.exp(-d / 10.0)), rtol=3e-3)


def test_feasible_area_and_comparison():
    """The feasible area equals the integral of min(h_crit, h_max); a narrower RTD gives a
    smaller feasible region (more conservative funnel) and a positive OOS increase."""
    t = np.arange(0.0, 300.0, 0.5)
    wide = funnel(t, axial_dispersion_open(t, 11.92, 16.37, 7.67))
    narrow = funnel(t, axial_dispersion_open(t, 11.92, 16.37, 15.0))
    h = np.clip(wide.h_crit, 0, 50)
    assert wide.feasible_area == pytest.approx(np.trapezoid(h, wide.durations))
    assert abs(wide.feasible_fraction - wide.feasible.mean()) < 0.02
    c = compare_funnels(wide, narrow)
    assert c["feasible_area_change"] < 0 and c["oos_increase_pct"] > 0
    assert oos_fraction(narrow) > oos_fraction(wide)
    assert compare_funnels(wide, wide)["cells_changed"] == 0
    with pytest.raises(ValueError, match="limit must be > 0"):
        funnel(t, axial_dispersion_open(t, 11.92, 16.37, 7.67), limit=0)
    with pytest.raises(ValueError, match="positive area"):
        funnel(t, np.zeros_like(t))


def test_oos_increase_curve_monotone_for_noise_free_profile():
    """Fig. 6.17 workflow on a noise-free AD profile: truncating more of the tail narrows E and
    shrinks the feasible region, so the OOS increase is positive and grows with the level
    (seed 6.2.4, first approach)."""
    from twin_core.quality.funnel import oos_increase_curve

    t = np.arange(0.0, 250.0, 1.0)
    c = 210.0 * axial_dispersion_open(t, 11.92, 16.37, 7.67)
    inc = oos_increase_curve(t, c, (0.0, 0.025, 0.05, 0.1))
    assert inc[0] == pytest.approx(0.0, abs=1e-12)
    assert np.all(np.diff(inc) > 0)


def test_anova_and_tukey_letters():
    """One-way ANOVA equals scipy.stats.f_oneway; letters: clearly separated groups get
    different letters, overlapping ones share (compact letter display, Piepho 2004)."""
    rng = np.random.default_rng(0)
    g = {"0": rng.normal(10, 0.1, 5), "a": rng.normal(10.05, 0.1, 5), "b": rng.normal(12, 0.1, 5)}
    c = compare_groups(g)
    assert c.f_stat == pytest.approx(stats.f_oneway(*g.values()).statistic)
    assert c.letters == ["A", "A", "B"]
    p = np.array([[1, 0.5, 0.01], [0.5, 1, 0.5], [0.01, 0.5, 1]])
    assert letters_from_pvalues(p) == ["A", "A B", "B"]
    with pytest.raises(ValueError, match="must hold >= 2 finite values"):
        compare_groups({"x": [1.0], "y": [1.0, 2.0]})


def test_synthetic_campaign_seeded_with_truth():
    """12 runs (4 amounts x 3 repeats), reproducible by seed, parameters drawn around Table 6.2,
    the 6 g day shifted in intensity, ground truth kept, baseline like the seed's PAT noise."""
    a = generate_campaign(5)
    b = generate_campaign(5)
    assert len(a) == 12 and [r.amount_g for r in a[::3]] == [10.0, 7.5, 6.0, 5.0]
    np.testing.assert_array_equal(a[4].c, b[4].c)
    taus = np.array([r.params["tau"] for r in generate_campaign(1) + generate_campaign(2)])
    assert taus.mean() == pytest.approx(TABLE_6_2["tau"][0], abs=0.5)
    six = [r for r in a if r.amount_g == 6.0]
    assert all(r.intensity_factor < 0.85 for r in six)
    r = a[0]
    base = np.delete(r.c - r.c_true, r.outlier_indices)[
        r.t[np.setdiff1d(np.arange(r.t.size), r.outlier_indices)] > 120
    ]
    assert -0.12 < base.mean() < 0.02 and 0.08 < base.std() < 0.2
