"""Quantities derived from a fitted RTD model, with intervals by the delta method.

A derived quantity g(theta) (mean residence time, variance, a quantile of F, a funnel limit)
is computed from the model's E(t; theta) on a fine grid that holds its whole mass
(:func:`model_grid`), so that the part of the tail beyond the measured record counts. Its
interval is the Wald interval of the fit (``RawFit.interval``) for the gradient of g by
central differences with steps of 1 % of each parameter's standard error (at least
``PROFILE_GRID_CELLS`` grid cells for a parameter whose interval is the profile likelihood's: it
moves a jump of E), g +/- t_nu SE,
SE^2 = grad^T Cov grad, nu Satterthwaite's (Seber & Wild 1989, ch. 5.1; delta method), on the
log scale for positive quantities.

Moments on the grid: mean t_m = int t E / int E, variance int (t - t_m)^2 E / int E
(Levenspiel 1999 ch. 11; trapezoid rule).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize, stats

from twin_core.rtd.likelihood import RawFit
from twin_core.rtd.models import get_model

__all__ = [
    "Estimate",
    "model_grid",
    "model_curve",
    "derived",
    "moment_estimates",
    "mean_residence_time",
    "model_average",
    "GRID_POINTS",
]

#: points of the model grid
GRID_POINTS = 20001
#: least step (in grid cells) of the difference quotient of a parameter whose interval is the
#: profile likelihood's (``RawFit.profile_ci``)
PROFILE_GRID_CELLS = 10
#: mass the grid may leave out beyond its end
TAIL_MASS = 1e-6


@dataclass(frozen=True)
class Estimate:
    """A derived quantity with its standard error and interval."""

    value: float
    stderr: float
    ci: tuple[float, float]

    def as_dict(self) -> dict[str, float | list[float]]:
        return {"value": self.value, "stderr": self.stderr, "ci": [self.ci[0], self.ci[1]]}


def model_curve(fit: RawFit, t: NDArray, theta: ArrayLike | None = None) -> NDArray[np.float64]:
    """E(t; theta) of the fitted model (theta defaults to the estimate)."""
    spec = get_model(fit.model)
    th = fit.theta if theta is None else np.asarray(theta, dtype=float)
    return np.asarray(spec.func(t, *th), dtype=float)


def _mass_beyond(t: NDArray, e: NDArray) -> float:
    area = np.concatenate([[0.0], np.cumsum(0.5 * (e[1:] + e[:-1]) * np.diff(t))])
    return 1.0 - float(area[-1]) if area[-1] > 0 else 1.0


def model_grid(fit: RawFit, t_record: ArrayLike) -> NDArray[np.float64]:
    """A uniform grid of ``GRID_POINTS`` from min(0, t_record[0]) to where the fitted E has
    lost less than ``TAIL_MASS`` (4, 8, ... 256 times the record's end)."""
    tr = np.asarray(t_record, dtype=float)
    start = min(0.0, float(tr[0]))
    spec = get_model(fit.model)
    if "mu" in spec.params:  # a Gaussian part may reach below t = 0
        start = min(start, fit.params["mu"] - 10.0 * fit.params.get("sigma", 0.0))
    end = float(tr[-1])
    for factor in (4, 8, 16, 32, 64, 128, 256):
        grid = np.linspace(start, start + factor * (end - start), GRID_POINTS)
        if _mass_beyond(grid, model_curve(fit, grid)) < TAIL_MASS:
            return grid
    return grid


def derived(
    fit: RawFit,
    grid: NDArray,
    fn: Callable[[NDArray, NDArray], ArrayLike],
    log_scale: bool = True,
) -> list[Estimate]:
    """Estimates of the quantities fn(grid, E) (a scalar or a vector) with their intervals
    (module docstring)."""
    value = np.atleast_1d(np.asarray(fn(grid, model_curve(fit, grid)), dtype=float))
    theta = fit.theta
    se = np.sqrt(np.clip(np.diag(fit.theta_cov()), 0.0, None))
    grads = np.zeros((value.size, fit.k))
    for i, v in enumerate(theta):
        h = 0.01 * se[i] if se[i] > 0 else 1e-6 * max(abs(v), 1.0)
        if fit.names[i] in fit.profile_ci:
            # a parameter with a profile interval moves a jump of E: a step of a few grid cells
            # keeps the difference quotient off the grid's own steps
            h = max(h, PROFILE_GRID_CELLS * float(grid[1] - grid[0]))
        up, down = theta.copy(), theta.copy()
        up[i], down[i] = v + h, v - h
        lo = np.asarray(get_model(fit.model).lower)[i]
        if down[i] <= lo:  # one-sided at a bound
            down[i] = v
            hh = h
        else:
            hh = 2 * h
        if up[i] > get_model(fit.model).upper[i]:  # one-sided below an upper bound (a fraction)
            up[i] = v
            hh -= h
        if hh <= 0:
            continue
        f_up = np.atleast_1d(np.asarray(fn(grid, model_curve(fit, grid, up)), dtype=float))
        f_dn = np.atleast_1d(np.asarray(fn(grid, model_curve(fit, grid, down)), dtype=float))
        grads[:, i] = (f_up - f_dn) / hh
    out = []
    for val, g in zip(value, grads):
        stderr = float(np.sqrt(max(g @ fit.cov @ g, 0.0)))
        out.append(Estimate(float(val), stderr, fit.interval(float(val), g, log_scale)))
    return out


def _mean(t: NDArray, e: NDArray) -> float:
    return float(np.trapezoid(t * e, t) / np.trapezoid(e, t))


def _variance(t: NDArray, e: NDArray) -> float:
    m = _mean(t, e)
    return float(np.trapezoid((t - m) ** 2 * e, t) / np.trapezoid(e, t))


def moment_estimates(fit: RawFit, grid: NDArray) -> dict[str, Estimate]:
    """Mean residence time (s) and variance (s^2) of the fitted model with intervals."""
    return {
        "mean_residence_time_s": derived(fit, grid, _mean)[0],
        "variance_s2": derived(fit, grid, _variance)[0],
    }


def mean_residence_time(fit: RawFit, t_record: ArrayLike) -> Estimate:
    """Mean residence time (s) of the fitted model with its interval (:func:`derived` on
    :func:`model_grid`)."""
    return derived(fit, model_grid(fit, t_record), _mean)[0]


def model_average(estimates: list[Estimate], weights: ArrayLike, alpha: float = 0.05) -> Estimate:
    """One quantity estimated under several models, averaged with their weights w_i (e.g.
    BIC weights, Burnham & Anderson 2002, ch. 4.2-4.3):

    value = sum_i w_i g_i, stderr^2 = sum_i w_i (se_i^2 + (g_i - value)^2) (the unconditional
    variance, Burnham & Anderson 2002, Eq. 6.12), and the model-averaged tail-area interval
    (MATA, Turek & Fletcher 2012, Comput. Stat. Data Anal. 56, 2809): the limits L, U with
    sum_i w_i Phi((ln L - ln g_i) / s_i) = alpha / 2 and sum_i w_i Phi((ln g_i - ln U) / s_i)
    = alpha / 2, where model i's estimate is log-normal with s_i = ln(hi_i / lo_i) / (2 z),
    z = Phi^-1(1 - alpha / 2), so that each model alone gives its own interval [lo_i, hi_i]
    back. The interval thus holds each model's own uncertainty and the spread between the
    models; it is the single model's interval when one weight is 1. Estimates must be > 0."""
    w = np.asarray(weights, dtype=float)
    if len(estimates) == 0 or w.shape != (len(estimates),) or np.any(w < 0) or not w.sum() > 0:
        raise ValueError(f"need one weight >= 0 per estimate, got {w!r} for {len(estimates)}")
    w = w / w.sum()
    g = np.array([e.value for e in estimates])
    if np.any(g <= 0) or any(not (0 < e.ci[0] <= e.value <= e.ci[1]) for e in estimates):
        raise ValueError("model_average needs positive estimates inside positive intervals")
    value = float(w @ g)
    se = np.array([e.stderr for e in estimates])
    stderr = float(np.sqrt(w @ (se**2 + (g - value) ** 2)))
    z = float(stats.norm.ppf(1 - alpha / 2))
    lg = np.log(g)
    s = np.array([max(np.log(e.ci[1] / e.ci[0]), 1e-12) for e in estimates]) / (2 * z)

    def below(x: float) -> float:  # sum_i w_i P_i(G < e^x)
        return float(w @ stats.norm.cdf((x - lg) / s))

    lo_x = float(np.min(lg - 10 * s))
    hi_x = float(np.max(lg + 10 * s))
    low = optimize.brentq(lambda x: below(x) - alpha / 2, lo_x, hi_x)
    high = optimize.brentq(lambda x: below(x) - (1 - alpha / 2), lo_x, hi_x)
    return Estimate(value, stderr, (float(np.exp(low)), float(np.exp(high))))
