"""T95 mixing times from mixing curves (seed sections 4.3.3 and 4.4.3).

The mixing-progress curve ``M(t)`` (0 unmixed .. 1 mixed, see
:func:`twin_core.mixing.series.mixing_progress`) is smoothed with a Savitzky-Golay filter and
fitted with the damped exponential of Eq. (29), ``M = 1 - A exp(-gamma t)``, or the oscillating
Eq. (30), ``M = 1 - A exp(-gamma t) cos(w t)``. T95 is the time at which the fit reaches 0.95.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import curve_fit
from scipy.signal import savgol_filter


def t95_time(A: float, gamma: float) -> float:
    """T95 of Eq. (29): ``1 - A exp(-gamma T) = 0.95``  =>  ``T95 = ln(20 A) / gamma``.

    For the oscillating Eq. (30) the same expression with ``|A|`` is the time after which the
    envelope ``|A| exp(-gamma t)`` stays below 0.05, i.e. the fit stays within 5 % of mixed.
    Reference: seed Eq. (29); reproduces Tables 8.2-8.4 (e.g. DM, 100 rpm: A = 0.6968,
    gamma = 0.3469 -> 7.595 s).
    """
    if gamma <= 0:
        raise ValueError(f"gamma must be > 0, got {gamma}")
    if A == 0:
        raise ValueError("A must be non-zero")
    return float(np.log(20.0 * abs(A)) / gamma)


def exponential_model(t: np.ndarray, A: float, gamma: float) -> np.ndarray:
    """Seed Eq. (29): ``M(t) = 1 - A exp(-gamma t)``."""
    return 1.0 - A * np.exp(-gamma * t)


def oscillating_model(t: np.ndarray, A: float, gamma: float, w: float) -> np.ndarray:
    """Seed Eq. (30): ``M(t) = 1 - A exp(-gamma t) cos(w t)``."""
    return 1.0 - A * np.exp(-gamma * t) * np.cos(w * t)


@dataclass
class T95Fit:
    """Result of :func:`fit_t95` (parameters with standard errors, R^2 of the fit)."""

    model: str
    A: float
    gamma: float
    w: float | None
    t95: float
    r2: float
    stderr: dict[str, float]


def smooth(m: np.ndarray, window: int = 11, polyorder: int = 3) -> np.ndarray:
    """Savitzky-Golay smoothing as in seed 4.4.3 (window shrunk to the series if shorter)."""
    m = np.asarray(m, float)
    w = min(window, m.size if m.size % 2 == 1 else m.size - 1)
    if w <= polyorder:
        return m.copy()
    return savgol_filter(m, w, polyorder)


def _fit_input(
    t: np.ndarray, m: np.ndarray, min_points: int, smooth_window: int | None, polyorder: int
) -> tuple[np.ndarray, np.ndarray]:
    """The finite points of a progress curve, smoothed unless ``smooth_window`` is None."""
    t = np.asarray(t, float)
    m = np.asarray(m, float)
    if t.shape != m.shape or t.ndim != 1:
        raise ValueError(f"t and m must be 1-D of equal length, got {t.shape}, {m.shape}")
    ok = np.isfinite(t) & np.isfinite(m)
    if ok.sum() < min_points:
        raise ValueError(f"need at least {min_points} finite points, got {int(ok.sum())}")
    t, m = t[ok], m[ok]
    return t, (smooth(m, smooth_window, polyorder) if smooth_window else m)


def fit_t95(
    t: np.ndarray,
    m: np.ndarray,
    model: str = "exp",
    smooth_window: int | None = 11,
    polyorder: int = 3,
) -> T95Fit:
    """Fit Eq. (29) (``model="exp"``) or Eq. (30) (``model="osc"``) and return T95.

    ``m`` is a mixing-progress curve; set ``smooth_window=None`` to fit the raw curve.
    R^2 is computed against the curve that was fitted.
    """
    t, y = _fit_input(t, m, 5, smooth_window, polyorder)
    t0 = t - t[0]
    a0 = 1.0 - y[0] if abs(1.0 - y[0]) > 1e-6 else 1.0
    span = max(t0[-1], 1e-9)
    if model == "exp":
        p0 = [a0, 3.0 / span]
        popt, pcov = curve_fit(
            exponential_model,
            t0,
            y,
            p0=p0,
            bounds=([-np.inf, 1e-9], [np.inf, np.inf]),
            maxfev=20000,
        )
        fitted = exponential_model(t0, *popt)
        names = ["A", "gamma"]
    elif model == "osc":
        best = None
        for w0 in np.linspace(0.5, 20.0, 12) * 2 * np.pi / span:
            try:
                popt_i, pcov_i = curve_fit(
                    oscillating_model, t0, y, p0=[a0, 3.0 / span, w0],
                    bounds=([-np.inf, 1e-9, 0.0], [np.inf, np.inf, np.inf]), maxfev=20000,
                )  # fmt: skip
            except RuntimeError:
                continue
            sse = float(np.sum((y - oscillating_model(t0, *popt_i)) ** 2))
            if best is None or sse < best[0]:
                best = (sse, popt_i, pcov_i)
        if best is None:
            raise RuntimeError("oscillating fit did not converge from any start")
        _, popt, pcov = best
        fitted = oscillating_model(t0, *popt)
        names = ["A", "gamma", "w"]
    else:
        raise ValueError(f"model must be 'exp' or 'osc', got {model!r}")
    ss_res = float(np.sum((y - fitted) ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - ss_res / ss_tot if ss_tot > 0 else float("nan")
    se = np.sqrt(np.clip(np.diag(pcov), 0, np.inf))
    A, gamma = float(popt[0]), float(popt[1])
    return T95Fit(
        model=model,
        A=A,
        gamma=gamma,
        w=float(popt[2]) if model == "osc" else None,
        t95=t95_time(A, gamma) + float(t[0]) if A != 0 else float(t[0]),
        r2=r2,
        stderr=dict(zip(names, map(float, se))),
    )


def delayed_model(
    t: np.ndarray, A: float, gamma: float, t0: float, w: float | None = None
) -> np.ndarray:
    """Delayed-onset mixing curve: ``M = 0`` for ``t < t0`` (filling, nothing mixes yet), then
    Eq. (29) ``1 - A exp(-gamma (t - t0))`` (or Eq. (30) with ``cos(w (t - t0))``) in
    ``t - t0``."""
    s = np.asarray(t, float) - t0
    decay = A * np.exp(-gamma * np.maximum(s, 0.0))
    if w is not None:
        decay = decay * np.cos(w * np.maximum(s, 0.0))
    return np.where(s < 0, 0.0, 1.0 - decay)


@dataclass
class OnsetFit(T95Fit):
    """Result of :func:`fit_delayed_onset`: onset ``t0`` (s) and Eq. (29)/(30) in ``t - t0``;
    ``t95 = t0 + ln(20 |A|) / gamma`` (absolute time, like :attr:`T95Fit.t95`)."""

    t0: float


def _exp_profile(s: np.ndarray, y: np.ndarray, span: float) -> tuple[np.ndarray, float]:
    """Least-squares Eq. (29) on ``(s, y)``: ``A`` in closed form for each ``gamma`` (linear
    least squares), ``gamma`` by a bounded search over ``log gamma``. Returns (A, gamma), SSE."""
    from scipy.optimize import minimize_scalar

    def a_and_sse(log_g):
        e = np.exp(-np.exp(log_g) * s)
        a = float(np.sum((1.0 - y) * e) / max(np.sum(e * e), 1e-300))
        return a, float(np.sum((y - 1.0 + a * e) ** 2))

    lo, hi = np.log(1e-3 / span), np.log(1e3 / span)
    res = minimize_scalar(lambda x: a_and_sse(x)[1], bounds=(lo, hi), method="bounded")
    a, sse = a_and_sse(res.x)
    return np.array([a, float(np.exp(res.x))]), sse


def _fit_after_onset(t, y, t0, model, start, span):
    """Least-squares Eq. (29)/(30) in ``t - t0`` on the points after ``t0``: (params, SSE over
    all points, covariance or None)."""
    after = t >= t0
    s = t[after] - t0
    before = float(np.sum(y[~after] ** 2))
    if model == "exp":
        popt, sse = _exp_profile(s, y[after], span)
        return popt, before + sse, None
    bounds = ([-np.inf, 1e-9, 0.0], [np.inf, np.inf, np.inf])
    popt, pcov = curve_fit(oscillating_model, s, y[after], p0=start, bounds=bounds, maxfev=20000)
    return popt, before + float(np.sum((y[after] - oscillating_model(s, *popt)) ** 2)), pcov


def fit_delayed_onset(
    t: np.ndarray,
    m: np.ndarray,
    model: str = "exp",
    smooth_window: int | None = 11,
    polyorder: int = 3,
    n_onsets: int = 40,
) -> OnsetFit:
    """Fit the delayed-onset curve (:func:`delayed_model`) and return its T95.

    The onset is found by profiling: for ``n_onsets`` candidate onsets between the first
    sample and the time the (smoothed) curve first reaches half way, Eq. (29)/(30) is fitted
    to the points after the onset and the curve is 0 before it; the onset with the smallest
    total squared error is refined by a bounded search between its neighbours. Fitting
    Eq. (29) from the first sample to a curve that only starts rising after filling bends
    ``gamma`` and ``A`` to absorb the flat start; this fit separates the two (seed Eq. 29,
    T95 in ``t - t0``).
    """
    from scipy.optimize import minimize_scalar

    if model not in ("exp", "osc"):
        raise ValueError(f"model must be 'exp' or 'osc', got {model!r}")
    t, y = _fit_input(t, m, 8, smooth_window, polyorder)
    span = max(t[-1] - t[0], 1e-9)
    half = np.flatnonzero(y >= 0.5)
    t_half = t[half[0]] if len(half) else t[-1]
    last = t[max(len(t) - 5, 1)]
    candidates = np.linspace(t[0], min(t_half, last), n_onsets)
    start = [1.0, 3.0 / span] if model == "exp" else [1.0, 3.0 / span, 2 * np.pi / span]
    best = None
    for t0 in candidates:
        try:
            popt, sse, pcov = _fit_after_onset(t, y, t0, model, start, span)
        except (RuntimeError, ValueError):
            continue
        if best is None or sse < best[1]:
            best = (t0, sse, popt, pcov)
    if best is None:
        raise RuntimeError("delayed-onset fit did not converge for any onset")
    step = candidates[1] - candidates[0] if len(candidates) > 1 else 0.0
    if step > 0:
        t_best, p_best = best[0], best[2]
        res = minimize_scalar(
            lambda x: _fit_after_onset(t, y, x, model, p_best, span)[1],
            bounds=(max(t[0], t_best - step), min(last, t_best + step)),
            method="bounded",
            options={"xatol": 1e-4 * span},
        )
        if res.success and res.fun < best[1]:
            popt, sse, pcov = _fit_after_onset(t, y, float(res.x), model, p_best, span)
            best = (float(res.x), sse, popt, pcov)
    t0, sse, popt, pcov = best
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    A, gamma = float(popt[0]), float(popt[1])
    names = ["A", "gamma"] if model == "exp" else ["A", "gamma", "w"]
    if pcov is None:  # Eq. (29): the covariance of (A, gamma) at the chosen onset
        after = t >= t0
        _, pcov = curve_fit(exponential_model, t[after] - t0, y[after], p0=popt, maxfev=20000)
    se = np.sqrt(np.clip(np.diag(pcov), 0, np.inf))
    return OnsetFit(
        model=model,
        t0=float(t0),
        A=A,
        gamma=gamma,
        w=float(popt[2]) if model == "osc" else None,
        t95=float(t0) + t95_time(A, gamma),
        r2=1.0 - sse / ss_tot if ss_tot > 0 else float("nan"),
        stderr=dict(zip(names, map(float, se))),
    )
