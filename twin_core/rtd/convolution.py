"""Convolution of signals with RTDs, cumulative distribution F(t), frequency response.

y(t) = int_0^t u(t') E(t - t') dt'  (Levenspiel 1999 Eq. 11.9; seed Eq. 6), evaluated on a
uniform grid by FFT convolution (scipy.signal.fftconvolve) times dt.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.signal import fftconvolve

__all__ = [
    "uniform_dt",
    "convolve",
    "convolve_rtds",
    "cumulative",
    "frequency_response",
    "series",
    "parallel",
]


def uniform_dt(t: ArrayLike, rtol: float = 1e-6) -> float:
    """Return the step of a uniform, increasing time grid; ValueError otherwise."""
    tt = np.asarray(t, dtype=float)
    if tt.ndim != 1 or tt.size < 2:
        raise ValueError(f"t must be a 1-D array with >= 2 points, got shape {tt.shape}")
    if not np.all(np.isfinite(tt)):
        raise ValueError("t must be finite, got NaN or inf")
    d = np.diff(tt)
    dt = float(d.mean())
    if dt <= 0 or np.any(d <= 0):
        raise ValueError("t must be strictly increasing")
    if np.max(np.abs(d - dt)) > rtol * max(abs(dt), 1e-300) + 1e-12 * np.max(np.abs(tt)):
        raise ValueError(f"t must be uniformly spaced, got steps from {d.min():g} to {d.max():g}")
    return dt


def _same(t: NDArray, x: ArrayLike, name: str) -> NDArray:
    arr = np.asarray(x, dtype=float)
    if arr.shape != t.shape:
        raise ValueError(f"{name} must have the shape of t {t.shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got NaN or inf")
    return arr


def convolve(t: ArrayLike, u: ArrayLike, e: ArrayLike) -> NDArray[np.float64]:
    """Outlet signal y on grid t for inlet signal u through a system with RTD e (1/s).

    y[i] = dt * sum_{j<=i} u[j] e[i-j]  (rectangle rule of y(t) = int u(t') E(t-t') dt'),
    with t uniform (t[0] is the time origin of both u and e). FFT-based, O(N log N).
    """
    tt = np.asarray(t, dtype=float)
    dt = uniform_dt(tt)
    uu = _same(tt, u, "u")
    ee = _same(tt, e, "e")
    return fftconvolve(uu, ee)[: tt.size] * dt


def convolve_rtds(t: ArrayLike, e1: ArrayLike, e2: ArrayLike) -> NDArray[np.float64]:
    """RTD of two units in series: E = E1 * E2 (seed Eq. 6), on grid t starting at 0.

    With trapezoid-consistent weighting so that the area is preserved for smooth E.
    """
    tt = np.asarray(t, dtype=float)
    dt = uniform_dt(tt)
    a = _same(tt, e1, "e1")
    b = _same(tt, e2, "e2")
    full = fftconvolve(a, b)[: tt.size] * dt
    # trapezoid correction: subtract half the end-point contributions
    full -= 0.5 * dt * (a[0] * b + b[0] * a)
    return full


def cumulative(t: ArrayLike, e: ArrayLike) -> NDArray[np.float64]:
    """F(t) = int_{t0}^{t} E dt' by the cumulative trapezoid rule (seed Eq. 4); F[0] = 0.

    Works on non-uniform grids. No normalization: F(end) equals the area of e.
    """
    tt = np.asarray(t, dtype=float)
    if tt.ndim != 1 or tt.size < 2:
        raise ValueError(f"t must be a 1-D array with >= 2 points, got shape {tt.shape}")
    if np.any(np.diff(tt) <= 0):
        raise ValueError("t must be strictly increasing")
    ee = _same(tt, e, "e")
    out = np.empty_like(ee)
    out[0] = 0.0
    np.cumsum(0.5 * (ee[1:] + ee[:-1]) * np.diff(tt), out=out[1:])
    return out


def frequency_response(
    t: ArrayLike, e: ArrayLike, omega: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.complex128]]:
    """Frequency response of any sampled RTD: G(i w) = int E(t) exp(-i w t) dt (trapezoid).

    Returns (amplitude ratio |G|, phase in rad (unwrapped), G). Exact for the sampled,
    piecewise-linear E up to quadrature error; compare with the closed forms of
    :func:`twin_core.rtd.models.transfer_function`.
    """
    tt = np.asarray(t, dtype=float)
    if np.any(np.diff(tt) <= 0):
        raise ValueError("t must be strictly increasing")
    ee = _same(tt, e, "e")
    w = np.atleast_1d(np.asarray(omega, dtype=float))
    wts = np.empty_like(tt)
    d = np.diff(tt)
    wts[0] = d[0] / 2
    wts[-1] = d[-1] / 2
    wts[1:-1] = (d[:-1] + d[1:]) / 2
    g = np.empty(w.size, dtype=complex)
    chunk = max(1, 2_000_000 // tt.size)
    for i in range(0, w.size, chunk):
        g[i : i + chunk] = np.exp(-1j * np.outer(w[i : i + chunk], tt)) @ (ee * wts)
    return np.abs(g), np.unwrap(np.angle(g)), g


def series(t: ArrayLike, *es: ArrayLike) -> NDArray[np.float64]:
    """RTD of several units in series, E = E_1 * E_2 * ... (repeated :func:`convolve_rtds`);
    e.g. a Zusatz-style combination of a PFR, tanks and dispersion (rtdpy "combinations")."""
    if len(es) < 1:
        raise ValueError("es must hold at least one RTD, got none")
    out = np.asarray(es[0], dtype=float)
    for e in es[1:]:
        out = convolve_rtds(t, out, e)
    return out


def parallel(fractions: ArrayLike, *es: ArrayLike) -> NDArray[np.float64]:
    """RTD of parallel flow paths: E = sum_i f_i E_i with sum f_i = 1 (Levenspiel 1999 ch. 12)."""
    f = np.asarray(fractions, dtype=float)
    if f.ndim != 1 or f.size != len(es) or f.size == 0:
        raise ValueError(f"fractions must have one entry per RTD ({len(es)}), got {f.shape}")
    if np.any(f < 0) or not np.isclose(f.sum(), 1.0):
        raise ValueError(f"fractions must be >= 0 and sum to 1, got {f.tolist()}")
    arrs = [np.asarray(e, dtype=float) for e in es]
    if any(a.shape != arrs[0].shape for a in arrs):
        raise ValueError("es must share one shape")
    return np.sum([fi * a for fi, a in zip(f, arrs)], axis=0)
