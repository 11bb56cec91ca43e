"""Feed factor of a screw feeder as a function of the hopper mass (seed Eq. 2).

The feed factor FF is the mass a screw delivers per revolution; with the screw speed w(t)
the outflow is F(t) = w(t) FF(t) (seed Eq. 1). Escotet-Espinoza et al. (2018), from
Heckel's compaction equation, model its dependence on the hopper mass W as

    FF(W) = FF_max - (FF_max - FF_min) exp(-beta W)                      (seed Eq. 2)

FF_max is the feed factor of a full hopper (densest powder in the screw flights), FF_min the
value extrapolated to an empty hopper, beta (1/mass) the rate of the decay.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import curve_fit

__all__ = ["feed_factor", "FeedFactorFit", "fit_feed_factor"]


def feed_factor(w: ArrayLike, ff_max: float, ff_min: float, beta: float) -> np.ndarray | float:
    """Feed factor at hopper mass ``w``: ``FF = ff_max - (ff_max - ff_min) exp(-beta w)``.

    Seed Eq. (2) (Escotet-Espinoza et al., 2018). ``w`` and ``1/beta`` share a mass unit;
    the result has the unit of ``ff_max`` (e.g. g/rev). Scalars in give a float out.
    """
    if beta < 0:
        raise ValueError(f"beta must be >= 0, got {beta}")
    w_arr = np.asarray(w, dtype=float)
    out = ff_max - (ff_max - ff_min) * np.exp(-beta * w_arr)
    return float(out) if out.ndim == 0 else out


@dataclass(frozen=True)
class FeedFactorFit:
    """Least-squares fit of seed Eq. (2); estimates with standard errors and R^2."""

    ff_max: float
    ff_min: float
    beta: float
    stderr: dict[str, float]
    r2: float
    rmse: float
    n: int

    def predict(self, w: ArrayLike) -> np.ndarray | float:
        """FF at hopper mass ``w`` from the fitted parameters."""
        return feed_factor(w, self.ff_max, self.ff_min, self.beta)

    def as_dict(self) -> dict[str, float]:
        return {
            "ff_max": self.ff_max,
            "ff_min": self.ff_min,
            "beta": self.beta,
            "ff_max_se": self.stderr["ff_max"],
            "ff_min_se": self.stderr["ff_min"],
            "beta_se": self.stderr["beta"],
            "r2": self.r2,
            "rmse": self.rmse,
            "n": self.n,
        }


def fit_feed_factor(
    w: ArrayLike,
    ff: ArrayLike,
    p0: tuple[float, float, float] | None = None,
    nonnegative: bool = True,
) -> FeedFactorFit:
    """Fit FF(W) of seed Eq. (2) to feed-factor vs hopper-mass data by nonlinear least squares.

    The seed used SciPy ``curve_fit``; so does this (trust-region reflective with bounds
    ``ff_min, beta >= 0`` when ``nonnegative``). Standard errors come from the covariance
    ``s^2 (J^T J)^-1``; R^2 = 1 - SSE/SST.
    """
    w_arr = np.asarray(w, dtype=float).ravel()
    y = np.asarray(ff, dtype=float).ravel()
    if w_arr.shape != y.shape:
        raise ValueError(f"w and ff must have the same length, got {w_arr.size} and {y.size}")
    ok = np.isfinite(w_arr) & np.isfinite(y)
    w_arr, y = w_arr[ok], y[ok]
    if w_arr.size < 4:
        raise ValueError(
            f"need at least 4 finite (w, ff) points to fit 3 parameters, got {w_arr.size}"
        )
    if np.ptp(w_arr) == 0:
        raise ValueError("w is constant: the decay rate beta cannot be identified")
    if p0 is None:
        span = float(np.ptp(w_arr))
        order = np.argsort(w_arr)
        p0 = (float(np.max(y)), float(max(np.min(y[order[:3]]), 0.0)), 3.0 / span)
    lower = [0.0, 0.0, 0.0] if nonnegative else [-np.inf, -np.inf, 0.0]
    popt, pcov = curve_fit(
        lambda x, a, b, c: a - (a - b) * np.exp(-c * x),
        w_arr,
        y,
        p0=p0,
        bounds=(lower, [np.inf, np.inf, np.inf]),
        maxfev=20000,
    )
    resid = y - feed_factor(w_arr, *popt)
    sse = float(resid @ resid)
    sst = float(((y - y.mean()) ** 2).sum())
    se = np.sqrt(np.clip(np.diag(pcov), 0, np.inf))
    return FeedFactorFit(
        ff_max=float(popt[0]),
        ff_min=float(popt[1]),
        beta=float(popt[2]),
        stderr={"ff_max": float(se[0]), "ff_min": float(se[1]), "beta": float(se[2])},
        r2=1.0 - sse / sst if sst > 0 else float("nan"),
        rmse=float(np.sqrt(sse / y.size)),
        n=int(y.size),
    )
