"""NIR sensor noise of the seed (chapter 6.1.3.2): white, pink (1/f), proportional, outliers.

measured(t) = signal(t) + baseline_offset + white + pink + proportional_rel * |signal| * N(0, 1)
              + outliers

with white ~ N(0, white_sd^2) i.i.d., pink a 1/f process of standard deviation ``pink_sd``
(``twin_core.rtd.noise.pink_noise``: the spectrum of white noise shaped, Timmer & Koenig 1995,
A&A 300:707), and outliers: with probability ``outlier_prob`` per sample a
Laplace-distributed spike of scale ``outlier_sd / sqrt(2)`` (standard deviation outlier_sd).
The seed reports baseline statistics beyond t = 120 s of mean -0.03 to -0.074 and standard
deviation 0.125 to 0.132 % w/w (docs/seed.md); the defaults of ``NIRNoise`` give -0.05 / 0.122.
"""

from __future__ import annotations

import numpy as np

from schemas.line import NIRNoise
from twin_core.rtd.noise import pink_noise


def add_nir_noise(
    signal: np.ndarray, noise: NIRNoise, seed: int | np.random.Generator | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Measured NIR reading from the noise-free sensor signal (% w/w).

    Returns ``(measured, outlier_mask)``. NaN samples of ``signal`` stay NaN.
    """
    rng = np.random.default_rng(seed)
    s = np.asarray(signal, dtype=float)
    n = s.size
    y = s + noise.baseline_offset
    y = y + noise.white_sd * rng.standard_normal(n)
    y = y + (pink_noise(n, noise.pink_sd, rng) if n >= 2 else np.zeros(n))
    y = y + noise.proportional_rel * np.abs(np.nan_to_num(s)) * rng.standard_normal(n)
    outliers = rng.random(n) < noise.outlier_prob
    if outliers.any():
        y[outliers] += rng.laplace(0.0, noise.outlier_sd / np.sqrt(2.0), int(outliers.sum()))
    return y, outliers


def noise_sd(signal: np.ndarray, noise: NIRNoise) -> np.ndarray:
    """Standard deviation of the non-outlier noise at each sample (for weighting), % w/w."""
    s = np.abs(np.nan_to_num(np.asarray(signal, dtype=float)))
    return np.sqrt(noise.white_sd**2 + noise.pink_sd**2 + (noise.proportional_rel * s) ** 2)


def scaled_noise(noise: NIRNoise, scale: float) -> NIRNoise:
    """The noise with its white, pink and proportional parts times ``scale`` (outliers and the
    baseline offset kept): "k x the seed's noise"."""
    if not (np.isfinite(scale) and scale >= 0):
        raise ValueError(f"scale must be >= 0, got {scale!r}")
    return noise.model_copy(
        update={
            "white_sd": noise.white_sd * scale,
            "pink_sd": noise.pink_sd * scale,
            "proportional_rel": noise.proportional_rel * scale,
        }
    )
