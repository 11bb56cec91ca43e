"""Convolution, cumulative F(t) and frequency response tests."""

import numpy as np
import pytest

from twin_core.rtd import models as M
from twin_core.rtd.convolution import convolve, convolve_rtds, cumulative, uniform_dt


def test_convolve_step_gives_f():
    """A unit step through a system gives F(t) (Levenspiel 1999 Eq. 11.9: F = int E)."""
    t = np.linspace(0, 200, 4001)
    e = M.cstr_pfr(t, 5.0, 10.0)
    y = convolve(t, np.ones_like(t), e)
    f = np.where(t > 5.0, 1.0 - np.exp(-(t - 5.0) / 10.0), 0.0)
    np.testing.assert_allclose(y, f, atol=0.01)


def test_convolve_matches_direct_sum():
    """FFT convolution equals the direct O(N^2) rectangle-rule sum (definition)."""
    rng = np.random.default_rng(0)
    t = np.arange(300) * 0.5
    u, e = rng.normal(size=300), rng.random(300)
    direct = np.array([sum(u[j] * e[i - j] for j in range(i + 1)) for i in range(300)]) * 0.5
    np.testing.assert_allclose(convolve(t, u, e), direct, atol=1e-10)


def test_convolve_rtds_cstr_cstr_is_two_tanks():
    """CSTR(tau) * CSTR(tau) = tanks in series with n = 2, total 2 tau (Levenspiel 1999 ch. 14)."""
    t = np.linspace(0, 300, 30001)
    e = convolve_rtds(t, M.cstr(t, 10.0), M.cstr(t, 10.0))
    np.testing.assert_allclose(e, M.tanks_in_series(t, 0.0, 20.0, 2.0), atol=2e-5)


def test_cumulative_of_cstr():
    """F(t) of a CSTR is 1 - exp(-t/tau) (Levenspiel 1999 Eq. 11.12)."""
    t = np.linspace(0, 100, 10001)
    np.testing.assert_allclose(cumulative(t, M.cstr(t, 8.0)), 1 - np.exp(-t / 8.0), atol=1e-5)


def test_convolution_errors():
    """Bad grids and shapes raise ValueError naming the field."""
    t = np.array([0.0, 1.0, 3.0])
    with pytest.raises(ValueError, match="uniformly spaced"):
        uniform_dt(t)
    with pytest.raises(ValueError, match="strictly increasing"):
        uniform_dt([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="u must have the shape"):
        convolve(np.arange(3.0), np.ones(2), np.ones(3))
    with pytest.raises(ValueError, match="e must be finite"):
        convolve(np.arange(3.0), np.ones(3), np.array([1.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="strictly increasing"):
        cumulative([1.0, 0.0], [1.0, 1.0])


def test_series_and_parallel_combinations():
    """Series of PFR-delayed CSTRs = tanks in series with delay (rtdpy-style combination);
    parallel paths are the fraction-weighted sum (Levenspiel 1999 ch. 12)."""
    from twin_core.rtd.convolution import parallel, series

    t = np.linspace(0, 300, 30001)
    e = series(t, M.cstr_pfr(t, 4.0, 10.0), M.cstr(t, 10.0), M.cstr(t, 10.0))
    np.testing.assert_allclose(e, M.tanks_in_series(t, 4.0, 30.0, 3.0), atol=5e-5)
    p = parallel([0.3, 0.7], M.cstr(t, 5.0), M.cstr(t, 20.0))
    assert np.trapezoid(t * p, t) == pytest.approx(0.3 * 5 + 0.7 * 20, rel=1e-3)
    with pytest.raises(ValueError, match="sum to 1"):
        parallel([0.5, 0.6], M.cstr(t, 5.0), M.cstr(t, 20.0))
    with pytest.raises(ValueError, match="at least one RTD"):
        series(t)
