"""Outlier detection by the Hampel identifier (moving-median filter), the project's one Hampel.

A point is an outlier if |y_i - med_i| > n_sigma * s_i, with med_i the median of its centred
window of half-width k and s_i a robust local scale (Hampel 1974; Pearson 2002, "Outliers in
process modeling and identification", IEEE TCST 10, 55). Two variants, one per use:

* ``variant="seed"`` (RTD profiles, seed 6.1.3.1): windows mirrored at the ends; s_i =
  max(1.4826 MAD_i, S) with S the global robust scale 1.4826 median|y - med| (a 7-point MAD
  is itself noisy and would flag ordinary noise); outliers replaced by linear interpolation
  between the nearest retained neighbours; y must be finite.
* ``variant="pearson"`` (NIR records of the close-loop, with gaps): Pearson's Hampel filter --
  windows extended with the end values, s_i = 1.4826 MAD_i, outliers replaced by the window
  median; NaN samples are left out of the windows, never flagged and kept. ``min_scale``
  (e.g. the known noise standard deviation) floors s_i: a 7-point MAD alone flags ~3 % of
  Gaussian noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import ArrayLike, NDArray

__all__ = ["OutlierResult", "hampel"]

#: MAD -> standard deviation of a Gaussian
_MAD_SCALE = 1.4826


@dataclass(frozen=True)
class OutlierResult:
    """Cleaned signal, indices of replaced points and their original values."""

    y: NDArray[np.float64]
    indices: NDArray[np.intp]
    original: NDArray[np.float64]

    @property
    def count(self) -> int:
        return int(self.indices.size)

    @property
    def mask(self) -> NDArray[np.bool_]:
        """True at the replaced points."""
        out = np.zeros(self.y.size, dtype=bool)
        out[self.indices] = True
        return out


def _running_median_mad(
    y: NDArray[np.float64], k: int, pad: Literal["reflect", "edge"]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Median and scaled MAD (1.4826 MAD) of each centred (2k + 1)-sample window, NaN left out."""
    win = sliding_window_view(np.pad(y, k, mode=pad), 2 * k + 1)
    median = np.nanmedian if np.isnan(y).any() else np.median
    med = median(win, axis=1)
    mad = _MAD_SCALE * median(np.abs(win - med[:, None]), axis=1)
    return med, mad


def hampel(
    y: ArrayLike,
    half_window: int = 3,
    n_sigma: float = 4.0,
    t: ArrayLike | None = None,
    *,
    variant: Literal["seed", "pearson"] = "seed",
    min_scale: ArrayLike | float = 0.0,
) -> OutlierResult:
    """Detect outliers with the Hampel identifier and replace them (see the module docstring).

    Windows shorter than ``2 half_window + 1`` samples at the ends are completed by the
    variant's padding; a record shorter than a window uses the widest window that fits.
    ``t`` (optional, ``seed`` variant) gives the abscissa for interpolation; default sample
    index. ``n_sigma`` = 4 flags 0.1 % of pure Gaussian noise as outliers (3, Pearson's choice,
    flags 0.9 % with the noisy 7-point windows). ``min_scale`` (``pearson``): a floor of the
    local scale, a number or one per sample.
    """
    if variant not in ("seed", "pearson"):
        raise ValueError(f"variant must be 'seed' or 'pearson', got {variant!r}")
    yy = np.asarray(y, dtype=float)
    if yy.ndim != 1 or yy.size < 3:
        raise ValueError(f"y must be 1-D with >= 3 points, got shape {yy.shape}")
    if variant == "seed" and not np.all(np.isfinite(yy)):
        raise ValueError("y must be finite, got NaN or inf")
    k = int(half_window)
    if k < 1:
        raise ValueError(f"half_window must be >= 1, got {half_window!r}")
    if not n_sigma > 0:
        raise ValueError(f"n_sigma must be > 0, got {n_sigma!r}")
    x = np.arange(yy.size, dtype=float) if t is None else np.asarray(t, dtype=float)
    if x.shape != yy.shape:
        raise ValueError(f"t must have the shape of y {yy.shape}, got {x.shape}")
    k = min(k, (yy.size - 1) // 2)
    cleaned = yy.copy()
    if variant == "pearson":
        med, mad = _running_median_mad(yy, k, "edge")
        floor = np.maximum(np.broadcast_to(np.asarray(min_scale, dtype=float), yy.shape), 1e-12)
        out = np.isfinite(yy) & (np.abs(yy - med) > n_sigma * np.maximum(mad, floor))
        cleaned[out] = med[out]
    else:
        med, mad = _running_median_mad(yy, k, "reflect")
        glob = _MAD_SCALE * np.median(np.abs(yy - med))
        scale = np.maximum(mad, max(glob, 1e-12 * max(np.max(np.abs(yy)), 1e-300)))
        out = np.abs(yy - med) > n_sigma * scale
        if out.any() and not out.all():
            cleaned[out] = np.interp(x[out], x[~out], yy[~out])
    idx = np.nonzero(out)[0]
    return OutlierResult(cleaned, idx, yy[idx].copy())
