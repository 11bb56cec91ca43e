"""Profiles, outliers, noise characterization, metrics and truncation."""

import numpy as np
import pytest

from twin_core.rtd import metrics, truncation
from twin_core.rtd.models import axial_dispersion_open, tanks_in_series
from twin_core.rtd.noise import characterize, pink_noise, synthesize
from twin_core.rtd.outliers import hampel
from twin_core.rtd.profiles import from_arrays, load_csv, moments

T = np.arange(0.0, 250.0, 0.25)
E = axial_dispersion_open(T, 11.92, 16.37, 7.67)


def test_moments_match_gamma_law():
    """Moments of a tanks-in-series profile: mean tau_d + tau, variance tau^2/n, skewness
    2/sqrt(n) (gamma distribution), scale-invariant in C (seed Eq. 3)."""
    t = np.linspace(0, 400, 40001)
    m = moments(t, 5.0 * tanks_in_series(t, 4.0, 20.0, 4.0))
    assert m.mean == pytest.approx(24.0, rel=1e-5)
    assert m.variance == pytest.approx(100.0, rel=1e-4)
    assert m.skewness == pytest.approx(1.0, rel=1e-3)
    assert m.area == pytest.approx(5.0, rel=1e-5)


def test_profile_e_and_f():
    """E integrates to 1 and F ends at 1 (seed Eqs. 3-5); times converted from minutes."""
    p = from_arrays(T / 60.0, 3.0 * E, time_unit="min")
    np.testing.assert_allclose(p.t, T, rtol=1e-12)
    assert np.trapezoid(p.e(), p.t) == pytest.approx(1.0)
    assert p.f()[-1] == pytest.approx(1.0)


def test_load_csv_units(tmp_path):
    """CSV with units declared in the header; undeclared units must be given; conflicts fail."""
    f = tmp_path / "run.csv"
    rows = "\n".join(f"{a},{b}" for a, b in zip(T[:40], E[:40] + 1))
    f.write_text("# tracer run\ntime [min],concentration [% w/w]\n" + rows + "\n")
    p = load_csv(f)
    assert p.conc_unit == "% w/w" and p.t[1] == pytest.approx(15.0)
    g = tmp_path / "bare.csv"
    g.write_text("time,concentration\n" + rows + "\n")
    with pytest.raises(ValueError, match="time_unit is not declared"):
        load_csv(g)
    assert load_csv(g, time_unit="s", conc_unit="mg/g").t[1] == pytest.approx(0.25)
    with pytest.raises(ValueError, match="time_unit given as 's' but the header declares 'min'"):
        load_csv(f, time_unit="s")
    h = tmp_path / "cols.csv"
    h.write_text("a [s],b [x],c [%]\n1,2,3\n")
    with pytest.raises(ValueError, match="concentration column is ambiguous among \\['b', 'c'\\]"):
        load_csv(h)
    with pytest.raises(ValueError, match="concentration unit must be one of .* got 'x'"):
        load_csv(h, conc_col="b")


@pytest.mark.parametrize(
    "t,c,msg",
    [
        (T[:20][::-1], E[:20], "sorted increasing"),
        (np.r_[T[:10], T[9:19]], E[:20], "duplicate times"),
        (T[:20], np.r_[E[:19], np.nan], "NaN or inf at index 19"),
        (T[:9], E[:9], "at least 10 points, got 9"),
    ],
)
def test_profile_bad_input(t, c, msg):
    """Unsorted or duplicate times, NaN and short profiles raise clear ValueErrors."""
    with pytest.raises(ValueError, match=msg):
        from_arrays(t, c)


def test_zero_area_and_bad_unit():
    """Zero area and unknown units raise ValueError naming the field."""
    with pytest.raises(ValueError, match="area must be > 0"):
        from_arrays(T[:20], np.zeros(20)).e()
    with pytest.raises(ValueError, match="area must be > 0"):
        moments(T[:20], np.zeros(20))
    with pytest.raises(ValueError, match="time_unit must be one of"):
        from_arrays(T[:20], E[:20], time_unit="fortnight")


def test_hampel_finds_injected_outliers():
    """Injected 20-sigma spikes are all found and replaced by linear interpolation (Hampel
    identifier, Pearson 2002); few false positives on Gaussian noise."""
    rng = np.random.default_rng(3)
    y = 10 * E / E.max() + rng.normal(0, 0.1, T.size)
    idx = np.array([100, 260, 261, 700])
    y_bad = y.copy()
    y_bad[idx] += np.array([2.0, -2.0, 2.5, 3.0])
    r = hampel(y_bad, t=T)
    assert set(idx) <= set(r.indices.tolist())
    assert r.count <= len(idx) + 3
    assert np.max(np.abs(r.y[idx] - y[idx])) < 0.5
    np.testing.assert_array_equal(r.original, y_bad[r.indices])
    with pytest.raises(ValueError, match="half_window must be >= 1"):
        hampel(y, 0)
    with pytest.raises(ValueError, match="y must be finite"):
        hampel(np.r_[y[:5], np.nan])
    with pytest.raises(ValueError, match="variant must be"):
        hampel(y, variant="mean")


def test_hampel_variants_replace_by_interpolation_or_by_the_window_median():
    """The two uses of the one Hampel identifier, on a convex curve y = x^2 with one upward
    spike (exact arithmetic): the seed variant interpolates linearly between the neighbours,
    (y[i-1] + y[i+1]) / 2 = y[i] + 1; the Pearson variant takes the median of the window, whose
    samples are increasing with the spike on top: the fourth smallest, y[i+1]."""
    x = np.arange(40.0)
    y = x**2
    z = y.copy()
    z[20] += 5000.0
    seed, pearson = hampel(z), hampel(z, variant="pearson")
    assert seed.indices.tolist() == pearson.indices.tolist() == [20]
    assert seed.y[20] == y[20] + 1.0 and pearson.y[20] == y[21]
    np.testing.assert_array_equal(pearson.mask, np.arange(40) == 20)


def test_noise_characterization_recovers_components():
    """White, pink and proportional components of synthetic noise are recovered (averaged over
    8 seeds, within 25 %); pink noise has spectral slope ~ -1 and white ~ 0 (definitions)."""
    s = 10 * E / E.max()
    est = []
    for seed in range(8):
        y = s + synthesize(s, 0.1, 0.07, 0.03, seed)
        est.append(characterize(T, y, s))
    assert np.mean([e.sigma_white for e in est]) == pytest.approx(0.1, rel=0.25)
    assert np.mean([e.sigma_pink for e in est]) == pytest.approx(0.07, rel=0.25)
    assert np.mean([e.k_proportional for e in est]) == pytest.approx(0.03, rel=0.25)
    slopes_p = [characterize(T, pink_noise(T.size, 1.0, k), 0 * T).spectral_slope for k in range(8)]
    slopes_w = [characterize(T, synthesize(s, 1.0, seed=k), 0 * T).spectral_slope for k in range(8)]
    assert np.mean(slopes_p) == pytest.approx(-1.0, abs=0.15)
    assert np.mean(slopes_w) == pytest.approx(0.0, abs=0.1)
    with pytest.raises(ValueError, match="at least 16 points"):
        characterize(T[:5], E[:5], E[:5])


def test_metrics_definitions():
    """FWHM of a Gaussian is 2 sqrt(2 ln 2) sigma; the seed's SNR metrics by definition."""
    t = np.linspace(0, 100, 10001)
    g = np.exp(-0.5 * ((t - 50) / 5) ** 2)
    assert metrics.fwhm(t, g) == pytest.approx(2 * np.sqrt(2 * np.log(2)) * 5, rel=1e-4)
    d = g + 0.01
    m = metrics.denoise_metrics(t, g, d)
    assert m["difference_std"] == pytest.approx(0.0, abs=1e-12) or m["improvement_snr"] > 1e6
    rng = np.random.default_rng(0)
    noisy = g + rng.normal(0, 0.1, t.size)
    m = metrics.denoise_metrics(t, noisy, g)
    diff = g - noisy
    assert m["improvement_snr"] == pytest.approx(1 / diff.std())
    assert m["difference_snr"] == pytest.approx(abs(diff.mean()) / diff.std())
    assert m["height"] == pytest.approx(1.0)
    tm = metrics.truth_metrics(t, g, g)
    assert tm["rmse_truth"] == 0 and tm["mrt_error"] == 0


def test_truncation_keeps_length_and_levels():
    """Truncations keep the number of samples (seed 6.2.3) and zero exactly the right points;
    the PAT level is mu + k sigma of the baseline window (seed 6.2.4)."""
    c = 10 * E / E.max()
    for y in (
        truncation.truncate_time(T, c, 50.0),
        truncation.truncate_level(c, 0.5),
        truncation.truncate_relative(c, 0.0375),
    ):
        assert y.shape == c.shape
    assert np.all(truncation.truncate_time(T, c, 50.0)[T > 50] == 0)
    y = truncation.truncate_relative(c, 0.05)
    assert np.all((y == 0) == (c < 0.5))
    rng = np.random.default_rng(0)
    base = c + rng.normal(-0.05, 0.13, T.size)
    lvl, mu, sd = truncation.pat_level(T, base, 3.0, 120.0)
    assert mu == pytest.approx(-0.05, abs=0.02) and sd == pytest.approx(0.13, rel=0.1)
    assert lvl == pytest.approx(mu + 3 * sd)
    spec = truncation.parse_spec("pat:3@100")
    assert (spec.kind, spec.value, spec.t_baseline) == ("pat", 3.0, 100.0)
    profiles = truncation.two_peak_profiles(T)
    assert len(profiles) == 2 and profiles[0].shape == T.shape
    for bad, msg in [
        ("x", "kind:value"),
        ("foo:1", "truncate kind"),
        ("rel:abc", "must be a number"),
    ]:
        with pytest.raises(ValueError, match=msg):
            truncation.parse_spec(bad)
    with pytest.raises(ValueError, match="fraction must be in"):
        truncation.truncate_relative(c, 1.5)
    with pytest.raises(ValueError, match="baseline samples"):
        truncation.pat_level(T, c, 3.0, 1e6)


def test_trim_with_sanity_checks():
    """Trimming keeps 1 - end_loss of the mass, renormalizes, and refuses profiles whose tail
    was cut by the measurement (sanity check as in bio-rtd's trimming)."""
    t = np.linspace(0, 300, 3001)
    e = axial_dispersion_open(t, 11.92, 16.37, 7.67)
    ts, es = truncation.trim(t, e, end_loss=1e-3)
    assert ts.size < t.size and np.trapezoid(es, ts) == pytest.approx(1.0)
    assert ts[-1] == pytest.approx(np.interp(0.999, np.cumsum(e) / e.sum(), t), abs=1.0)
    with pytest.raises(ValueError, match="does not decay"):
        truncation.trim(t[:300], e[:300])
    with pytest.raises(ValueError, match="positive peak"):
        truncation.trim(t, np.zeros_like(t))
