"""Free-surface profiles of particle heaps and their angles (drawdown test responses).

The seed measured the angle of repose (upper heap) and the shear angle (lower heap) by image
analysis and averaged both sides (3.3.1.1). Here the free surface is the highest sphere top
(z + r) in columns of width ``bin_w`` along x (over the whole depth y), and each side's angle is
the slope of a least-squares line through the sloped part of the profile: the columns whose
height lies between 15 % and 85 % of the side's height range (this drops the flat top or floor
and the wall-bounded columns).
"""

from __future__ import annotations

import numpy as np

__all__ = ["fit_slope_angle", "surface_profile"]


def surface_profile(
    pos: np.ndarray,
    radii: np.ndarray,
    x_lo: float,
    x_hi: float,
    bin_w: float,
    z_floor: float,
    z_ceiling: float = np.inf,
) -> tuple[np.ndarray, np.ndarray]:
    """Column centres and free-surface height (max of z + r, ``z_floor`` for empty columns) of
    the particles with ``z_floor <= z < z_ceiling`` in [x_lo, x_hi)."""
    if bin_w <= 0:
        raise ValueError(f"bin_w must be > 0, got {bin_w}")
    n = max(1, int(round((x_hi - x_lo) / bin_w)))
    edges = np.linspace(x_lo, x_hi, n + 1)
    xc = 0.5 * (edges[1:] + edges[:-1])
    h = np.full(n, float(z_floor))
    sel = (
        (pos[:, 2] >= z_floor) & (pos[:, 2] < z_ceiling) & (pos[:, 0] >= x_lo) & (pos[:, 0] < x_hi)
    )
    k = np.clip(np.searchsorted(edges, pos[sel, 0], side="right") - 1, 0, n - 1)
    np.maximum.at(h, k, pos[sel, 2] + radii[sel])
    return xc, h


def fit_slope_angle(
    x: np.ndarray, h: np.ndarray, *, lower: float = 0.15, upper: float = 0.85
) -> dict[str, float]:
    """Angle (deg) of the least-squares line through the profile points whose height lies in
    [lower, upper] of the profile's height range; returns angle, slope, its standard error,
    R^2 and the number of points (angle NaN with fewer than 3 points)."""
    x = np.asarray(x, float)
    h = np.asarray(h, float)
    lo, hi = h.min(), h.max()
    if hi - lo <= 0:
        return {
            "angle_deg": 0.0,
            "slope": 0.0,
            "slope_se": float("nan"),
            "r2": float("nan"),
            "n": 0,
        }
    sel = (h >= lo + lower * (hi - lo)) & (h <= lo + upper * (hi - lo))
    if sel.sum() < 3:
        return {
            "angle_deg": float("nan"),
            "slope": float("nan"),
            "slope_se": float("nan"),
            "r2": float("nan"),
            "n": int(sel.sum()),
        }
    xs, hs = x[sel], h[sel]
    A = np.c_[xs, np.ones_like(xs)]
    coef, *_ = np.linalg.lstsq(A, hs, rcond=None)
    res = hs - A @ coef
    dof = max(len(xs) - 2, 1)
    s2 = float(res @ res) / dof
    se = float(np.sqrt(s2 / np.sum((xs - xs.mean()) ** 2)))
    sst = float(((hs - hs.mean()) ** 2).sum())
    return {
        "angle_deg": float(np.degrees(np.arctan(abs(coef[0])))),
        "slope": float(coef[0]),
        "slope_se": se,
        "r2": 1 - float(res @ res) / sst if sst > 0 else float("nan"),
        "n": int(len(xs)),
    }
