"""RTD model tests: normalization, moments and transfer functions against closed forms."""

import numpy as np
import pytest
from scipy import special
from scipy.integrate import trapezoid

from twin_core.rtd import models as M
from twin_core.rtd.convolution import frequency_response

T = np.linspace(0.0, 600.0, 300_001)
T_COARSE = np.linspace(0.0, 600.0, 30_001)  # for the numerically inverted models


def _moments(t, e):
    a = trapezoid(e, t)
    m = trapezoid(t * e, t) / a
    v = trapezoid((t - m) ** 2 * e, t) / a
    s = trapezoid((t - m) ** 3 * e, t) / a / v**1.5
    return a, m, v, s


@pytest.mark.parametrize("pe", [2.0, 7.67, 40.0, 300.0])
def test_ad_open_integrates_to_one_and_mean_levenspiel(pe):
    """Open-open dispersion: area 1, mean tau_d + tau (1 + 2/Pe), variance tau^2 (2/Pe + 8/Pe^2)
    (Levenspiel 1999, Eq. 13.19 and its moments)."""
    tau_d, tau = 11.92, 16.37
    a, m, v, _ = _moments(T, M.axial_dispersion_open(T, tau_d, tau, pe))
    assert a == pytest.approx(1.0, abs=1e-6)
    assert m == pytest.approx(tau_d + tau * (1 + 2 / pe), rel=1e-5)
    assert v == pytest.approx(tau**2 * (2 / pe + 8 / pe**2), rel=1e-4)


def test_ad_open_zero_before_delay_and_seed_mean():
    """E = 0 for t <= tau_d; Table 6.2 parameters give a mean residence time ~32.5 s
    (seed Table 6.2 with the standard AD moments)."""
    e = M.axial_dispersion_open(T, 11.92, 16.37, 7.67)
    assert np.all(e[T <= 11.92] == 0.0)
    _, m, _, _ = _moments(T, e)
    assert m == pytest.approx(32.5, abs=0.1)


@pytest.mark.parametrize("pe", [0.5, 7.67, 29.0, 31.0, 120.0, 1000.0])
def test_ad_closed_variance_law(pe):
    """Closed-closed dispersion: area 1, mean tau_d + tau, variance
    tau^2 (2/Pe - 2/Pe^2 (1 - exp(-Pe))) (van der Laan 1958; Levenspiel 1999 Eq. 13.13).
    Covers both inversion paths (Talbot for Pe <= 30, Fourier above)."""
    tau_d, tau = 5.0, 16.37
    a, m, v, _ = _moments(T_COARSE, M.axial_dispersion_closed(T_COARSE, tau_d, tau, pe))
    assert a == pytest.approx(1.0, abs=1e-6)
    assert m == pytest.approx(tau_d + tau, rel=1e-6)
    assert v == pytest.approx(tau**2 * (2 / pe - 2 / pe**2 * (1 - np.exp(-pe))), rel=1e-5)


def test_ad_closed_eigen_series_cross_check():
    """Closed-closed E at Pe = 4 against the independent eigenfunction series (residues of the
    Danckwerts transfer function at tan(l) = 4 Pe l / (4 l^2 - Pe^2), Levenspiel 1999 ch. 13)."""
    from scipy.optimize import brentq

    pe, tau = 4.0, 10.0
    f = lambda lam: (4 * lam**2 - pe**2) * np.sin(lam) - 4 * pe * lam * np.cos(lam)  # noqa: E731
    lams = [brentq(f, 1e-9 if k == 0 else k * np.pi, (k + 1) * np.pi) for k in range(60)]
    theta = np.linspace(0.05, 4.0, 200)
    e_series = np.zeros_like(theta)
    for lam in lams:
        q = 2j * lam / pe
        a = q * pe / 2
        dd = (
            2 * (1 + q) * np.exp(a)
            + (1 + q) ** 2 * pe / 2 * np.exp(a)
            + 2 * (1 - q) * np.exp(-a)
            + (1 - q) ** 2 * pe / 2 * np.exp(-a)
        )
        s = pe * (q**2 - 1) / 4
        e_series += np.real(2 * pe * q**2 * np.exp(pe / 2 + s * theta) / dd)
    e_model = M.axial_dispersion_closed(theta * tau, 0.0, tau, pe) * tau
    np.testing.assert_allclose(e_model, e_series, atol=1e-7)


@pytest.mark.parametrize("n", [0.7, 1.0, 3.5, 20.0])
def test_tanks_in_series_gamma_moments(n):
    """Tanks in series (non-integer n) = gamma distribution: mean tau_d + tau, variance tau^2/n,
    skewness 2/sqrt(n) (Levenspiel 1999 Eq. 14.3; gamma-distribution moments)."""
    tau_d, tau = 3.0, 20.0
    t = (
        T
        if n >= 1
        else np.concatenate([np.linspace(0, 3.1, 200_001)[:-1], np.linspace(3.1, 600, 300_001)])
    )
    e = M.tanks_in_series(t, tau_d, tau, n)
    a, m, v, s = _moments(t, e)
    rtol = 1e-4 if n >= 1 else 3e-3
    assert a == pytest.approx(1.0, rel=rtol)
    assert m == pytest.approx(tau_d + tau, rel=rtol)
    assert v == pytest.approx(tau**2 / n, rel=rtol)
    assert s == pytest.approx(2 / np.sqrt(n), rel=5 * rtol)


def test_tanks_in_series_matches_scipy_gamma():
    """Pointwise equality with scipy.stats.gamma(a=n, loc=tau_d, scale=tau/n) (peer code)."""
    from scipy.stats import gamma

    t = np.linspace(0, 100, 1001)
    np.testing.assert_allclose(
        M.tanks_in_series(t, 4.0, 15.0, 2.7),
        gamma.pdf(t, 2.7, loc=4.0, scale=15.0 / 2.7),
        rtol=1e-12,
        atol=1e-300,
    )


def test_cstr_pfr_and_emg_and_zusatz_moments():
    """CSTR+PFR mean tau_p + tau_c, variance tau_c^2; EMG mean mu + tau_e, variance
    sigma^2 + tau_e^2 (Grushka 1972); Zusatz area 1 and mean tau_d + b k^(1/c) Gamma(1-1/c),
    k = (c+1)/c (derived from u = (b/s)^c ~ Exp(k); Poulesquen et al. 2003)."""
    _, m, v, _ = _moments(T, M.cstr_pfr(T, 7.0, 12.0))
    assert (m, v) == (pytest.approx(19.0, rel=1e-4), pytest.approx(144.0, rel=1e-3))
    _, m, v, _ = _moments(T, M.emg(T, 30.0, 3.0, 6.0))
    assert (m, v) == (pytest.approx(36.0, rel=1e-6), pytest.approx(45.0, rel=1e-5))
    t = np.linspace(0, 5000, 2_000_001)
    a, m, _, _ = _moments(t, M.zusatz(t, 2.0, 10.0, 4.0))
    k = 5.0 / 4.0
    assert a == pytest.approx(1.0, abs=1e-5)
    assert m == pytest.approx(2.0 + 10.0 * k**0.25 * special.gamma(0.75), rel=1e-4)


def test_convection_and_high_pe_models():
    """Laminar convection E = tau^2/(2 t^3), t >= tau/2: area 1 and mean tau (Levenspiel 1999
    Eq. 15.3); the small-dispersion model has mean tau_d + tau and variance 2 tau^2/Pe (Eq. 13.8)."""
    t = np.geomspace(5.0, 20000, 400_001)  # starts at the jump t = tau/2
    e = M.convection(t, 10.0)
    assert trapezoid(e, t) == pytest.approx(1.0, abs=1e-3)
    assert trapezoid(t * e, t) == pytest.approx(10.0 - 10.0**2 / (2 * 20000), rel=1e-3)
    a, m, v, _ = _moments(T, M.plug_flow_dispersion_high_pe(T, 5.0, 20.0, 400.0))
    assert (a, m) == (pytest.approx(1.0, abs=1e-6), pytest.approx(25.0, rel=1e-6))
    assert v == pytest.approx(2 * 20.0**2 / 400.0, rel=1e-4)


def test_dead_volume_and_bypass_variants():
    """Dead (exchanging) volume keeps area 1 and multiplies the dispersion mean by (1 + r)
    (mobile-immobile model, van Genuchten & Wierenga 1976); r = 0 gives the plain model; bypass
    mean = tau_d + f tau_b + (1 - f) tau (1 + 2/Pe) (parallel paths, Levenspiel ch. 12)."""
    a, m, v, _ = _moments(
        T_COARSE, M.axial_dispersion_open_dead_volume(T_COARSE, 11.92, 16.37, 7.67, 0.4, 6.0)
    )
    assert a == pytest.approx(1.0, abs=1e-6)
    mean_ad = 16.37 * (1 + 2 / 7.67)
    assert m == pytest.approx(11.92 + 1.4 * mean_ad, rel=1e-6)
    var_ad = 16.37**2 * (2 / 7.67 + 8 / 7.67**2)
    assert v == pytest.approx(var_ad * 1.4**2 + 2 * 0.4 * 6.0 * mean_ad, rel=1e-5)
    # Pe = 100 takes the Fourier inversion path
    a, m, v, _ = _moments(
        T_COARSE, M.axial_dispersion_open_dead_volume(T_COARSE, 11.92, 16.37, 100.0, 0.4, 6.0)
    )
    mean_ad, var_ad = 16.37 * 1.02, 16.37**2 * (2 / 100 + 8 / 100**2)
    assert a == pytest.approx(1.0, abs=1e-9)
    assert m == pytest.approx(11.92 + 1.4 * mean_ad, rel=1e-9)
    assert v == pytest.approx(var_ad * 1.4**2 + 2 * 0.4 * 6.0 * mean_ad, rel=1e-6)
    t = np.linspace(0, 200, 2001)
    np.testing.assert_allclose(
        M.axial_dispersion_open_dead_volume(t, 11.92, 16.37, 7.67, 0.0, 6.0),
        M.axial_dispersion_open(t, 11.92, 16.37, 7.67),
        atol=1e-10,
    )
    # the bypass path jumps at tau_d: trapezoid error dt/2 * f / tau_b = 5e-5
    a, m, _, _ = _moments(T, M.axial_dispersion_open_bypass(T, 11.92, 16.37, 7.67, 0.1, 2.0))
    assert a == pytest.approx(1.0, abs=1e-4)
    assert m == pytest.approx(11.92 + 0.1 * 2.0 + 0.9 * 16.37 * (1 + 2 / 7.67), rel=1e-4)
    e = M.tanks_in_series_bypass(T, 5.0, 20.0, 3.0, 0.2, 1.0)
    assert trapezoid(e, T) == pytest.approx(1.0, abs=3e-4)  # jump 0.2 / 1 s at dt 2 ms


@pytest.mark.parametrize(
    "name,func,params",
    [
        ("axial_dispersion_open", M.axial_dispersion_open, dict(tau_d=11.92, tau=16.37, pe=7.67)),
        ("axial_dispersion_closed", M.axial_dispersion_closed, dict(tau_d=5.0, tau=16.37, pe=50.0)),
        ("tanks_in_series", M.tanks_in_series, dict(tau_d=5.0, tau=20.0, n=2.5)),
        ("cstr_pfr", M.cstr_pfr, dict(tau_pfr=5.0, tau_cstr=10.0)),
        ("emg", M.emg, dict(mu=30.0, sigma=3.0, tau_e=6.0)),
        (
            "axial_dispersion_open_dead_volume",
            M.axial_dispersion_open_dead_volume,
            dict(tau_d=11.92, tau=16.37, pe=7.67, r_dead=0.3, tau_x=5.0),
        ),
    ],
)
def test_transfer_function_matches_numerical_frequency_response(name, func, params):
    """Closed-form G(i w) equals the quadrature of the model's E(t) (definition of the Laplace
    transform), for w up to 1 rad/s."""
    t = np.linspace(0, 600, 120_001 if name == "cstr_pfr" else 30_001)
    w = np.linspace(0.0, 1.0, 21)
    amp, _, g_num = frequency_response(t, func(t, **params), w)
    g = M.transfer_function(name, 1j * w, **params)
    # E with a jump (cstr_pfr) carries the trapezoid error dt/2 * E(jump) = 2.5e-4
    np.testing.assert_allclose(g_num, g, atol=3e-4)
    assert amp[0] == pytest.approx(1.0, abs=3e-4)


def test_talbot_inverse_of_known_transform():
    """Fixed-Talbot inversion of 1/(s+1)^2 reproduces t exp(-t) (Abate & Valko 2004)."""
    t = np.linspace(0.01, 10, 50)
    np.testing.assert_allclose(
        M.talbot_inverse(lambda s: 1 / (s + 1) ** 2, t), t * np.exp(-t), atol=1e-10
    )


@pytest.mark.parametrize(
    "call,msg",
    [
        (lambda: M.axial_dispersion_open(T, -1.0, 1.0, 1.0), "tau_d must be >= 0, got -1.0"),
        (lambda: M.axial_dispersion_open(T, 1.0, 0.0, 1.0), "tau must be > 0"),
        (lambda: M.axial_dispersion_closed(T, 1.0, 1.0, -2.0), "pe must be > 0"),
        (lambda: M.axial_dispersion_closed(T, 1.0, 1.0, 5000.0), "pe must be <= 1400"),
        (lambda: M.tanks_in_series(T, 0.0, 1.0, 0.0), "n must be > 0"),
        (lambda: M.cstr_pfr(T, 0.0, np.nan), "tau_cstr must be finite"),
        (lambda: M.emg(T, 1.0, -1.0, 1.0), "sigma must be > 0"),
        (lambda: M.zusatz(T, 0.0, 1.0, 0.0), "c must be > 0"),
        (lambda: M.with_bypass(T, T, 1.5, 1.0), "fraction must be <= 1"),
        (lambda: M.axial_dispersion_open([0.0, np.nan], 1.0, 1.0, 1.0), "t must be finite"),
        (lambda: M.get_model("nope"), "model must be one of"),
        (lambda: M.transfer_function("zusatz", 1j), "no closed-form transfer function"),
    ],
)
def test_model_errors(call, msg):
    """Every parameter check raises ValueError naming the field and value."""
    with pytest.raises(ValueError, match=msg.replace("(", r"\(").replace(")", r"\)")):
        call()


def test_ad_open_analytic_jacobian():
    """Analytic derivatives of the open-open model equal central finite differences
    (differentiation of seed Eq. 7 in standard form)."""
    t = np.linspace(0, 100, 200)
    th = np.array([11.92, 16.37, 7.67])
    jac = M.axial_dispersion_open_jac(t, *th)
    h = 1e-6
    num = np.column_stack(
        [
            (
                M.axial_dispersion_open(t, *(th + h * np.eye(3)[i]))
                - M.axial_dispersion_open(t, *(th - h * np.eye(3)[i]))
            )
            / (2 * h)
            for i in range(3)
        ]
    )
    np.testing.assert_allclose(jac, num, atol=1e-9)
