"""Whole blender from a periodic section: RTD, outlet prediction, RSD along the axis.

* n sections in series (seed 5.3.4, default 8): E_blender = E_section^{*n} (Eq. 8-9), computed
  on a fine internal grid by FFT convolution, or by chaining the section networks
  (:func:`~twin_core.compartment.network.chain_sections`); both agree.
* Outlet prediction for a piecewise-constant (zero-order hold) inlet concentration u_j on
  [t_j, t_j+1): y(t_k) = c_init (1 - F(t_k)) + sum_{j<k} u_j [F(t_k - t_j) - F(t_k - t_j+1)],
  exact for a linear time-invariant vessel with cumulative RTD F (Levenspiel ch. 11).
* Dynamic runs with flows scaled by s(t) (rpm or throughput relative to the basis, holdup
  fixed): dm/dt = s(t) A m is the basis system in the warped time theta = int s dt
  (Nauman, *Chemical Reactor Design*, 2008, ch. 15: time-varying flow through a vessel of
  constant volume), so the outlet is the basis response evaluated at theta(t).
* RSD along the blender, Eq. (10) in the time-of-flight form of Gao et al. (2011, Chem. Eng.
  Sci. 66, 417): RSD^2(t) = RSD_ss^2 + (RSD_0^2 - RSD_ss^2) exp(-k_b t), t = x / v_x.  The seed
  prints exp(-k_b v_x x), which is not dimensionless for k_b in 1/s; see
  :func:`blender_rsd_profile`.
"""

from __future__ import annotations

import math

import numpy as np

from twin_core.compartment.network import (
    CompartmentNetwork,
    _propagate,
    convolve_power,
    fftconvolve,
    section_tau,
)


def _fine_grid(section: CompartmentNetwork, dt: float, points_per_tau: int) -> tuple[float, int]:
    tau = section_tau(section)
    r = max(1, math.ceil(dt * points_per_tau / tau))
    return dt / r, r


def blender_rtd(
    section: CompartmentNetwork,
    n_sections: int,
    t: np.ndarray,
    points_per_tau: int = 100,
) -> np.ndarray:
    """E(t) (1/s) of ``n_sections`` open sections in series on a uniform grid t (from 0).

    The section E is exact at the points of an internal grid with at least
    ``points_per_tau`` points per section mean residence time; the n-fold convolution uses
    the trapezoid rule (error O(dt_fine^2)).
    """
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.size < 2:
        raise ValueError("t must be a 1-D grid with >= 2 points")
    dt = float(t[1] - t[0])
    if abs(t[0]) > 1e-12 * dt:
        raise ValueError(f"t must start at 0, got {t[0]}")
    dtf, r = _fine_grid(section, dt, points_per_tau)
    tf = np.arange((t.size - 1) * r + 1) * dtf
    e_sec, _ = _propagate(section, tf, section.impulse_state())
    e = convolve_power(e_sec, n_sections, dtf)
    return e[::r][: t.size]


def blender_cdf_increments(
    section: CompartmentNetwork,
    n_sections: int,
    dt: float,
    n_steps: int,
    points_per_tau: int = 100,
    tail: float = 1e-9,
) -> np.ndarray:
    """F(k dt) of the whole blender for k = 0..K (K <= n_steps, cut once 1 - F < ``tail``)."""
    tau = section_tau(section) * n_sections
    dtf, r = _fine_grid(section, dt, points_per_tau)
    horizon = min(n_steps * dt, 12.0 * tau)
    while True:
        kf = int(math.ceil(horizon / dtf)) + 1
        tf = np.arange(kf) * dtf
        e_sec, _ = _propagate(section, tf, section.impulse_state())
        e = convolve_power(e_sec, n_sections, dtf)
        F = np.concatenate([[0.0], np.cumsum(0.5 * (e[1:] + e[:-1])) * dtf])
        if 1.0 - F[-1] < tail or horizon >= n_steps * dt:
            break
        horizon = min(2.0 * horizon, n_steps * dt)
    return np.minimum(F[::r], 1.0)


def predict_outlet(
    section: CompartmentNetwork,
    n_sections: int,
    t: np.ndarray,
    inlet: np.ndarray,
    flow_scale: np.ndarray | None = None,
    initial: float | None = None,
    points_per_tau: int = 100,
    cdf: np.ndarray | None = None,
) -> np.ndarray:
    """Outlet concentration on the uniform grid t for a zero-order-hold inlet signal.

    ``initial`` is the uniform concentration in the blender at t[0] (default inlet[0]: steady
    state).  ``flow_scale`` (len(t), >= 0) scales all flows on [t_j, t_j+1) relative to the
    basis (dynamic rpm/throughput, holdup fixed; module docstring).  ``cdf`` may pass a
    precomputed :func:`blender_cdf_increments` for the grid step.
    """
    t = np.asarray(t, dtype=float)
    u = np.asarray(inlet, dtype=float)
    if t.ndim != 1 or t.size < 2:
        raise ValueError("t must be a 1-D grid with >= 2 points")
    if u.shape != t.shape:
        raise ValueError(f"inlet must have the shape of t {t.shape}, got {u.shape}")
    if not np.all(np.isfinite(u)):
        raise ValueError("inlet must be finite")
    dt = float(t[1] - t[0])
    if dt <= 0 or not np.allclose(np.diff(t), dt, rtol=1e-6, atol=0):
        raise ValueError("t must be uniform and increasing")
    c0 = float(u[0]) if initial is None else float(initial)
    if flow_scale is None:
        F = (
            cdf
            if cdf is not None
            else blender_cdf_increments(section, n_sections, dt, t.size, points_per_tau)
        )
        return _zoh(u, F, c0, t.size)
    s = np.asarray(flow_scale, dtype=float)
    if s.shape != t.shape:
        raise ValueError(f"flow_scale must have the shape of t {t.shape}, got {s.shape}")
    if np.any(s < 0) or not np.all(np.isfinite(s)):
        raise ValueError("flow_scale must be finite and >= 0")
    theta = np.concatenate([[0.0], np.cumsum(s[:-1] * dt)])
    pos = s[s > 0]
    if pos.size == 0:
        return np.full(t.size, c0)
    dth = dt * max(float(pos.min()), float(pos.max()) / 50.0)
    m = int(math.ceil(theta[-1] / dth)) + 2
    th = np.arange(m) * dth
    j = np.clip(np.searchsorted(theta, th, side="right") - 1, 0, t.size - 1)
    F = blender_cdf_increments(section, n_sections, dth, m, points_per_tau)
    y_th = _zoh(u[j], F, c0, m)
    return np.interp(theta, th, y_th)


def _zoh(u: np.ndarray, F: np.ndarray, c0: float, n: int) -> np.ndarray:
    """y_k = c0 (1 - F_k) + sum_{j<k} u_j G_{k-j}, G_m = F_m - F_{m-1} (F padded with its last
    value beyond its length)."""
    if F.size < n:
        F = np.concatenate([F, np.full(n - F.size, F[-1])])
    F = F[:n]
    G = np.diff(F)
    y = np.empty(n)
    y[0] = c0 * (1.0 - F[0])
    y[1:] = c0 * (1.0 - F[1:]) + fftconvolve(u[:-1], G)[: n - 1]
    return y


# ----------------------------------------------------------------------------- RSD, Eq. 10


def rsd_decay(t: np.ndarray, rsd_ss: float, rsd_0: float, k_b: float) -> np.ndarray:
    """RSD(t) = sqrt(RSD_ss^2 + (RSD_0^2 - RSD_ss^2) exp(-k_b t)) (Eq. 10, time form)."""
    return np.sqrt(np.maximum(rsd_ss**2 + (rsd_0**2 - rsd_ss**2) * np.exp(-k_b * t), 0.0))


def fit_rsd_decay(t: np.ndarray, rsd_values: np.ndarray) -> dict[str, float]:
    """Least-squares fit of :func:`rsd_decay` to an RSD(t) profile of the periodic section.

    Returns estimates ``rsd_ss``, ``rsd_0``, ``k_b`` (1/s) with standard errors ``*_se`` from
    the covariance of ``scipy.optimize.curve_fit`` and the residual RMS.
    """
    from scipy.optimize import curve_fit

    t = np.asarray(t, dtype=float)
    y = np.asarray(rsd_values, dtype=float)
    ok = np.isfinite(y)
    if ok.sum() < 4:
        raise ValueError(f"rsd_values needs >= 4 finite points, got {int(ok.sum())}")
    t, y = t[ok], y[ok]
    y0 = float(y[0])
    half = y0 / 2 + float(y[-1]) / 2
    t_half = float(t[np.argmax(y <= half)]) if np.any(y <= half) else float(t[-1])
    k0 = math.log(2.0) / max(t_half - t[0], 1e-9)
    p, cov = curve_fit(
        rsd_decay,
        t,
        y,
        p0=[max(float(y[-1]), 1e-3), y0, k0],
        bounds=([0.0, 0.0, 0.0], [np.inf, np.inf, np.inf]),
        maxfev=20000,
    )
    se = np.sqrt(np.clip(np.diag(cov), 0.0, np.inf))
    resid = y - rsd_decay(t, *p)
    return {
        "rsd_ss": float(p[0]),
        "rsd_0": float(p[1]),
        "k_b": float(p[2]),
        "rsd_ss_se": float(se[0]),
        "rsd_0_se": float(se[1]),
        "k_b_se": float(se[2]),
        "rms": float(np.sqrt(np.mean(resid**2))),
    }


def blender_rsd_profile(
    x: np.ndarray, rsd_ss: float, rsd_0: float, k_b: float, v_x: float
) -> np.ndarray:
    """RSD along the blender axis, Eq. (10): RSD_c^2(x) = RSD_ss^2 + (RSD_0^2 - RSD_ss^2)
    exp(-k_b x / v_x), with k_b (1/s) fitted in time on the periodic section and v_x the mean
    axial velocity (m/s) of the compartment model (time of flight t = x / v_x; the seed's
    printed product k_b v_x x is dimensionally inconsistent)."""
    if v_x <= 0:
        raise ValueError(f"v_x must be > 0, got {v_x}")
    return rsd_decay(np.asarray(x, dtype=float) / v_x, rsd_ss, rsd_0, k_b)
