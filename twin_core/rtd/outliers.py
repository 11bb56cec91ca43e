"""Outlier detection by the Hampel identifier (moving-median filter) with interpolation.

A point is an outlier if |y_i - med_i| > n_sigma * max(1.4826 MAD_i, S), where med_i and MAD_i
are the median and median absolute deviation in a centred window of half-width k and S is the
global robust scale 1.4826 median|y - med| (guards against the noisy 7-point MAD) (Hampel 1974;
Pearson 2002, "Outliers in process modeling and identification", IEEE TCST 10, 55). Outliers
are replaced by linear interpolation between the nearest retained neighbours (seed 6.1.3.1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import ArrayLike, NDArray

__all__ = ["OutlierResult", "hampel"]


@dataclass(frozen=True)
class OutlierResult:
    """Cleaned signal, indices of replaced points and their original values."""

    y: NDArray[np.float64]
    indices: NDArray[np.intp]
    original: NDArray[np.float64]

    @property
    def count(self) -> int:
        return int(self.indices.size)


def hampel(
    y: ArrayLike, half_window: int = 3, n_sigma: float = 4.0, t: ArrayLike | None = None
) -> OutlierResult:
    """Detect outliers with the Hampel identifier and replace them by linear interpolation.

    Windows are truncated at the ends (edge padding by reflection). ``t`` (optional) gives the
    abscissa for interpolation; default sample index. ``n_sigma`` = 4 flags 0.1 % of pure Gaussian
    noise as outliers (3, Pearson's choice, flags 0.9 % with the noisy 7-point windows).
    """
    yy = np.asarray(y, dtype=float)
    if yy.ndim != 1 or yy.size < 3:
        raise ValueError(f"y must be 1-D with >= 3 points, got shape {yy.shape}")
    if not np.all(np.isfinite(yy)):
        raise ValueError("y must be finite, got NaN or inf")
    k = int(half_window)
    if k < 1:
        raise ValueError(f"half_window must be >= 1, got {half_window!r}")
    if not n_sigma > 0:
        raise ValueError(f"n_sigma must be > 0, got {n_sigma!r}")
    k = min(k, (yy.size - 1) // 2)
    padded = np.pad(yy, k, mode="reflect")
    win = sliding_window_view(padded, 2 * k + 1)
    med = np.median(win, axis=1)
    mad = 1.4826 * np.median(np.abs(win - med[:, None]), axis=1)
    # floor the local scale by the global robust scale of the residual to the running median:
    # a 7-point MAD is itself noisy and would flag ordinary noise
    glob = 1.4826 * np.median(np.abs(yy - med))
    scale = np.maximum(mad, max(glob, 1e-12 * max(np.max(np.abs(yy)), 1e-300)))
    out = np.abs(yy - med) > n_sigma * scale
    idx = np.nonzero(out)[0]
    x = np.arange(yy.size, dtype=float) if t is None else np.asarray(t, dtype=float)
    if x.shape != yy.shape:
        raise ValueError(f"t must have the shape of y {yy.shape}, got {x.shape}")
    cleaned = yy.copy()
    if idx.size and idx.size < yy.size:
        keep = ~out
        cleaned[out] = np.interp(x[out], x[keep], yy[keep])
    return OutlierResult(cleaned, idx, yy[idx].copy())
