"""Lot boundaries and diversion windows from an RTD (material traceability).

Following Engisch & Muzzio (2016, J. Pharm. Innov. 11, 64) as used in the seed (6.1.4.3.1):
material entering at the inlet at time 0 leaves between the `lower` and `upper` quantiles of
F(t) (0.5 % and 99.5 % by default). A disturbance present at the inlet during
[t_start, t_end] therefore reaches the outlet during [t_start + t_lo, t_end + t_hi].
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from twin_core.rtd.convolution import cumulative

__all__ = ["quantile_time", "lot_boundaries", "diversion_window", "excursion_window"]


def _check_level(name: str, value: float) -> float:
    v = float(value)
    if not (0.0 < v < 1.0):
        raise ValueError(f"{name} must be in (0, 1), got {value!r}")
    return v


def quantile_time(t: ArrayLike, e: ArrayLike, q: float) -> float:
    """Time at which the normalized F(t) = int E / int E first reaches q (linear interp.)."""
    q = _check_level("q", q)
    tt = np.asarray(t, dtype=float)
    f = cumulative(tt, e)
    area = f[-1]
    if not area > 0:
        raise ValueError(f"e must have a positive area, got {area!r}")
    # first time the normalized F reaches q: search the running maximum, which is monotone
    # even when a measured profile has negative (baseline-noise) values
    fn = np.maximum.accumulate(f / area)
    i = int(np.searchsorted(fn, q, side="left"))
    if i == 0:
        return float(tt[0])
    f0, f1 = fn[i - 1], fn[i]
    w = 0.0 if f1 == f0 else (q - f0) / (f1 - f0)
    return float(tt[i - 1] + w * (tt[i] - tt[i - 1]))


def lot_boundaries(
    t: ArrayLike, e: ArrayLike, lower: float = 0.005, upper: float = 0.995
) -> tuple[float, float]:
    """(t_lo, t_hi): the times where F(t) reaches `lower` and `upper` (seed 6.1.4.3.1).

    E is normalized by its area first, so a tracer concentration profile may be passed.
    """
    lower = _check_level("lower", lower)
    upper = _check_level("upper", upper)
    if not lower < upper:
        raise ValueError(f"lower must be < upper, got lower={lower!r}, upper={upper!r}")
    return quantile_time(t, e, lower), quantile_time(t, e, upper)


def diversion_window(
    t_start: float,
    t_end: float,
    t: ArrayLike,
    e: ArrayLike,
    lower: float = 0.005,
    upper: float = 0.995,
) -> tuple[float, float]:
    """Outlet window (start, end) to divert for an inlet disturbance during [t_start, t_end].

    start = t_start + t_lo, end = t_end + t_hi with (t_lo, t_hi) = lot_boundaries(t, e).
    Times of E are measured from the moment material enters (E's time origin is t[0] = 0).
    """
    ts, te = float(t_start), float(t_end)
    if not (np.isfinite(ts) and np.isfinite(te)):
        raise ValueError(f"t_start and t_end must be finite, got {t_start!r}, {t_end!r}")
    if te < ts:
        raise ValueError(f"t_end must be >= t_start, got t_start={t_start!r}, t_end={t_end!r}")
    lo, hi = lot_boundaries(t, e, lower, upper)
    t0 = float(np.asarray(t, dtype=float)[0])
    return ts + lo - t0, te + hi - t0


def excursion_window(
    t_start: float,
    deviation: ArrayLike,
    e: ArrayLike,
    dt: float,
    target: float,
    lower: float,
    upper: float,
    guard: float = 0.0,
) -> tuple[float, float] | None:
    """Outlet window where an inlet disturbance's predicted outlet leaves [lower + guard,
    upper - guard], or None when it stays inside.

    ``deviation``: the inlet composition's deviation from ``target`` (% w/w) on the tick grid
    from ``t_start``; ``e``: E(t) on the same grid from 0 (sum(e) dt = 1). For a linear blender
    the outlet deviation is the convolution (Engisch & Muzzio 2016, J. Pharm. Innov. 11:64,
    Eq. 1 of the funnel plot)

        c_out(t_start + k dt) = target + dt sum_j deviation[j] e[k - j],

    and the window is [first, last] plant time of the samples outside the guarded limits: the
    product the disturbance actually puts at risk, where the lot boundaries
    (:func:`diversion_window`) divert every outlet sample holding >= 0.5 % of the disturbed
    material, in specification or not. ``guard`` (% w/w, >= 0) widens the window for the error
    of E(t) and of the inlet signal.
    """
    if not dt > 0:
        raise ValueError(f"dt must be > 0, got {dt!r}")
    if not (guard >= 0 and lower + guard < target < upper - guard):
        raise ValueError(
            f"guard must be >= 0 and leave target inside the guarded limits, got guard {guard!r} "
            f"with target {target!r} in ({lower!r}, {upper!r})"
        )
    d = np.asarray(deviation, dtype=float)
    k = np.asarray(e, dtype=float)
    if d.size == 0 or k.size == 0:
        return None
    c = target + np.convolve(d, k) * dt
    out = np.flatnonzero((c < lower + guard) | (c > upper - guard))
    if out.size == 0:
        return None
    t0 = float(t_start)
    return t0 + float(out[0]) * dt, t0 + float(out[-1]) * dt
