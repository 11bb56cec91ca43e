"""Noise synthesis and characterization for tracer profiles (seed 6.1.3.2).

Model of the measurement: y = s + e_white + e_pink + k s eta, with e_white white noise
(flat spectrum), e_pink 1/f noise and a signal-proportional term (k times the signal times
unit white noise). Characterization from the residual r = y - s_fit:

1. variance-vs-signal regression: E[r^2] = a + b s_fit^2 (least squares, a, b >= 0), giving
   the signal-independent variance a and the proportional coefficient k = sqrt(b);
2. the residual rescaled to constant variance, r / sqrt(1 + (b/a) s_fit^2), has the
   one-sided periodogram fitted (non-negative least squares) by P(f) = W + P1 / f; the white
   variance is W (f_N - f_1) and the pink variance P1 ln(f_N / f_1) over the band
   [f_1 = 1/T, f_N = Nyquist];
3. the spectral slope is the ordinary least-squares slope of log P vs log f (0 white,
   -1 pink, -2 red/Brownian; Press 1978, Comments Astrophys. 7, 103).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import nnls
from scipy.signal import periodogram

__all__ = ["NoiseReport", "white_noise", "pink_noise", "synthesize", "characterize"]


def _rng(seed: int | np.random.Generator | None) -> np.random.Generator:
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


def white_noise(n: int, std: float, seed: int | np.random.Generator | None = None) -> NDArray:
    """Gaussian white noise of standard deviation `std`."""
    if std < 0:
        raise ValueError(f"std must be >= 0, got {std!r}")
    return _rng(seed).normal(0.0, std, int(n))


def pink_noise(n: int, std: float, seed: int | np.random.Generator | None = None) -> NDArray:
    """1/f (pink) Gaussian noise of standard deviation ``std`` (the project's one pink-noise
    generator: RTD profiles and the plant's NIR probe).

    Spectral shaping (Timmer & Koenig 1995, A&A 300, 707): complex Gaussian Fourier
    coefficients with amplitude f^(-1/2) for f > 0, zero at f = 0; for even n the Nyquist
    coefficient is real and scaled by sqrt(2) to keep the power of its bin; inverse real FFT,
    standardised to zero mean and unit standard deviation, times ``std``.
    """
    if std < 0:
        raise ValueError(f"std must be >= 0, got {std!r}")
    n = int(n)
    if n < 2:
        raise ValueError(f"n must be >= 2, got {n!r}")
    rng = _rng(seed)
    f = np.fft.rfftfreq(n)
    amp = np.zeros_like(f)
    amp[1:] = f[1:] ** -0.5
    coef = amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size))
    if n % 2 == 0:
        coef[-1] = coef[-1].real * np.sqrt(2.0)
    x = np.fft.irfft(coef, n)
    sd = x.std()
    return (x - x.mean()) / sd * std if sd > 0 else x


def synthesize(
    signal: ArrayLike,
    white_std: float = 0.0,
    pink_std: float = 0.0,
    proportional: float = 0.0,
    seed: int | np.random.Generator | None = None,
) -> NDArray:
    """Noise realization (not including the signal): white + pink + proportional * s * N(0,1)."""
    s = np.asarray(signal, dtype=float)
    if proportional < 0:
        raise ValueError(f"proportional must be >= 0, got {proportional!r}")
    rng = _rng(seed)
    return (
        white_noise(s.size, white_std, rng)
        + pink_noise(s.size, pink_std, rng)
        + proportional * s * rng.normal(size=s.size)
    )


@dataclass(frozen=True)
class NoiseReport:
    """Estimated noise components of a residual."""

    sigma_white: float
    sigma_pink: float
    k_proportional: float
    spectral_slope: float
    sigma_total: float
    sigma_baseline: float
    n: int

    def as_dict(self) -> dict:
        return asdict(self)


def characterize(t: ArrayLike, y: ArrayLike, y_fit: ArrayLike) -> NoiseReport:
    """Estimate white, pink and signal-proportional noise from y and a fitted model y_fit.

    ``t`` must be (nearly) uniform; see the module docstring for the method.
    """
    tt = np.asarray(t, dtype=float)
    yy = np.asarray(y, dtype=float)
    ff = np.asarray(y_fit, dtype=float)
    if not (tt.shape == yy.shape == ff.shape) or tt.ndim != 1:
        raise ValueError(
            f"t, y, y_fit must be 1-D of equal shape, got {tt.shape}, {yy.shape}, {ff.shape}"
        )
    if tt.size < 16:
        raise ValueError(f"need at least 16 points to characterize noise, got {tt.size}")
    if not (np.all(np.isfinite(yy)) and np.all(np.isfinite(ff))):
        raise ValueError("y and y_fit must be finite, got NaN or inf")
    r = yy - ff
    design = np.column_stack([np.ones_like(ff), ff**2])
    (a, b), _ = nnls(design, r**2)
    if a <= 0:
        a = max(float(np.var(r)) * 1e-6, 1e-300)
    rc = r / np.sqrt(1.0 + (b / a) * ff**2)
    fs = 1.0 / float(np.median(np.diff(tt)))
    f, p = periodogram(rc, fs=fs, detrend="constant", scaling="density")
    f, p = f[1:], p[1:]
    (w, p1), _ = nnls(np.column_stack([np.ones_like(f), 1.0 / f]), p)
    f1, fn = f[0], f[-1]
    var_w = w * (fn - f1)
    var_p = p1 * np.log(fn / f1)
    # rescale the spectral split to the regression's signal-independent variance
    tot = var_w + var_p
    if tot > 0:
        var_w, var_p = a * var_w / tot, a * var_p / tot
    pos = p > 0
    slope = (
        float(np.polyfit(np.log(f[pos]), np.log(p[pos]), 1)[0]) if pos.sum() > 2 else float("nan")
    )
    thr = 0.02 * float(np.max(np.abs(ff))) if np.any(ff) else np.inf
    base = np.abs(ff) <= thr
    sb = float(np.std(r[base], ddof=1)) if base.sum() > 2 else float("nan")
    return NoiseReport(
        sigma_white=float(np.sqrt(var_w)),
        sigma_pink=float(np.sqrt(var_p)),
        k_proportional=float(np.sqrt(b)),
        spectral_slope=slope,
        sigma_total=float(np.std(r, ddof=1)),
        sigma_baseline=sb,
        n=int(tt.size),
    )
