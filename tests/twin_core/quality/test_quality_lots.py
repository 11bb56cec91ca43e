"""Lot boundaries and diversion windows."""

import numpy as np
import pytest

from twin_core.quality.lots import (
    diversion_window,
    excursion_window,
    lot_boundaries,
    quantile_time,
)
from twin_core.rtd.models import axial_dispersion_open, cstr


def test_table_6_2_lot_boundaries():
    """Table 6.2 AD parameters (tau_d 11.92 s, tau 16.37 s, Pe 7.67) give 0.5 % / 99.5 %
    boundaries of 17.3 s / 72.2 s for the noise-free model (seed Table 6.2,
    standard open-open AD form)."""
    t = np.linspace(0, 300, 3001)
    lo, hi = lot_boundaries(t, axial_dispersion_open(t, 11.92, 16.37, 7.67))
    assert lo == pytest.approx(17.3, abs=0.05)
    assert hi == pytest.approx(72.2, abs=0.05)


def test_quantiles_of_cstr_analytic():
    """CSTR quantile t_q = -tau ln(1 - q) (Levenspiel 1999 Eq. 11.12), also for an unnormalized
    concentration profile (scale-invariance of Eq. 3)."""
    t = np.linspace(0, 400, 40001)
    assert quantile_time(t, 7.0 * cstr(t, 10.0), 0.5) == pytest.approx(10 * np.log(2), abs=1e-3)
    lo, hi = lot_boundaries(t, cstr(t, 10.0), 0.01, 0.99)
    assert lo == pytest.approx(-10 * np.log(0.99), abs=1e-3)
    assert hi == pytest.approx(-10 * np.log(0.01), abs=1e-3)


def test_diversion_window_shifts_by_boundaries():
    """Diversion window = [t_start + t_lo, t_end + t_hi] (Engisch & Muzzio 2016)."""
    t = np.linspace(0, 300, 3001)
    e = axial_dispersion_open(t, 11.92, 16.37, 7.67)
    lo, hi = lot_boundaries(t, e)
    s, f = diversion_window(100.0, 130.0, t, e)
    assert (s, f) == (pytest.approx(100 + lo), pytest.approx(130 + hi))


def test_quantile_with_negative_noise_is_first_crossing():
    """With negative baseline values F is not monotone; the boundary is the first time the
    normalized F reaches the level (definition of the quantile)."""
    t = np.linspace(0, 10, 11)
    e = np.array([0, 1, 1, -0.5, 1, 1, 0, 0, 0, 0, 0], dtype=float)
    f = np.cumsum(np.r_[0, 0.5 * (e[1:] + e[:-1])])
    f /= f[-1]
    q = 0.3
    i = int(np.argmax(f >= q))
    expected = t[i - 1] + (q - f[i - 1]) / (f[i] - f[i - 1]) * (t[i] - t[i - 1])
    assert quantile_time(t, e, q) == pytest.approx(expected)


def test_lots_errors():
    """Bad levels, zero area and reversed windows raise ValueError naming the field."""
    t = np.linspace(0, 10, 11)
    e = np.ones_like(t)
    with pytest.raises(ValueError, match="lower must be in"):
        lot_boundaries(t, e, lower=0.0)
    with pytest.raises(ValueError, match="lower must be < upper"):
        lot_boundaries(t, e, lower=0.9, upper=0.1)
    with pytest.raises(ValueError, match="positive area"):
        lot_boundaries(t, np.zeros_like(t))
    with pytest.raises(ValueError, match="t_end must be >= t_start"):
        diversion_window(5.0, 1.0, t, e)


def test_excursion_window_of_a_rectangle_through_a_cstr_matches_the_closed_form():
    """Reference: a rectangular inlet deviation h over d through a CSTR (E = exp(-t/tau)/tau)
    gives c(t) = h (1 - exp(-t/tau)) for t < d and c(d) exp(-(t - d)/tau) after, so the outlet
    exceeds a limit L from t1 = -tau ln(1 - L/h) to t2 = d + tau ln(c(d)/L)."""
    dt, tau, h, d, L = 0.01, 20.0, 3.0, 60.0, 1.5
    t = np.arange(0.0, 400.0, dt)
    e = np.exp(-t / tau) / tau
    dev = np.full(int(round(d / dt)), h)
    w = excursion_window(100.0, dev, e, dt, 10.0, 10.0 - L, 10.0 + L)
    cd = h * (1.0 - np.exp(-d / tau))
    t1, t2 = -tau * np.log(1.0 - L / h), d + tau * np.log(cd / L)
    assert w == pytest.approx((100.0 + t1, 100.0 + t2), abs=3 * dt)
    # a guard of 0.5 widens it to the limit L - 0.5
    g = excursion_window(100.0, dev, e, dt, 10.0, 10.0 - L, 10.0 + L, guard=0.5)
    assert g[0] == pytest.approx(100.0 - tau * np.log(1.0 - (L - 0.5) / h), abs=3 * dt)
    # a deviation that stays inside: no window; a negative one mirrors
    assert excursion_window(0.0, np.full(10, 1.0), e, dt, 10.0, 8.5, 11.5) is None
    neg = excursion_window(100.0, -dev, e, dt, 10.0, 10.0 - L, 10.0 + L)
    assert neg == pytest.approx(w)
    with pytest.raises(ValueError, match="guard"):
        excursion_window(0.0, dev, e, dt, 10.0, 8.5, 11.5, guard=2.0)
