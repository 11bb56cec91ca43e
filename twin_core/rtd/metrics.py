"""Comparison metrics for denoised profiles (seed 6.1.3.4) and errors against a known truth.

- height: max of the profile;
- width: full width at half maximum (FWHM) of the main peak in time units, with linear
  interpolation of the half-height crossings; ``width_samples`` is the same in samples
  (scipy.signal.peak_widths, rel_height 0.5), the unit the seed's Table 6.1 appears to use;
- Signal_STD: standard deviation of the (denoised) signal;
- Difference_STD: std of (denoised - original);
- Difference_SNR: |mean(diff)| / std(diff);
- Improvement_SNR: 1 / std(diff) (the seed takes the mean as 1).
With a truth: RMSE to truth, error of the mean residence time and of the variance.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.signal import peak_widths

from twin_core.rtd.profiles import moments

__all__ = ["height", "fwhm", "width_samples", "denoise_metrics", "truth_metrics"]


def height(y: ArrayLike) -> float:
    """Maximum of the profile."""
    return float(np.max(np.asarray(y, dtype=float)))


def fwhm(t: ArrayLike, y: ArrayLike) -> float:
    """Full width at half maximum of the highest peak (interpolated crossings)."""
    tt, yy = np.asarray(t, float), np.asarray(y, float)
    i = int(np.argmax(yy))
    half = 0.5 * yy[i]
    if not half > 0:
        raise ValueError(f"y must have a positive maximum, got {yy[i]!r}")
    left = i
    while left > 0 and yy[left] > half:
        left -= 1
    right = i
    while right < yy.size - 1 and yy[right] > half:
        right += 1

    def cross(a: int, b: int) -> float:
        ya, yb = yy[a], yy[b]
        return (
            float(tt[a] + (half - ya) * (tt[b] - tt[a]) / (yb - ya)) if yb != ya else float(tt[a])
        )

    tl = cross(left, left + 1) if yy[left] <= half else float(tt[0])
    tr = cross(right - 1, right) if yy[right] <= half else float(tt[-1])
    return tr - tl


def width_samples(y: ArrayLike) -> float:
    """FWHM in samples of the highest peak (scipy.signal.peak_widths)."""
    yy = np.asarray(y, float)
    return float(peak_widths(yy, [int(np.argmax(yy))], rel_height=0.5)[0][0])


def denoise_metrics(t: ArrayLike, original: ArrayLike, denoised: ArrayLike) -> dict[str, float]:
    """The seed's six metrics of a denoised profile against the original (noisy) one."""
    yo, yd = np.asarray(original, float), np.asarray(denoised, float)
    if yo.shape != yd.shape:
        raise ValueError(f"denoised must have the shape of original {yo.shape}, got {yd.shape}")
    diff = yd - yo
    sd = float(np.std(diff))
    return {
        "height": height(yd),
        "width": fwhm(t, yd),
        "width_samples": width_samples(yd),
        "signal_std": float(np.std(yd)),
        "difference_std": sd,
        "difference_snr": float(abs(np.mean(diff)) / sd) if sd > 0 else float("inf"),
        "improvement_snr": 1.0 / sd if sd > 0 else float("inf"),
    }


def truth_metrics(t: ArrayLike, estimate: ArrayLike, truth: ArrayLike) -> dict[str, float]:
    """RMSE to the truth and the errors of mean residence time (s) and variance (s^2)."""
    ye, yt = np.asarray(estimate, float), np.asarray(truth, float)
    me, mt = moments(t, ye), moments(t, yt)
    return {
        "rmse_truth": float(np.sqrt(np.mean((ye - yt) ** 2))),
        "mrt_error": me.mean - mt.mean,
        "variance_error": me.variance - mt.variance,
    }
