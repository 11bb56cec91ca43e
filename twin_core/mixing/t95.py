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
    t = np.asarray(t, float)
    m = np.asarray(m, float)
    if t.shape != m.shape or t.ndim != 1:
        raise ValueError(f"t and m must be 1-D of equal length, got {t.shape}, {m.shape}")
    ok = np.isfinite(t) & np.isfinite(m)
    if ok.sum() < 5:
        raise ValueError(f"need at least 5 finite points, got {int(ok.sum())}")
    t, m = t[ok], m[ok]
    y = smooth(m, smooth_window, polyorder) if smooth_window else m
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
