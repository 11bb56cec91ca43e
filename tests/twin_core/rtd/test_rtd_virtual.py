"""Virtual tracer experiments (``rtd.virtual``): the truths the fits are checked on come from
code paths independent of ``rtd.models``, and each is validated here against an analytic
solution or a literature law."""

import numpy as np
import pytest
from scipy import signal

from twin_core.rtd import virtual as V
from twin_core.rtd.models import axial_dispersion_open, axial_dispersion_open_dead_volume, emg

T = np.arange(0.0, 161.0)


def test_dispersion_pde_matches_the_open_open_solution():
    """Method-of-lines PDE solution vs the closed-form open-open E(t) (Levenspiel 1999 Eq.
    13.19, the resident concentration of an infinite domain): within 1e-3 of the peak with
    200 nodes per length (measured 2e-5 with the default 400)."""
    e = V.dispersion_pde(T[:100], 11.92, 16.37, 7.67, nodes=200)
    ref = axial_dispersion_open(T[:100], 11.92, 16.37, 7.67)
    assert np.max(np.abs(e - ref)) < 1e-3 * ref.max()


def test_two_zone_pde_matches_the_laplace_inversion():
    """Two-zone (mobile-immobile) PDE vs the Talbot inversion of the exchange model's transfer
    function G_AD(s (1 + r / (1 + s tau_x))) (van Genuchten & Wierenga 1976; an independent
    numerical method): within 1e-3 of the peak, 200 nodes per length."""
    e = V.dispersion_pde(T[:100], 10.0, 14.0, 10.0, 0.3, 25.0, nodes=200)
    ref = axial_dispersion_open_dead_volume(T[:100], 10.0, 14.0, 10.0, 0.3, 25.0)
    assert np.max(np.abs(e - ref)) < 1e-3 * ref.max()


def test_tanks_gamma_moments():
    """scipy.stats.gamma tanks in series: mean tau_d + tau, variance tau^2 / n (Levenspiel
    1999 Eq. 14.3)."""
    t = np.linspace(0.0, 400.0, 40001)
    e = V.tanks_gamma(t, 8.0, 24.0, 4.0)
    mean = np.trapezoid(t * e, t)
    assert mean == pytest.approx(32.0, rel=1e-6)
    assert np.trapezoid((t - mean) ** 2 * e, t) == pytest.approx(24.0**2 / 4, rel=1e-5)


def test_emg_convolution_matches_grushka():
    """Numerical convolution of a Gaussian with an exponential vs the closed form of Grushka
    (1972): within 1e-4 of the peak."""
    e = V.emg_convolution(T, 22.0, 4.0, 12.0)
    ref = emg(T, 22.0, 4.0, 12.0)
    assert np.max(np.abs(e - ref)) < 1e-4 * ref.max()


def test_measure_noise_components():
    """On a zero signal the measured noise is offset + white + 1/f: the periodogram slope of
    the 1/f-only part is about -1 (between -1.3 and -0.7 over 20 records; Press 1978), twice
    the noise doubles the spread of the white-only part, and outliers land at the
    indices returned with 1-3 % w/w."""
    rng = np.random.default_rng(0)
    pink_only = V.NoiseSpec(0.0, 0.1, 0.0, 0.0, 0.0, 0.0)
    slopes = []
    for _ in range(20):
        y, _ = V.measure(np.zeros(1024), pink_only, rng)
        f, p = signal.periodogram(y)
        slopes.append(np.polyfit(np.log(f[1:]), np.log(p[1:]), 1)[0])
    assert -1.3 < np.mean(slopes) < -0.7
    white = V.NoiseSpec(0.1, 0.0, 0.0, 0.0, 0.0, 0.0)
    s1 = np.std(V.measure(np.zeros(20000), white, rng)[0])
    s2 = np.std(V.measure(np.zeros(20000), white.scaled(2.0), rng)[0])
    assert s2 / s1 == pytest.approx(2.0, rel=0.03)
    spiky = V.NoiseSpec(0.0, 0.0, 0.0, 0.0, 0.0, 0.05)
    y, idx = V.measure(np.zeros(1000), spiky, rng)
    assert idx.size > 20 and np.all((np.abs(y[idx]) >= 1.0) & (np.abs(y[idx]) <= 3.0))
    assert np.count_nonzero(y) == idx.size


def test_pulse_concentration_and_errors():
    """c = 100 r m E / Q (the synthetic campaign's recovery and flow); bad arguments fail."""
    e = axial_dispersion_open(T, 11.92, 16.37, 7.67)
    c = V.pulse_concentration(e, 10.0)
    assert np.trapezoid(c, T) == pytest.approx(100 * 0.7 * 10.0 / (12000 / 3600), rel=1e-3)
    with pytest.raises(ValueError, match="pe must be finite and > 0"):
        V.dispersion_pde(T, 1.0, 10.0, -1.0)
    with pytest.raises(ValueError, match="r_dead must be finite and >= 0"):
        V.dispersion_pde(T, 1.0, 10.0, 5.0, -0.1)
    with pytest.raises(ValueError, match="sigma, tau_e and step must be > 0"):
        V.emg_convolution(T, 1.0, 0.0, 1.0)
