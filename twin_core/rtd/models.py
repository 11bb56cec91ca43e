"""Residence time distribution (RTD) models.

Every model returns the exit-age density E(t) in 1/s on an array of times t (s). Models with a
delay (plug-flow section) return exactly zero for t <= delay. Transfer functions G(s) (Laplace
transforms of E) are given where a closed form exists; they feed the frequency response and the
numerical Laplace inversion used for the closed-closed dispersion model and the dead-volume
variant.

References
----------
- Levenspiel, O. (1999) Chemical Reaction Engineering, 3rd ed., ch. 13-14 (dispersion, tanks).
- Danckwerts, P.V. (1953) Chem. Eng. Sci. 2, 1-13 (closed-vessel boundary conditions).
- van der Laan, E.T. (1958) Chem. Eng. Sci. 7, 187 (moments of the closed-closed model).
- Poulesquen, A., Vergnes, B. et al. (2003) Polym. Eng. Sci. 43, 1849 (Zusatz model).
- Grushka, E. (1972) Anal. Chem. 44, 1733 (exponentially modified Gaussian).
- Abate, J., Valko, P. (2004) Int. J. Numer. Meth. Eng. 60, 979 (fixed Talbot inversion).
- van Genuchten, M.T., Wierenga, P.J. (1976) Soil Sci. Soc. Am. J. 40, 473 (mobile-immobile
  exchange, the dead-volume variant).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special

__all__ = [
    "axial_dispersion_open",
    "axial_dispersion_open_jac",
    "axial_dispersion_closed",
    "tanks_in_series",
    "cstr_pfr",
    "cstr",
    "convection",
    "plug_flow_dispersion_high_pe",
    "emg",
    "zusatz",
    "axial_dispersion_open_dead_volume",
    "with_bypass",
    "axial_dispersion_open_bypass",
    "tanks_in_series_bypass",
    "transfer_function",
    "talbot_inverse",
    "fourier_inverse",
    "ModelSpec",
    "MODELS",
    "E_FUNCTIONS",
    "get_model",
    "model_e",
    "DELAYS",
    "TIME_CONSTANTS",
    "TIME_CONSTANT_MAX_RECORDS",
    "TIME_CONSTANT_MIN_STEPS",
    "record_bounds",
]


def _as_t(t: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(t, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise ValueError("t must be finite, got non-finite values")
    return arr


def _check(name: str, value: float, *, lo: float = 0.0, strict: bool = True) -> float:
    v = float(value)
    if not np.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if strict and v <= lo:
        raise ValueError(f"{name} must be > {lo:g}, got {value!r}")
    if not strict and v < lo:
        raise ValueError(f"{name} must be >= {lo:g}, got {value!r}")
    return v


# --------------------------------------------------------------------------------------------
# Numerical Laplace inversion
# --------------------------------------------------------------------------------------------


def talbot_inverse(
    transfer: Callable[[NDArray[np.complex128]], NDArray[np.complex128]],
    t: ArrayLike,
    m: int = 24,
) -> NDArray[np.float64]:
    """Invert a Laplace transform G(s) numerically at times t > 0 (fixed Talbot method).

    f(t) ~ (r/M) [ G(r) e^{rt}/2 + sum_{k=1}^{M-1} Re( e^{t s_k} G(s_k) (1 + i sigma_k) ) ],
    s_k = r theta_k (cot theta_k + i), theta_k = k pi / M, r = 2M/(5t),
    sigma_k = theta_k + (theta_k cot theta_k - 1) cot theta_k (Abate & Valko 2004).
    Returns 0 where t <= 0. ``transfer`` must accept complex arrays of any shape.
    """
    tt = _as_t(t)
    out = np.zeros(tt.shape, dtype=float)
    pos = tt > 0
    if not np.any(pos):
        return out
    tp = tt[pos].ravel()
    theta = np.arange(1, m) * np.pi / m
    cot = 1.0 / np.tan(theta)
    r = 2.0 * m / (5.0 * tp)  # (nt,)
    s = r[:, None] * theta[None, :] * (cot[None, :] + 1j)  # (nt, m-1)
    sigma = theta + (theta * cot - 1.0) * cot
    g = transfer(s)
    terms = np.real(np.exp(tp[:, None] * s) * g * (1.0 + 1j * sigma[None, :]))
    g0 = np.real(transfer(r.astype(complex)))
    val = (r / m) * (0.5 * g0 * np.exp(r * tp) + terms.sum(axis=1))
    out[pos] = val
    return out


def fourier_inverse(
    transfer: Callable[[NDArray[np.complex128]], NDArray[np.complex128]],
    t: ArrayLike,
    t_end: float,
    tol: float = 1e-15,
) -> NDArray[np.float64]:
    """Invert the Laplace transform G(s) of a causal density supported (to within tol) on
    [0, t_end], by the trapezoid rule on the Bromwich line Re(s) = 0:

    E(t) ~ (dw/pi) [G(0)/2 + sum_{k>=1} Re(G(i k dw) exp(i k dw t))],  dw = 2 pi / (2 t_end).

    By Poisson summation the error is the periodic wrap-around sum_m E(t + 2 m t_end), i.e.
    the mass beyond t_end; the sum stops where |G(i w)| < tol. Returns 0 outside (0, t_end].
    Used where Talbot inversion loses precision (sharp, nearly delayed responses, large Pe).
    """
    tt = _as_t(t)
    out = np.zeros(tt.shape, dtype=float)
    period = 2.0 * t_end
    dw = 2.0 * np.pi / period
    # find the cut-off frequency on a geometric grid
    w = dw * np.geomspace(1.0, 1e7, 400)
    mag = np.abs(transfer(1j * w))
    above = np.nonzero(mag > tol)[0]
    w_max = w[min(above[-1] + 1, len(w) - 1)] if above.size else dw
    nk = int(np.ceil(w_max / dw))
    if nk > 200_000:
        raise ValueError(f"fourier inversion needs too many terms ({nk}); t_end={t_end!r}")
    k = np.arange(1, nk + 1)
    g = transfer(1j * dw * k)
    g0 = float(np.real(transfer(np.array([0.0 + 0.0j]))[0]))
    m = (tt > 0) & (tt <= t_end)
    tm = tt[m].ravel()
    val = np.empty(tm.shape)
    chunk = max(1, 4_000_000 // max(nk, 1))
    for i in range(0, tm.size, chunk):
        ph = np.exp(1j * dw * np.outer(tm[i : i + chunk], k))
        val[i : i + chunk] = (dw / np.pi) * (0.5 * g0 + np.real(ph @ g))
    out[m] = val
    return out


# --------------------------------------------------------------------------------------------
# Core models (cross-area contract)
# --------------------------------------------------------------------------------------------


def axial_dispersion_open(t: ArrayLike, tau_d: float, tau: float, pe: float) -> NDArray:
    """Axial dispersion with plug-flow delay, open-open boundaries (seed Eq. 7, corrected).

    E(t) = sqrt(Pe / (4 pi s tau)) exp(-Pe (tau - s)^2 / (4 tau s)),  s = t - tau_d > 0,
    E(t) = 0 for t <= tau_d.

    The seed's Eq. (7) is garbled in transcription; this is the standard form
    (Levenspiel 1999 Eq. 13.19 in dimensional time). Moments: mean = tau_d + tau (1 + 2/Pe),
    variance = tau^2 (2/Pe + 8/Pe^2). Transfer function G(s) = exp(Pe (1 - q) / 2) / q,
    q = sqrt(1 + 4 s tau / Pe).
    """
    tt = _as_t(t)
    tau_d = _check("tau_d", tau_d, strict=False)
    tau = _check("tau", tau)
    pe = _check("pe", pe)
    s = tt - tau_d
    out = np.zeros_like(tt)
    m = s > 0
    sp = s[m]
    out[m] = np.sqrt(pe / (4.0 * np.pi * sp * tau)) * np.exp(
        -pe * (tau - sp) ** 2 / (4.0 * tau * sp)
    )
    return out


def _g_ad_closed(s: NDArray, tau: float, pe: float) -> NDArray:
    q = np.sqrt(1.0 + 4.0 * s * tau / pe)
    return (
        4.0 * q * np.exp(0.5 * pe * (1.0 - q)) / ((1.0 + q) ** 2 - (1.0 - q) ** 2 * np.exp(-q * pe))
    )


def axial_dispersion_closed(t: ArrayLike, tau_d: float, tau: float, pe: float) -> NDArray:
    """Axial dispersion with plug-flow delay, closed-closed (Danckwerts) boundaries.

    No closed form in time; E is the inverse Laplace transform of
    G(s) = 4 q exp(Pe/2) / ((1+q)^2 exp(q Pe/2) - (1-q)^2 exp(-q Pe/2)), q = sqrt(1 + 4 s tau/Pe)
    (Danckwerts 1953), evaluated at s = t - tau_d with the fixed Talbot method (written in the
    overflow-free form 4 q exp(Pe (1-q)/2) / ((1+q)^2 - (1-q)^2 exp(-q Pe))).
    Moments (van der Laan 1958): mean = tau_d + tau,
    variance = tau^2 (2/Pe - 2/Pe^2 (1 - exp(-Pe))).
    """
    tt = _as_t(t)
    tau_d = _check("tau_d", tau_d, strict=False)
    tau = _check("tau", tau)
    pe = _check("pe", pe)
    if pe > 1400:
        raise ValueError(f"pe must be <= 1400 for the closed-closed model, got {pe!r}")
    out = _invert(lambda s: _g_ad_closed(s, tau, pe), tt - tau_d, pe, tau, tau * np.sqrt(2 / pe))
    return np.maximum(out, 0.0)


def _invert(g: Callable, s: NDArray, pe: float, mean: float, std: float) -> NDArray:
    """Talbot for Pe <= 30 (smooth, broad responses); Fourier on a finite support above,
    where the response is sharp and Talbot's contour sums cancel catastrophically."""
    if pe <= 30.0:
        return talbot_inverse(g, s)
    return fourier_inverse(g, s, t_end=mean + 40.0 * std)


def tanks_in_series(t: ArrayLike, tau_d: float, tau: float, n: float) -> NDArray:
    """Tanks in series with delay, real n > 0 (gamma distribution).

    E(t) = s^(n-1) / (Gamma(n) (tau/n)^n) exp(-n s / tau),  s = t - tau_d > 0,
    tau = total mean residence time of the tanks (Levenspiel 1999 Eq. 14.3).
    Moments: mean = tau_d + tau, variance = tau^2 / n, skewness = 2 / sqrt(n).
    G(s) = exp(-s tau_d) (1 + s tau / n)^(-n).
    """
    tt = _as_t(t)
    tau_d = _check("tau_d", tau_d, strict=False)
    tau = _check("tau", tau)
    n = _check("n", n)
    s = tt - tau_d
    out = np.zeros_like(tt)
    m = s > 0
    theta = tau / n
    sp = s[m]
    logpdf = (n - 1.0) * np.log(sp) - sp / theta - special.gammaln(n) - n * np.log(theta)
    out[m] = np.exp(logpdf)
    if n == 1.0:
        out[s == 0] = 1.0 / theta  # the exponential's value at the jump
    return out


def cstr_pfr(t: ArrayLike, tau_pfr: float, tau_cstr: float) -> NDArray:
    """Plug-flow reactor in series with a CSTR.

    E(t) = exp(-(t - tau_pfr) / tau_cstr) / tau_cstr for t >= tau_pfr, 0 for t < tau_pfr
    (Levenspiel 1999 ch. 12). Mean tau_pfr + tau_cstr, variance tau_cstr^2.
    G(s) = exp(-s tau_pfr) / (1 + s tau_cstr).
    """
    tt = _as_t(t)
    tau_pfr = _check("tau_pfr", tau_pfr, strict=False)
    tau_cstr = _check("tau_cstr", tau_cstr)
    s = tt - tau_pfr
    out = np.zeros_like(tt)
    m = s >= 0
    out[m] = np.exp(-s[m] / tau_cstr) / tau_cstr
    return out


# --------------------------------------------------------------------------------------------
# Further models
# --------------------------------------------------------------------------------------------


def cstr(t: ArrayLike, tau: float) -> NDArray:
    """Single ideal CSTR, E(t) = exp(-t/tau)/tau for t > 0 (Levenspiel 1999 ch. 11)."""
    return cstr_pfr(t, 0.0, tau)


def convection(t: ArrayLike, tau: float) -> NDArray:
    """Pure convection in laminar pipe flow (no diffusion), as rtdpy's Convection model.

    E(t) = tau^2 / (2 t^3) for t >= tau/2, 0 before (Levenspiel 1999 Eq. 15.3). Mean tau; the
    variance is infinite (the tail decays as t^-3).
    """
    tt = _as_t(t)
    tau = _check("tau", tau)
    out = np.zeros_like(tt)
    m = tt >= tau / 2
    out[m] = tau**2 / (2 * tt[m] ** 3)
    return out


def plug_flow_dispersion_high_pe(t: ArrayLike, tau_d: float, tau: float, pe: float) -> NDArray:
    """Small-dispersion (Gaussian) limit of the dispersion model, with delay.

    E(t) = sqrt(Pe / (4 pi)) / tau exp(-Pe (1 - s/tau)^2 / 4), s = t - tau_d > 0
    (Levenspiel 1999 Eq. 13.8, valid for Pe > ~100). Mean tau_d + tau, variance 2 tau^2 / Pe.
    """
    tt = _as_t(t)
    tau_d = _check("tau_d", tau_d, strict=False)
    tau = _check("tau", tau)
    pe = _check("pe", pe)
    s = tt - tau_d
    out = np.zeros_like(tt)
    m = s > 0
    out[m] = np.sqrt(pe / (4 * np.pi)) / tau * np.exp(-pe * (1 - s[m] / tau) ** 2 / 4)
    return out


def emg(t: ArrayLike, mu: float, sigma: float, tau_e: float) -> NDArray:
    """Exponentially modified Gaussian (Gaussian mu, sigma convolved with exp. decay tau_e).

    E(t) = (1/(2 tau_e)) exp(sigma^2/(2 tau_e^2) - (t-mu)/tau_e)
           erfc((sigma/tau_e - (t-mu)/sigma)/sqrt(2))   (Grushka 1972),
    evaluated stably with scipy.stats.exponnorm. Defined for all t (not truncated at 0).
    Mean mu + tau_e, variance sigma^2 + tau_e^2, G(s) = exp(-mu s + sigma^2 s^2/2)/(1 + s tau_e).
    """
    from scipy.stats import exponnorm

    tt = _as_t(t)
    mu = _check("mu", mu, lo=-np.inf)
    sigma = _check("sigma", sigma)
    tau_e = _check("tau_e", tau_e)
    return exponnorm.pdf(tt, tau_e / sigma, loc=mu, scale=sigma)


def zusatz(t: ArrayLike, tau_d: float, b: float, c: float) -> NDArray:
    """Zusatz model with delay (Poulesquen et al. 2003; as in rtdpy).

    E(t) = a s^(-c-1) b^(c+1) exp(-(c+1)/c ((b/s)^c - 1)),  a = (1+c) / (b exp(1 + 1/c)),
    s = t - tau_d > 0. With u = (b/s)^c ~ Exponential(rate (c+1)/c), the mean is
    tau_d + b ((c+1)/c)^(1/c) Gamma(1 - 1/c) for c > 1; the mode is at s = b.
    """
    tt = _as_t(t)
    tau_d = _check("tau_d", tau_d, strict=False)
    b = _check("b", b)
    c = _check("c", c)
    s = tt - tau_d
    out = np.zeros_like(tt)
    m = s > 0
    sp = s[m]
    k = (c + 1.0) / c
    u = (b / sp) ** c
    # log E = log(k c / b) + (c+1) log(b/s) - k u ... with a b^(c+1) s^(-c-1) e^{k}
    log_e = np.log(c + 1.0) - np.log(b) - k + (c + 1.0) * np.log(b / sp) - k * (u - 1.0)
    out[m] = np.exp(log_e)
    return out


def _g_ad_open(s: NDArray, tau: float, pe: float) -> NDArray:
    q = np.sqrt(1.0 + 4.0 * s * tau / pe)
    return np.exp(0.5 * pe * (1.0 - q)) / q


def axial_dispersion_open_dead_volume(
    t: ArrayLike, tau_d: float, tau: float, pe: float, r_dead: float, tau_x: float
) -> NDArray:
    """Open-open axial dispersion with a stagnant, exchanging (dead) volume, with delay.

    The flowing zone exchanges with a stagnant zone of volume ratio r_dead = V_dead/V_flow and
    exchange time constant tau_x (first-order, dC_dead/dt = (C - C_dead)/tau_x). In Laplace
    space the flowing-zone balance has s replaced by s' = s (1 + r_dead / (1 + s tau_x))
    (mobile-immobile model, van Genuchten & Wierenga 1976), so G(s) = G_AD,open(s'); E is
    obtained by fixed Talbot inversion. Mean = tau_d + (1 + r_dead) tau (1 + 2/Pe).
    Variance = tau^2 (2/Pe + 8/Pe^2) (1 + r_dead)^2 + 2 r_dead tau_x tau (1 + 2/Pe) (cumulants
    of G). r_dead = 0 reduces to :func:`axial_dispersion_open`.
    """
    tt = _as_t(t)
    tau_d = _check("tau_d", tau_d, strict=False)
    tau = _check("tau", tau)
    pe = _check("pe", pe)
    r_dead = _check("r_dead", r_dead, strict=False)
    tau_x = _check("tau_x", tau_x)

    def g(s: NDArray) -> NDArray:
        return _g_ad_open(s * (1.0 + r_dead / (1.0 + s * tau_x)), tau, pe)

    mean = (1.0 + r_dead) * tau * (1.0 + 2.0 / pe)
    # cumulants of G_AD(s (1 + r/(1 + s tau_x))): var = var_AD (1+r)^2 + 2 r tau_x mean_AD
    var = tau**2 * (2 / pe + 8 / pe**2) * (1 + r_dead) ** 2 + 2 * r_dead * tau_x * tau * (
        1 + 2 / pe
    )
    return np.maximum(_invert(g, tt - tau_d, pe, mean, float(np.sqrt(var))), 0.0)


def with_bypass(
    t: ArrayLike, e_main: ArrayLike, fraction: float, tau_bypass: float, tau_d: float = 0.0
) -> NDArray:
    """Parallel bypass: a fraction of the flow short-circuits through a small well-mixed path.

    E(t) = f E_cstr(t - tau_d; tau_bypass) + (1 - f) E_main(t) (Levenspiel 1999 ch. 12,
    parallel flow paths; a Dirac bypass is the limit tau_bypass -> 0).
    """
    f = _check("fraction", fraction, strict=False)
    if f > 1:
        raise ValueError(f"fraction must be <= 1, got {fraction!r}")
    return f * cstr_pfr(t, tau_d, tau_bypass) + (1.0 - f) * np.asarray(e_main, dtype=float)


def axial_dispersion_open_bypass(
    t: ArrayLike, tau_d: float, tau: float, pe: float, fraction: float, tau_bypass: float
) -> NDArray:
    """Open-open axial dispersion with delay plus a bypass fraction (see :func:`with_bypass`).

    Mean = tau_d + f tau_bypass + (1 - f) tau (1 + 2/Pe).
    """
    return with_bypass(t, axial_dispersion_open(t, tau_d, tau, pe), fraction, tau_bypass, tau_d)


def tanks_in_series_bypass(
    t: ArrayLike, tau_d: float, tau: float, n: float, fraction: float, tau_bypass: float
) -> NDArray:
    """Tanks in series with delay plus a bypass fraction (see :func:`with_bypass`)."""
    return with_bypass(t, tanks_in_series(t, tau_d, tau, n), fraction, tau_bypass, tau_d)


# --------------------------------------------------------------------------------------------
# Transfer functions
# --------------------------------------------------------------------------------------------


def transfer_function(model: str, s: ArrayLike, **params: float) -> NDArray[np.complex128]:
    """Closed-form Laplace transform G(s) = int_0^inf E(t) exp(-s t) dt of a named model.

    Frequency response: G(i omega). Supported: axial_dispersion_open, axial_dispersion_closed,
    tanks_in_series, cstr_pfr, cstr, emg, axial_dispersion_open_dead_volume,
    axial_dispersion_open_bypass, tanks_in_series_bypass. For other models (or measured E)
    use :func:`twin_core.rtd.convolution.frequency_response`.
    """
    sc = np.asarray(s, dtype=complex)
    p = params
    if model in ("axial_dispersion_open", "axial_dispersion_closed"):
        fn = _g_ad_open if model.endswith("open") else _g_ad_closed
        return np.exp(-sc * p["tau_d"]) * fn(sc, p["tau"], p["pe"])
    if model == "tanks_in_series":
        return np.exp(-sc * p["tau_d"]) * (1.0 + sc * p["tau"] / p["n"]) ** (-p["n"])
    if model == "cstr_pfr":
        return np.exp(-sc * p["tau_pfr"]) / (1.0 + sc * p["tau_cstr"])
    if model == "cstr":
        return 1.0 / (1.0 + sc * p["tau"])
    if model == "emg":
        return np.exp(-p["mu"] * sc + 0.5 * p["sigma"] ** 2 * sc**2) / (1.0 + sc * p["tau_e"])
    if model == "axial_dispersion_open_dead_volume":
        s2 = sc * (1.0 + p["r_dead"] / (1.0 + sc * p["tau_x"]))
        return np.exp(-sc * p["tau_d"]) * _g_ad_open(s2, p["tau"], p["pe"])
    if model in ("axial_dispersion_open_bypass", "tanks_in_series_bypass"):
        f = p["fraction"]
        by = np.exp(-sc * p["tau_d"]) / (1.0 + sc * p["tau_bypass"])
        inner = "axial_dispersion_open" if model.startswith("axial") else "tanks_in_series"
        keys = ("tau_d", "tau", "pe") if inner == "axial_dispersion_open" else ("tau_d", "tau", "n")
        main = transfer_function(inner, sc, **{k: p[k] for k in keys})
        return f * by + (1.0 - f) * main
    raise ValueError(f"model has no closed-form transfer function: {model!r}")


# --------------------------------------------------------------------------------------------
# Registry used by fitting and the CLI
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ModelSpec:
    """A fittable model: function, parameter names, bounds and an initial-guess rule."""

    name: str
    func: Callable[..., NDArray]
    params: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    guess: Callable[[float, float, float], tuple | list[tuple]] = field(repr=False)
    """guess(t_first, mean, std) from the profile's moments -> initial parameter vector, or a
    list of them (multi-start; the fit keeps the lowest residual)."""
    jac: Callable[..., NDArray] | None = field(default=None, repr=False)
    """Optional analytic Jacobian jac(t, *theta) -> (len(t), len(params))."""

    def __call__(self, t: ArrayLike, *theta: float) -> NDArray:
        return self.func(t, *theta)


def axial_dispersion_open_jac(t: ArrayLike, tau_d: float, tau: float, pe: float) -> NDArray:
    """Analytic derivatives of :func:`axial_dispersion_open` w.r.t. (tau_d, tau, pe), s = t - tau_d:
    d ln E/d pe = 1/(2 pe) - (tau - s)^2 / (4 tau s),
    d ln E/d tau = -1/(2 tau) - pe (tau^2 - s^2) / (4 s tau^2),
    d ln E/d tau_d = 1/(2 s) - pe (tau^2 - s^2) / (4 tau s^2); all zero for s <= 0."""
    tt = _as_t(t)
    e = axial_dispersion_open(tt, tau_d, tau, pe)
    s = tt - tau_d
    out = np.zeros((tt.size, 3))
    m = s > 0
    sp = s[m]
    d2 = tau**2 - sp**2
    out[m, 0] = e[m] * (0.5 / sp - pe * d2 / (4 * tau * sp**2))
    out[m, 1] = e[m] * (-0.5 / tau - pe * d2 / (4 * sp * tau**2))
    out[m, 2] = e[m] * (0.5 / pe - (tau - sp) ** 2 / (4 * tau * sp))
    return out


def _g_ad(t0: float, mean: float, std: float) -> tuple[float, ...]:
    # moments of the open-open model: var = tau^2 (2/Pe + 8/Pe^2), mean = tau_d + tau (1+2/Pe)
    tau_d = max(0.0, min(t0, mean - 2.0 * std))
    rest = max(mean - tau_d, 1e-3)
    cv2 = (std / rest) ** 2
    pe = float(np.clip(2.0 / max(cv2, 1e-3), 0.5, 500.0))
    tau = rest / (1.0 + 2.0 / pe)
    return (tau_d, tau, pe)


def _g_tis(t0: float, mean: float, std: float) -> tuple[float, ...]:
    tau_d = max(0.0, min(t0, mean - 2.0 * std))
    rest = max(mean - tau_d, 1e-3)
    n = float(np.clip((rest / max(std, 1e-9)) ** 2, 0.3, 200.0))
    return (tau_d, rest, n)


def _g_cp(t0: float, mean: float, std: float) -> tuple[float, ...]:
    tc = max(min(std, mean), 1e-3)
    return (max(mean - tc, 0.0), tc)


def _g_emg(t0: float, mean: float, std: float) -> tuple[float, ...]:
    return (mean - 0.5 * std, 0.7 * std, 0.5 * std)


def _g_zus(t0: float, mean: float, std: float) -> list[tuple[float, ...]]:
    out = []
    for tau_d in {max(0.0, min(t0, mean - 2.0 * std)), 0.9 * t0}:
        out += [(tau_d, max(0.7 * (mean - tau_d), 1e-3), c) for c in (1.5, 4.0)]
    return out


def _g_dead(t0: float, mean: float, std: float) -> list[tuple[float, ...]]:
    tau_d, tau, pe = _g_ad(t0, mean, std)
    return [(tau_d, tau * 0.9, pe, r, max(k * std, 1e-3)) for r in (0.1, 0.5) for k in (0.3, 2.0)]


def _g_adb(t0: float, mean: float, std: float) -> list[tuple[float, ...]]:
    # the bypass jumps at tau_d, so also start with tau_d at the onset of the profile
    out = []
    for td in {_g_ad(t0, mean, std)[0], 0.95 * t0}:
        _, tau, pe = _g_ad(td, mean, std)
        out += [(td, tau, pe, f, max(k * std, 1e-3)) for f in (0.05, 0.2) for k in (0.1, 0.5)]
    return out


def _g_tisb(t0: float, mean: float, std: float) -> list[tuple[float, ...]]:
    out = []
    for td in {_g_tis(t0, mean, std)[0], 0.95 * t0}:
        _, tau, n = _g_tis(td, mean, std)
        out += [(td, tau, n, f, max(k * std, 1e-3)) for f in (0.05, 0.2) for k in (0.1, 0.5)]
    return out


_INF = np.inf
MODELS: dict[str, ModelSpec] = {
    "ad_open": ModelSpec(
        "ad_open",
        axial_dispersion_open,
        ("tau_d", "tau", "pe"),
        (0, 1e-6, 1e-3),
        (_INF,) * 3,
        _g_ad,
    ),
    "ad_closed": ModelSpec(
        "ad_closed",
        axial_dispersion_closed,
        ("tau_d", "tau", "pe"),
        (0, 1e-6, 1e-3),
        (_INF, _INF, 1400.0),
        _g_ad,
    ),
    "tis": ModelSpec(
        "tis", tanks_in_series, ("tau_d", "tau", "n"), (0, 1e-6, 1e-2), (_INF, _INF, 1e4), _g_tis
    ),
    "cstr_pfr": ModelSpec(
        "cstr_pfr", cstr_pfr, ("tau_pfr", "tau_cstr"), (0, 1e-6), (_INF,) * 2, _g_cp
    ),
    "emg": ModelSpec(
        "emg", emg, ("mu", "sigma", "tau_e"), (-_INF, 1e-6, 1e-6), (_INF,) * 3, _g_emg
    ),
    "zusatz": ModelSpec(
        "zusatz", zusatz, ("tau_d", "b", "c"), (0, 1e-6, 0.05), (_INF,) * 3, _g_zus
    ),
    "ad_open_dead": ModelSpec(
        "ad_open_dead",
        axial_dispersion_open_dead_volume,
        ("tau_d", "tau", "pe", "r_dead", "tau_x"),
        (0, 1e-6, 1e-3, 0.0, 1e-3),
        (_INF, _INF, _INF, 10.0, _INF),
        _g_dead,
    ),
    "ad_open_bypass": ModelSpec(
        "ad_open_bypass",
        axial_dispersion_open_bypass,
        ("tau_d", "tau", "pe", "fraction", "tau_bypass"),
        (0, 1e-6, 1e-3, 0.0, 1e-3),
        (_INF, _INF, _INF, 1.0, _INF),
        _g_adb,
    ),
    "tis_bypass": ModelSpec(
        "tis_bypass",
        tanks_in_series_bypass,
        ("tau_d", "tau", "n", "fraction", "tau_bypass"),
        (0, 1e-6, 1e-2, 0.0, 1e-3),
        (_INF, _INF, 1e4, 1.0, _INF),
        _g_tisb,
    ),
}

#: parameters that place the response in time (a plug-flow delay, the Gaussian's centre)
DELAYS = frozenset({"tau_d", "tau_pfr", "mu"})
#: parameters that are time constants or time scales of the response
TIME_CONSTANTS = frozenset({"tau", "tau_cstr", "sigma", "tau_e", "b", "tau_x", "tau_bypass"})
#: a time constant is identified by a record of length T sampled at dt between
#: TIME_CONSTANT_MIN_STEPS dt and TIME_CONSTANT_MAX_RECORDS T
TIME_CONSTANT_MAX_RECORDS = 2.0
TIME_CONSTANT_MIN_STEPS = 0.5


def record_bounds(spec: ModelSpec, t: ArrayLike) -> tuple[NDArray, NDArray]:
    """(lower, upper) of ``spec``'s parameters as far as a record on the times ``t`` (length
    T = t_end - t_0, step dt) can identify them: a time constant within
    [``TIME_CONSTANT_MIN_STEPS`` dt, ``TIME_CONSTANT_MAX_RECORDS`` T] (below half a step it
    shapes a single sample; a decay slower than twice the record length is not seen to end,
    and a profile is accepted only once it is back at its baseline), a delay within
    [t_0 - T, t_end] (no later than the record's end); dimensionless parameters (Pe, n, c,
    fractions, volume ratios) keep the model's own bounds. Each bound is the tighter of the
    model's and the record's."""
    tt = np.asarray(t, dtype=float)
    if tt.ndim != 1 or tt.size < 2:
        raise ValueError(f"t must be 1-D with >= 2 samples, got shape {tt.shape}")
    length = float(tt[-1] - tt[0])
    step = float(np.median(np.diff(tt)))
    if not (length > 0 and step > 0):
        raise ValueError(f"t must increase, got {tt[0]!r} .. {tt[-1]!r}")
    lo = np.array(spec.lower, dtype=float)
    hi = np.array(spec.upper, dtype=float)
    for i, name in enumerate(spec.params):
        if name in TIME_CONSTANTS:
            lo[i] = max(lo[i], TIME_CONSTANT_MIN_STEPS * step)
            hi[i] = min(hi[i], TIME_CONSTANT_MAX_RECORDS * length)
        elif name in DELAYS:
            lo[i] = max(lo[i], float(tt[0]) - length)
            hi[i] = min(hi[i], float(tt[-1]))
    return lo, hi


_ALIASES = {
    "axial_dispersion_open": "ad_open",
    "ad": "ad_open",
    "axial_dispersion_closed": "ad_closed",
    "tanks_in_series": "tis",
    "emg": "emg",
}


def get_model(name: str) -> ModelSpec:
    """Look a fittable model up by name (``ad_open``, ``ad_closed``, ``tis``, ``cstr_pfr``,
    ``emg``, ``zusatz``, ``ad_open_dead``, ``ad_open_bypass``, ``tis_bypass``; long names of the
    functions are accepted as aliases)."""
    key = _ALIASES.get(name, name)
    if key not in MODELS:
        raise ValueError(f"model must be one of {sorted(MODELS)}, got {name!r}")
    return MODELS[key]


#: the E(t) functions a configuration or a wire message may name (``LineSpec.blender.model``,
#: ``RtdEstimate.model``), by function name
E_FUNCTIONS: dict[str, Callable[..., NDArray]] = {
    f.__name__: f
    for f in (
        axial_dispersion_open,
        axial_dispersion_closed,
        tanks_in_series,
        cstr_pfr,
        cstr,
        convection,
        plug_flow_dispersion_high_pe,
        emg,
        zusatz,
        axial_dispersion_open_dead_volume,
        axial_dispersion_open_bypass,
        tanks_in_series_bypass,
    )
}


def model_e(model: str, params: Mapping[str, float], t: ArrayLike) -> NDArray[np.float64]:
    """E(t) (1/s) of the RTD model named ``model`` with parameters ``params`` on the times ``t``.

    The one builder of a named model's E(t): the declared line model
    (``twin_core.plant.model.rtd_kernel``), the live blender prediction and the diverter's
    funnel and lot boundaries (``twin_core.online.blender.BlenderKernel``) all evaluate E(t)
    here. ``model`` is a function name of this module (:data:`E_FUNCTIONS`, e.g.
    ``axial_dispersion_open``: Levenspiel 1999 Eq. 13.19 with a plug-flow delay); ``params`` are
    its keyword arguments in SI units.
    """
    fn = E_FUNCTIONS.get(model)
    if fn is None:
        raise ValueError(f"model must be one of {sorted(E_FUNCTIONS)}, got {model!r}")
    return np.asarray(fn(t, **params), dtype=float)
