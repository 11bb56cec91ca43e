"""Funnel plots for out-of-specification (OOS) analysis (seed 6.1.4.3.2, 6.2.2.2).

A rectangular inlet disturbance of duration d and intensity h (% of the nominal
concentration) passes a system with RTD E; the outlet deviation is
y(t) = h int_{t-d}^{t} E = h (F(t) - F(t - d)) (convolution of a pulse with E, Levenspiel
1999 Eq. 11.9), so the maximum % deviation is h M(d) with M(d) = max_t (F(t) - F(t - d)).
The grid of max deviations over (d, h) is the funnel plot; the feasible region is where the
deviation stays below the limit (5 % by default; Engisch & Muzzio 2016), bounded by
h_crit(d) = limit / M(d).

Fig. 6.17 workflow (``oos_increase``): OOS fraction = 1 - feasible area / grid area
(disturbances uniformly distributed over the grid); the % increase of OOS tablets of a
truncated profile is 100 (OOS_truncated - OOS_original) percentage points.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from twin_core.rtd.convolution import convolve, cumulative, uniform_dt

__all__ = [
    "FunnelResult",
    "max_window_fraction",
    "funnel_gain",
    "funnel",
    "funnel_brute_force",
    "compare_funnels",
    "oos_fraction",
    "oos_increase_curve",
]


@dataclass
class FunnelResult:
    """Funnel grid: max % deviation for each (duration, intensity)."""

    durations: NDArray[np.float64]
    intensities: NDArray[np.float64]
    max_dev: NDArray[np.float64] = field(repr=False)  # shape (n_durations, n_intensities)
    m: NDArray[np.float64] = field(repr=False)  # M(d)
    limit: float = 5.0

    @property
    def feasible(self) -> NDArray[np.bool_]:
        return self.max_dev < self.limit

    @property
    def h_crit(self) -> NDArray[np.float64]:
        """Boundary of the feasible region: intensity at which the max deviation hits the limit."""
        with np.errstate(divide="ignore"):
            return np.where(self.m > 0, self.limit / self.m, np.inf)

    @property
    def grid_area(self) -> float:
        return float(np.ptp(self.durations) * np.ptp(self.intensities))

    @property
    def feasible_area(self) -> float:
        """Area (s x %) of the feasible region within the grid's rectangle:
        int min(h_crit(d), h_max) - h_min dd (trapezoid over the duration grid)."""
        h = np.clip(self.h_crit, self.intensities.min(), self.intensities.max())
        return float(np.trapezoid(h - self.intensities.min(), self.durations))

    @property
    def feasible_fraction(self) -> float:
        return self.feasible_area / self.grid_area if self.grid_area > 0 else float("nan")

    def as_dict(self) -> dict:
        return {
            "limit": self.limit,
            "durations": [
                float(self.durations.min()),
                float(self.durations.max()),
                self.durations.size,
            ],
            "intensities": [
                float(self.intensities.min()),
                float(self.intensities.max()),
                self.intensities.size,
            ],
            "feasible_area": self.feasible_area,
            "grid_area": self.grid_area,
            "feasible_fraction": self.feasible_fraction,
            "feasible_cells": int(self.feasible.sum()),
        }


def max_window_fraction(t: ArrayLike, e: ArrayLike, durations: ArrayLike) -> NDArray[np.float64]:
    """M(d) = max_t (F(t) - F(t - d)) for each duration d, F normalized to 1 (F(t<t0) = 0)."""
    tt = np.asarray(t, dtype=float)
    f = cumulative(tt, e)
    if not f[-1] > 0:
        raise ValueError(f"e must have a positive area, got {f[-1]!r}")
    f = f / f[-1]
    d = np.asarray(durations, dtype=float)
    if np.any(d < 0) or not np.all(np.isfinite(d)):
        raise ValueError("durations must be finite and >= 0")
    # F(t) - F(t - d): evaluate on the grid t and also on the shifted grid t + d (the max of a
    # difference of piecewise-linear functions sits at a breakpoint of either)
    out = np.empty(d.size)
    for i, di in enumerate(d):
        a = f - np.interp(tt - di, tt, f, left=0.0)
        b = np.interp(tt + di, tt, f, right=1.0) - f
        out[i] = max(a.max(), b.max())
    return out


def funnel_gain(e: ArrayLike, dt: float) -> NDArray[np.float64]:
    """The funnel boundary on a tick grid: g[m] = M(m dt) for pulses of m = 0..K ticks,

        M(d) = max_t [F(t) - F(t - d)]   (:func:`max_window_fraction`),

    with E given on t = k dt, k = 0..K-1 (F normalised to 1), made non-decreasing in m (a longer
    pulse never leaves less). A rectangular inlet deviation of h lasting m ticks gives a largest
    outlet deviation h g[m] (Engisch & Muzzio 2016; the seed's funnel plot, ch. 6). The one
    funnel gain of the twin: the diverter's early flag of feeder disturbances
    (``twin_core.online.funnel.FunnelFlagger``) uses it.
    """
    e = np.asarray(e, dtype=float)
    if e.ndim != 1 or e.size < 2:
        raise ValueError(f"e must be a 1-D array of >= 2 samples, got shape {e.shape}")
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be > 0, got {dt!r}")
    tk = np.arange(e.size) * dt
    return np.maximum.accumulate(max_window_fraction(tk, e, np.arange(e.size + 1) * dt))


def funnel(
    t: ArrayLike,
    e: ArrayLike,
    durations: ArrayLike | None = None,
    intensities: ArrayLike | None = None,
    limit: float = 5.0,
) -> FunnelResult:
    """Funnel grid by the closed form h M(d). Defaults: 200 durations 0-60 s,
    200 intensities 0-50 % of nominal (as the CLI)."""
    if not limit > 0:
        raise ValueError(f"limit must be > 0, got {limit!r}")
    d = np.linspace(0.0, 60.0, 200) if durations is None else np.asarray(durations, float)
    h = np.linspace(0.0, 50.0, 200) if intensities is None else np.asarray(intensities, float)
    if d.ndim != 1 or h.ndim != 1 or d.size < 2 or h.size < 2:
        raise ValueError("durations and intensities must be 1-D with >= 2 values")
    if np.any(h < 0):
        raise ValueError("intensities must be >= 0")
    m = max_window_fraction(t, e, d)
    return FunnelResult(d, h, np.outer(m, h), m, float(limit))


def funnel_brute_force(
    t: ArrayLike, e: ArrayLike, durations: ArrayLike, intensities: ArrayLike, limit: float = 5.0
) -> FunnelResult:
    """Reference: simulate each rectangular pulse through E by time-domain convolution
    (t uniform; pulse starts at t[0]; durations rounded to whole samples)."""
    tt = np.asarray(t, dtype=float)
    dt = uniform_dt(tt)
    en = np.asarray(e, float) / cumulative(tt, e)[-1]
    d = np.asarray(durations, float)
    h = np.asarray(intensities, float)
    out = np.empty((d.size, h.size))
    m = np.empty(d.size)
    for i, di in enumerate(d):
        u = ((tt - tt[0]) < di - 1e-9 * dt).astype(float)
        y = convolve(tt, u, en)
        m[i] = y.max()
        for j, hj in enumerate(h):
            out[i, j] = np.max(convolve(tt, hj * u, en))
    return FunnelResult(d, h, out, m, float(limit))


def compare_funnels(a: FunnelResult, b: FunnelResult) -> dict[str, float]:
    """Difference of two funnels on the same grid: feasible-area change, cells that change
    class, max |difference| of deviation, and intersection-over-union of the feasible sets."""
    if a.max_dev.shape != b.max_dev.shape:
        raise ValueError(f"funnels must share a grid, got {a.max_dev.shape} and {b.max_dev.shape}")
    fa, fb = a.feasible, b.feasible
    union = np.logical_or(fa, fb).sum()
    return {
        "feasible_area_a": a.feasible_area,
        "feasible_area_b": b.feasible_area,
        "feasible_area_change": b.feasible_area - a.feasible_area,
        "oos_increase_pct": 100.0 * (a.feasible_fraction - b.feasible_fraction),
        "cells_changed": int(np.logical_xor(fa, fb).sum()),
        "max_abs_deviation_difference": float(np.max(np.abs(b.max_dev - a.max_dev))),
        "feasible_iou": float(np.logical_and(fa, fb).sum() / union) if union else 1.0,
    }


def oos_fraction(f: FunnelResult) -> float:
    """Fraction of the (uniformly distributed) disturbances in the grid giving OOS product."""
    return 1.0 - f.feasible_fraction


def oos_increase_curve(
    t: ArrayLike,
    c: ArrayLike,
    levels: ArrayLike = (0.0125, 0.025, 0.0375, 0.05, 0.075, 0.1),
    smooth: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None,
    durations: ArrayLike | None = None,
    intensities: ArrayLike | None = None,
    limit: float = 5.0,
) -> NDArray[np.float64]:
    """Fig. 6.17 workflow for one profile: for each level (fraction of the peak height),
    zero the values below it (same length), apply `smooth` (the seed uses the wavelet
    denoiser), normalize to E, build the funnel, and return the % increase of OOS tablets
    (percentage points) against the untruncated, smoothed profile."""
    from twin_core.rtd.profiles import e_curve
    from twin_core.rtd.truncation import truncate_relative

    tt = np.asarray(t, dtype=float)
    cc = np.asarray(c, dtype=float)
    sm = smooth or (lambda y: y)
    ref = funnel(tt, e_curve(tt, sm(cc)), durations, intensities, limit)
    out = []
    for lv in np.atleast_1d(np.asarray(levels, dtype=float)):
        f = funnel(
            tt, e_curve(tt, sm(truncate_relative(cc, float(lv)))), durations, intensities, limit
        )
        out.append(compare_funnels(ref, f)["oos_increase_pct"])
    return np.array(out)
