"""Denoising methods: lengths, references (pandas, scipy, PyWavelets) and automatic choices."""

import numpy as np
import pandas as pd
import pytest
import pywt
from scipy.signal import savgol_filter

from twin_core.rtd import denoise as D
from twin_core.rtd.models import axial_dispersion_open

T = np.arange(0.0, 250.0, 0.25)
S = 10 * axial_dispersion_open(T, 11.92, 16.37, 7.67) / 0.0436
Y = S + np.random.default_rng(7).normal(0, 0.15, T.size)


@pytest.mark.parametrize("method", ["sa", "sa_centred", "sg", "fft", "wavelet", "auto"])
def test_same_length_out(method):
    """Same length in, same length out, for every method (odd and even lengths)."""
    for y in (Y, Y[:-1]):
        assert D.denoise(y, method).y.shape == y.shape


def test_trailing_average_equals_pandas_rolling():
    """The trailing sliding average equals the seed's pandas Series.rolling(M).mean() where
    pandas is defined, and MATLAB-style movmean (centred) on the interior."""
    ref = pd.Series(Y).rolling(5).mean().to_numpy()
    got = D.sliding_average(Y, 5, "trailing")
    np.testing.assert_allclose(got[4:], ref[4:], atol=1e-12)
    cen = pd.Series(Y).rolling(5, center=True, min_periods=1).mean().to_numpy()
    np.testing.assert_allclose(D.sliding_average(Y, 5, "centred"), cen, atol=1e-12)


def test_savgol_equals_scipy():
    """Savitzky-Golay with the seed's (11, 3) equals scipy.signal.savgol_filter."""
    np.testing.assert_allclose(D.savitzky_golay(Y), savgol_filter(Y, 11, 3), rtol=1e-12)


@pytest.mark.parametrize("mode", ["soft", "hard", "garrote"])
def test_wavelet_matches_pywavelets_thresholding(mode):
    """With a fixed threshold our wavelet denoiser equals PyWavelets' own pipeline
    (wavedec -> pywt.threshold on details, sigma from level-1 MAD -> waverec), sym4."""
    x = np.sin(np.linspace(0, 8, 300)) + np.random.default_rng(1).normal(0, 0.2, 300)
    coeffs = pywt.wavedec(x, "sym4", mode="symmetric", level=5)
    sigma = np.median(np.abs(coeffs[-1])) / 0.6745
    thr = 2.5 * sigma
    ref = pywt.waverec(
        [coeffs[0]] + [pywt.threshold(c, thr, mode=mode) for c in coeffs[1:]],
        "sym4",
        mode="symmetric",
    )[:300]
    got = D.wavelet(x, level=5, threshold=2.5, mode=mode)
    np.testing.assert_allclose(got, ref, atol=1e-12)


def test_wavelet_default_level_is_matlab_rule():
    """MATLAB wdenoise default level: min(floor(log2 N), wmaxlev(N, 'sym4'))."""
    assert D.wavelet_level(1000) == min(9, pywt.dwt_max_level(1000, 8))
    assert D.wavelet_level(64) == pywt.dwt_max_level(64, 8)


@pytest.mark.parametrize("prior,far", [("cauchy", 20.0 - 2.0 / 20.0), ("laplace", 19.5)])
def test_ebayes_posterior_median_properties(prior, far):
    """Empirical Bayes posterior median (Johnstone & Silverman 2005): a thresholding rule, odd
    and monotone; for large x it tends to x - 2/x (quasi-Cauchy, the MATLAB wdenoise prior) or
    x - a (Laplace, a = 0.5); mostly zeros on pure noise."""
    rng = np.random.default_rng(0)
    x = np.r_[rng.normal(size=500), 20.0, -20.0, 8.0]
    mu, w = D.ebayes_posterior_median(x, prior)
    assert 0 < w < 1
    assert np.mean(mu[:500] == 0) > 0.9
    assert mu[500] == pytest.approx(far, abs=1e-3)
    assert mu[501] == pytest.approx(-far, abs=1e-3)
    order = np.argsort(x)
    assert np.all(np.diff(mu[order]) >= -1e-9)


@pytest.mark.parametrize("prior", ["cauchy", "laplace"])
def test_ebayes_threshold_consistent_with_median(prior):
    """The posterior median is exactly zero below the threshold t(w) given by the threshold
    equation and positive above it: two independent formulas of Johnstone & Silverman (2005)
    agree."""
    for w in (0.02, 0.1, 0.5):
        t = D.threshold_from_weight(w, prior)
        assert t > 0
        if prior == "cauchy":
            lo, hi = D._postmed_cauchy(np.array([t - 1e-4, t + 1e-4]), w)
        else:
            lo, hi = D._postmed_laplace(np.array([t - 1e-4, t + 1e-4]), w, 0.5)
        assert lo == 0 and 0 < hi < 0.05


def test_denoising_reduces_error_to_truth():
    """Each method reduces the RMSE to the truth below the noise level (0.15); the
    automatic choices do at least as well as the seed's SA(5) trailing average."""
    rmse = {m: np.sqrt(np.mean((D.denoise(Y, m).y - S) ** 2)) for m in D.METHODS}
    assert all(v < 0.15 for k, v in rmse.items() if k != "sa")
    assert rmse["auto"] < rmse["sa"]
    a = D.auto_savitzky_golay(Y)
    assert a.params["window"] % 2 == 1 and np.sqrt(np.mean((a.y - S) ** 2)) < 0.08


def test_fft_lowpass_is_dct_truncation():
    """Low-pass of the mirror extension equals truncation of the orthonormal DCT-II (Makhoul
    1980, IEEE TASSP 28, 27), which makes the Cp degrees of freedom exact."""
    from scipy.fft import dct, idct

    c = dct(Y, norm="ortho")
    c[40:] = 0
    np.testing.assert_allclose(D.fft_lowpass(Y, 40), idct(c, norm="ortho"), atol=1e-12)


def test_fft_cutoff_rule_and_sure_risk():
    """The FFT cutoff rule keeps the signal band (cutoff well below Nyquist); the Cp/SURE risk
    estimate is unbiased for the mean squared error to the truth (Stein 1981; Mallows 1973):
    averaged over 12 noise seeds it is within 30 % of the realized MSE."""
    k = D.fft_cutoff_rule(Y)
    assert 5 < k < Y.size // 4
    for f in (D.auto_fft, D.auto_savitzky_golay):
        est, mse = [], []
        for seed in range(12):
            y = S + np.random.default_rng(100 + seed).normal(0, 0.15, T.size)
            r = f(y, sigma=0.15)
            est.append(r.risk)
            mse.append(np.mean((r.y - S) ** 2))
        assert np.mean(est) == pytest.approx(np.mean(mse), rel=0.3)


def test_denoise_errors():
    """Bad parameters raise ValueError naming them."""
    with pytest.raises(ValueError, match="method must be one of"):
        D.denoise(Y, "magic")
    with pytest.raises(ValueError, match="window must be odd"):
        D.savitzky_golay(Y, 10)
    with pytest.raises(ValueError, match="mode must be 'trailing' or 'centred'"):
        D.sliding_average(Y, 5, "future")
    with pytest.raises(ValueError, match="wavelet must be a discrete"):
        D.wavelet(Y, wavelet="morl")
    with pytest.raises(ValueError, match="cutoff must be in"):
        D.fft_lowpass(Y, 0)
    with pytest.raises(ValueError, match="y must be finite"):
        D.denoise(np.r_[Y[:10], np.nan])


@pytest.mark.parametrize("prior", ["cauchy", "laplace"])
def test_weight_threshold_roundtrip(prior):
    """The lower weight bound w_lo (threshold at sqrt(2 log n)) inverts the threshold equation."""
    for t in (1.5, 2.5, 3.7):
        w = D._weight_from_threshold(t, prior, 0.5)
        assert D.threshold_from_weight(w, prior) == pytest.approx(t, abs=1e-6)


def test_wavelet_bayes_equals_per_level_pipeline():
    """The default (MATLAB wdenoise-like) wavelet denoiser equals the explicit per-level
    pipeline: PyWavelets sym4 wavedec, sigma = median|d1|/0.6745, quasi-Cauchy empirical Bayes
    posterior median on every detail level, approximation kept, waverec."""
    coeffs = pywt.wavedec(Y, "sym4", mode="symmetric", level=D.wavelet_level(Y.size))
    sigma = np.median(np.abs(coeffs[-1])) / 0.6745
    shrunk = [coeffs[0]] + [D.ebayes_posterior_median(c / sigma)[0] * sigma for c in coeffs[1:]]
    ref = pywt.waverec(shrunk, "sym4", mode="symmetric")[: Y.size]
    np.testing.assert_allclose(D.wavelet(Y), ref, atol=1e-9)
