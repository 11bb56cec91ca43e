"""Denoising of tracer profiles (seed 6.1.3.3), each returning an array of the input length.

Methods
-------
- ``sliding_average``: unweighted moving average of M points. ``mode="trailing"`` is the
  seed's ``pandas.Series(C).rolling(M).mean()`` (lags the signal by (M-1)/2 samples); its first
  M-1 values, NaN in pandas, are the expanding mean. ``mode="centred"`` is symmetric (MATLAB
  ``movmean``), shrinking the window at the ends.
- ``savitzky_golay``: ``scipy.signal.savgol_filter`` (defaults window 11, order 3, as the seed).
- ``fft_lowpass``: ideal low-pass on the mirror-extended signal (even extension removes the
  end discontinuity; this equals truncating the orthonormal DCT-II, an orthogonal projection). Default cutoff rule (documented in docs/rtd.md): the noise floor is the
  median power of the upper half of the spectrum; the cutoff is the highest frequency at which
  the 5-bin running median of the power still exceeds 10x that floor.
- ``wavelet``: discrete wavelet shrinkage with PyWavelets; defaults follow MATLAB ``wdenoise``:
  ``sym4``, level min(floor(log2 N), pywt.dwt_max_level), half-point symmetric extension,
  noise sigma = median(|d_1|)/0.6745 from the finest details ("LevelIndependent"), empirical
  Bayes thresholding with a quasi-Cauchy prior and the posterior median rule (Johnstone &
  Silverman 2005, Ann. Stat. 33, 1700; mixing weight by marginal maximum likelihood bounded
  by the universal threshold; a Laplace prior is available), approximation coefficients
  untouched. Other rules: ``sure`` (SureShrink,
  Donoho & Johnstone 1995), ``universal`` (VisuShrink), with soft/hard/garrote shrinkage by
  ``pywt.threshold``.

Automatic meta-parameters (``auto_*``) minimize Mallows' Cp / Stein's unbiased risk estimate
R = mean((y - y_hat)^2) - sigma^2 + 2 sigma^2 df / N, with sigma from the finest wavelet
details and df the trace of the linear smoother (sliding average, Savitzky-Golay), the number
of retained Fourier coefficients (FFT) or of nonzero wavelet coefficients (soft thresholding;
Zou, Hastie & Tibshirani 2007). ``denoise(y, "auto")`` picks the method with the lowest R.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pywt
from numpy.typing import ArrayLike, NDArray
from scipy import optimize, special
from scipy.fft import dct
from scipy.ndimage import median_filter
from scipy.signal import savgol_coeffs, savgol_filter

__all__ = [
    "METHODS",
    "DenoiseResult",
    "sliding_average",
    "savitzky_golay",
    "fft_lowpass",
    "fft_cutoff_rule",
    "wavelet",
    "wavelet_level",
    "ebayes_posterior_median",
    "ebayes_weight",
    "threshold_from_weight",
    "noise_sigma",
    "risk",
    "auto_sliding_average",
    "auto_savitzky_golay",
    "auto_fft",
    "auto_wavelet",
    "denoise",
]

METHODS = ("sa", "sa_centred", "sg", "fft", "wavelet", "auto")


def _arr(y: ArrayLike, min_n: int = 4) -> NDArray[np.float64]:
    yy = np.asarray(y, dtype=float)
    if yy.ndim != 1 or yy.size < min_n:
        raise ValueError(f"y must be 1-D with >= {min_n} points, got shape {yy.shape}")
    if not np.all(np.isfinite(yy)):
        raise ValueError("y must be finite, got NaN or inf")
    return yy


@dataclass(frozen=True)
class DenoiseResult:
    """A denoised signal with its method, meta-parameters and estimated risk."""

    y: NDArray[np.float64]
    method: str
    params: dict = field(default_factory=dict)
    risk: float = float("nan")
    df: float = float("nan")


# ---------------------------------------------------------------------------------------------
# sliding average and Savitzky-Golay
# ---------------------------------------------------------------------------------------------


def sliding_average(y: ArrayLike, window: int = 5, mode: str = "trailing") -> NDArray[np.float64]:
    """Moving average of `window` points; see module docstring for the modes."""
    yy = _arr(y, 2)
    m = int(window)
    if m < 1 or m > yy.size:
        raise ValueError(f"window must be in [1, {yy.size}], got {window!r}")
    if mode == "trailing":
        c = np.cumsum(np.concatenate([[0.0], yy]))
        out = np.empty_like(yy)
        k = np.arange(1, yy.size + 1)
        lo = np.maximum(k - m, 0)
        out[:] = (c[k] - c[lo]) / (k - lo)
        return out
    if mode in ("centred", "centered"):
        h = m // 2
        c = np.cumsum(np.concatenate([[0.0], yy]))
        i = np.arange(yy.size)
        lo = np.maximum(i - h, 0)
        hi = np.minimum(i + (m - 1 - h) + 1, yy.size)
        return (c[hi] - c[lo]) / (hi - lo)
    raise ValueError(f"mode must be 'trailing' or 'centred', got {mode!r}")


def savitzky_golay(y: ArrayLike, window: int = 11, order: int = 3) -> NDArray[np.float64]:
    """Savitzky-Golay smoothing (Savitzky & Golay 1964), scipy.signal.savgol_filter, mode 'interp'."""
    yy = _arr(y)
    w, o = int(window), int(order)
    if w % 2 == 0 or w < 3:
        raise ValueError(f"window must be odd and >= 3, got {window!r}")
    if w > yy.size:
        raise ValueError(f"window must be <= len(y) = {yy.size}, got {window!r}")
    if not 0 <= o < w:
        raise ValueError(f"order must be in [0, window), got {order!r}")
    return savgol_filter(yy, w, o)


# ---------------------------------------------------------------------------------------------
# FFT low-pass
# ---------------------------------------------------------------------------------------------


def _mirror_fft(yy: NDArray) -> NDArray[np.complex128]:
    return np.fft.rfft(np.concatenate([yy, yy[::-1]]))


def fft_cutoff_rule(y: ArrayLike, factor: float = 10.0) -> int:
    """Cutoff index (number of retained rfft bins of the mirror-extended signal) by the
    noise-floor rule of the module docstring."""
    yy = _arr(y)
    p = np.abs(_mirror_fft(yy)) ** 2
    floor = float(np.median(p[p.size // 2 :]))
    smooth = median_filter(p, size=5, mode="nearest")
    above = np.nonzero(smooth > factor * floor)[0]
    return int(max(above[-1] + 1 if above.size else 1, 2))


def fft_lowpass(y: ArrayLike, cutoff: int | None = None) -> NDArray[np.float64]:
    """Ideal low-pass keeping the first `cutoff` rfft bins of the mirror-extended signal.

    ``cutoff=None`` applies :func:`fft_cutoff_rule`. The cutoff frequency in Hz is
    cutoff / (2 N dt).
    """
    yy = _arr(y)
    coef = _mirror_fft(yy)
    k = fft_cutoff_rule(yy) if cutoff is None else int(cutoff)
    if not 1 <= k <= coef.size:
        raise ValueError(f"cutoff must be in [1, {coef.size}], got {cutoff!r}")
    coef[k:] = 0.0
    return np.fft.irfft(coef, 2 * yy.size)[: yy.size]


# ---------------------------------------------------------------------------------------------
# wavelets
# ---------------------------------------------------------------------------------------------


def wavelet_level(n: int, wavelet: str = "sym4") -> int:
    """MATLAB wdenoise default level: min(floor(log2 N), wmaxlev(N, wavelet))."""
    w = pywt.Wavelet(wavelet)
    return max(1, min(int(np.floor(np.log2(n))), pywt.dwt_max_level(n, w.dec_len)))


def noise_sigma(y: ArrayLike, wavelet: str = "sym4") -> float:
    """sigma = median(|d_1|) / 0.6745 from the finest-level details (Donoho & Johnstone 1994)."""
    yy = _arr(y)
    d1 = pywt.wavedec(yy, wavelet, mode="symmetric", level=1)[-1]
    return float(np.median(np.abs(d1)) / 0.6745)


def _mills_upper(z: NDArray) -> NDArray:
    """(1 - Phi(z)) / phi(z), stable."""
    return np.sqrt(np.pi / 2) * special.erfcx(z / np.sqrt(2))


def _phi(x: NDArray) -> NDArray:
    return np.exp(-0.5 * np.asarray(x, float) ** 2) / np.sqrt(2 * np.pi)


def _beta(x: NDArray, prior: str, a: float) -> NDArray:
    """beta(x) = g(x)/phi(x) - 1, g the prior convolved with N(0, 1) (Johnstone & Silverman
    2005). Laplace(a): (a/2)(R(x+a) + R(a-x)) - 1 with R the upper Mills ratio;
    quasi-Cauchy: (exp(x^2/2) - 1)/x^2 - 1, -1/2 at x = 0. Capped at 1e280."""
    x = np.abs(np.asarray(x, dtype=float))
    if prior == "laplace":
        b = 0.5 * a * (_mills_upper(x + a) + _mills_upper(a - x)) - 1.0
    else:
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            b = np.where(x > 0, np.expm1(np.minimum(0.5 * x**2, 700.0)) / x**2 - 1.0, -0.5)
    return np.minimum(b, 1e280)


def _threshold_equation(t: NDArray, w: float, prior: str, a: float) -> NDArray:
    """Zero at the posterior-median threshold t(w) (increasing in t)."""
    t = np.asarray(t, dtype=float)
    if prior == "laplace":
        return special.ndtr(t - a) - _phi(t - a) * (1.0 / w + _beta(t, prior, a)) / a
    return special.ndtr(t) - t * _phi(t) - 0.5 - 0.5 * t**2 * np.exp(-0.5 * t**2) * (1.0 / w - 1.0)


def threshold_from_weight(w: float, prior: str = "cauchy", a: float = 0.5) -> float:
    """Posterior-median threshold for mixing weight w: |x| below it shrinks to exactly 0."""
    if not 0 < w <= 1:
        raise ValueError(f"w must be in (0, 1], got {w!r}")

    def f(t: float) -> float:
        return float(_threshold_equation(np.array([t]), w, prior, a)[0])

    t0 = 1e-4  # f(0) = 0 for the quasi-Cauchy prior; f < 0 just above 0 when w < 1
    if f(t0) >= 0:
        return 0.0
    return float(optimize.brentq(f, t0, 40.0, xtol=1e-12)) if f(40.0) > 0 else 40.0


def _weight_from_threshold(t: float, prior: str, a: float) -> float:
    """Inverse of threshold_from_weight (closed form from the threshold equation)."""
    if prior == "laplace":
        inv = a * special.ndtr(t - a) / _phi(t - a) - float(_beta(np.array([t]), prior, a)[0])
    else:
        inv = 1.0 + (special.ndtr(t) - t * _phi(t) - 0.5) / (np.sqrt(np.pi / 2) * _phi(t) * t**2)
    return float(np.clip(1.0 / inv, 1e-300, 1.0)) if np.isfinite(inv) and inv > 0 else 1.0


def _postmed_laplace(x: NDArray, w: float, a: float) -> NDArray:
    ax = np.abs(x)
    xma = ax - a
    zz = (
        _phi(xma) * (1.0 / w - 1.0)
        + 0.5 * a * (_phi(xma) * _mills_upper(ax + a) + special.ndtr(xma))
    ) / a
    zz = np.where(xma > 25, 0.5, zz)
    mucor = special.ndtri(np.clip(zz, 0.0, 1.0))
    return np.sign(x) * np.maximum(0.0, xma - mucor)


def _postmed_cauchy(x: NDArray, w: float | NDArray) -> NDArray:
    """Posterior median under the quasi-Cauchy prior: the mu in [0, |x|] where the posterior
    probability of theta <= mu is 1/2, found by vectorized bisection (45 halvings); zero where
    the median is zero (below the threshold t(w)); |x| >= 20 uses the asymptote |x| - 2/|x|.
    ``w`` may be a scalar or an array broadcast against x."""
    z = np.abs(np.asarray(x, dtype=float))
    ww = np.broadcast_to(np.asarray(w, dtype=float), z.shape)
    out = np.where(z >= 20, z - 2.0 / np.maximum(z, 1e-300), 0.0)
    m = z < 20
    if np.any(m):
        zm, wm = z[m], ww[m]
        rhs = 0.5 * (1.0 + np.exp(-0.5 * zm**2) * (zm**2 * (1.0 / wm - 1.0) - 1.0))

        def g(mu: NDArray, zz: NDArray, r: NDArray) -> NDArray:
            h = zz - mu
            ph = _phi(h)
            left = special.ndtr(h) - zz * ph + (zz * mu - 1.0) * ph * _mills_upper(mu)
            return r - left

        # g increases in mu; the median is 0 unless g < 0 just above 0
        act = g(np.full_like(zm, 1e-7), zm, rhs) <= 0
        za, ra = zm[act], rhs[act]
        lo = np.zeros_like(za)
        hi = za.copy()
        for _ in range(45):
            mid = 0.5 * (lo + hi)
            up = g(mid, za, ra) <= 0
            lo = np.where(up, mid, lo)
            hi = np.where(up, hi, mid)
        res = np.zeros_like(zm)
        res[act] = 0.5 * (lo + hi)
        out[m] = res
    out = np.where(out < 1e-7, 0.0, out)
    return np.sign(x) * out


def ebayes_weight(x: ArrayLike, prior: str = "cauchy", a: float = 0.5) -> float:
    """Marginal maximum likelihood mixing weight w in [w_lo, 1] (Johnstone & Silverman 2005):
    the root of the score sum beta(x_i) / (1 + w beta(x_i)); w_lo puts the threshold at the
    universal sqrt(2 log n)."""
    if prior not in ("cauchy", "laplace"):
        raise ValueError(f"prior must be 'cauchy' or 'laplace', got {prior!r}")
    xx = np.asarray(x, dtype=float)
    if xx.size == 0:
        return 1.0
    tuniv = float(np.sqrt(2.0 * np.log(max(xx.size, 2))))
    wlo = _weight_from_threshold(tuniv, prior, a)
    beta = _beta(xx, prior, a)

    def score(w: float) -> float:
        return float(np.sum(beta / (1.0 + w * beta)))

    if score(1.0) >= 0:
        return 1.0
    if score(wlo) <= 0:
        return wlo
    return float(optimize.brentq(score, wlo, 1.0, xtol=1e-12))


def ebayes_posterior_median(
    x: ArrayLike, prior: str = "cauchy", a: float = 0.5
) -> tuple[NDArray[np.float64], float]:
    """Empirical Bayes posterior-median shrinkage of unit-variance coefficients x
    (Johnstone & Silverman 2005, Ann. Stat. 33, 1700).

    Prior (1 - w) delta_0 + w gamma, gamma quasi-Cauchy (default, the prior of MATLAB
    ``wdenoise``) or Laplace(a); w from :func:`ebayes_weight`. Returns the shrunk coefficients
    and w.
    """
    xx = np.asarray(x, dtype=float)
    w = ebayes_weight(xx, prior, a)
    mu = _postmed_cauchy(xx, w) if prior == "cauchy" else _postmed_laplace(xx, w, a)
    return mu, w


def _sure_threshold(x: NDArray) -> float:
    """SureShrink threshold for unit-variance x (hybrid with universal for sparse levels)."""
    n = x.size
    if n == 0:
        return 0.0
    tuniv = np.sqrt(2.0 * np.log(max(n, 2)))
    eta = (np.sum(x**2) - n) / n
    crit = np.log2(max(n, 2)) ** 1.5 / np.sqrt(n)
    if eta < crit:
        return float(tuniv)
    a2 = np.sort(x**2)
    cs = np.cumsum(a2)
    k = np.arange(1, n + 1)
    risks = (n - 2 * k + cs + (n - k) * a2) / n
    return float(min(np.sqrt(a2[int(np.argmin(risks))]), tuniv))


def wavelet(
    y: ArrayLike,
    wavelet: str = "sym4",
    level: int | None = None,
    method: str = "bayes",
    mode: str = "soft",
    noise: str = "level_independent",
    threshold: float | None = None,
    prior: str = "cauchy",
) -> NDArray[np.float64]:
    """Discrete wavelet denoising (defaults reproduce MATLAB ``wdenoise``; module docstring).

    ``method``: ``bayes`` (posterior median; ``prior`` 'cauchy' or 'laplace'), ``sure``,
    ``universal``; ``threshold`` (in units
    of sigma) overrides the rule with a fixed threshold applied by ``pywt.threshold(mode)``.
    ``noise``: ``level_independent`` (sigma from level 1) or ``level_dependent`` (per level).
    """
    return _wavelet(y, wavelet, level, method, mode, noise, threshold, prior)[0]


def _wavelet(y, wname, level, method, mode, noise, threshold, prior="cauchy"):
    yy = _arr(y)
    if wname not in pywt.wavelist(kind="discrete"):
        raise ValueError(f"wavelet must be a discrete PyWavelets name, got {wname!r}")
    lev = wavelet_level(yy.size, wname) if level is None else int(level)
    if lev < 1:
        raise ValueError(f"level must be >= 1, got {level!r}")
    if method not in ("bayes", "sure", "universal"):
        raise ValueError(f"method must be 'bayes', 'sure' or 'universal', got {method!r}")
    if mode not in ("soft", "hard", "garrote"):
        raise ValueError(f"mode must be 'soft', 'hard' or 'garrote', got {mode!r}")
    if noise not in ("level_independent", "level_dependent"):
        raise ValueError(f"noise must be 'level_independent' or 'level_dependent', got {noise!r}")
    coeffs = pywt.wavedec(yy, wname, mode="symmetric", level=lev)
    sig1 = float(np.median(np.abs(coeffs[-1])) / 0.6745)
    if threshold is None and method == "bayes" and prior == "cauchy" and sig1 > 0:
        # one vectorized posterior-median solve for all levels (per-level weights)
        sigs = [
            float(np.median(np.abs(d)) / 0.6745) if noise == "level_dependent" else sig1
            for d in coeffs[1:]
        ]
        sigs = [sg if sg > 0 else sig1 for sg in sigs]
        xs = [d / sg for d, sg in zip(coeffs[1:], sigs)]
        ws = np.concatenate([np.full(x.size, ebayes_weight(x, "cauchy")) for x in xs])
        mu = _postmed_cauchy(np.concatenate(xs), ws)
        parts = np.split(mu, np.cumsum([x.size for x in xs])[:-1])
        out = [coeffs[0]] + [p * sg for p, sg in zip(parts, sigs)]
        nnz = coeffs[0].size + int(np.count_nonzero(mu))
        rec = pywt.waverec(out, wname, mode="symmetric")[: yy.size]
        return rec, nnz, lev
    out = [coeffs[0]]
    nnz = coeffs[0].size
    for d in coeffs[1:]:
        sig = float(np.median(np.abs(d)) / 0.6745) if noise == "level_dependent" else sig1
        if sig <= 0:
            out.append(d.copy())
            nnz += int(np.count_nonzero(d))
            continue
        x = d / sig
        if threshold is not None:
            dn = pywt.threshold(x, float(threshold), mode=mode)
        elif method == "bayes":
            dn, _ = ebayes_posterior_median(x, prior)
        elif method == "sure":
            dn = pywt.threshold(x, _sure_threshold(x), mode=mode)
        else:
            dn = pywt.threshold(x, np.sqrt(2 * np.log(max(yy.size, 2))), mode=mode)
        nnz += int(np.count_nonzero(dn))
        out.append(dn * sig)
    rec = pywt.waverec(out, wname, mode="symmetric")[: yy.size]
    return rec, nnz, lev


# ---------------------------------------------------------------------------------------------
# automatic meta-parameters
# ---------------------------------------------------------------------------------------------


def risk(y: ArrayLike, y_hat: ArrayLike, df: float, sigma: float) -> float:
    """Mallows' Cp / SURE estimate of mean squared error to the truth per sample."""
    yy, yh = np.asarray(y, float), np.asarray(y_hat, float)
    return float(np.mean((yy - yh) ** 2) - sigma**2 + 2.0 * sigma**2 * df / yy.size)


def _sigma(yy: NDArray, sigma: float | None) -> float:
    s = noise_sigma(yy) if sigma is None else float(sigma)
    if not s > 0:
        raise ValueError(f"sigma must be > 0, got {s!r}")
    return s


def _windows(n: int, lo: int, hi: int) -> list[int]:
    return [w for w in range(lo, min(hi, n // 2) + 1, 2)] or [lo]


def auto_sliding_average(
    y: ArrayLike, sigma: float | None = None, max_window: int = 51, mode: str = "centred"
) -> DenoiseResult:
    """Window M (odd, 3..max_window) minimizing Cp; df = N/M for the centred average."""
    yy = _arr(y)
    s = _sigma(yy, sigma)
    best = None
    for m in _windows(yy.size, 3, max_window):
        yh = sliding_average(yy, m, "centred")
        r = risk(yy, yh, yy.size / m, s)
        if best is None or r < best[0]:
            best = (r, m)
    r, m = best  # type: ignore[misc]
    return DenoiseResult(sliding_average(yy, m, mode), f"sa_{mode}", {"window": m}, r, yy.size / m)


def auto_savitzky_golay(
    y: ArrayLike, sigma: float | None = None, order: int = 3, max_window: int = 61
) -> DenoiseResult:
    """Window (odd, order+2..max_window) minimizing Cp; df = N * h_00 (central SG weight)."""
    yy = _arr(y)
    s = _sigma(yy, sigma)
    best = None
    lo = order + 2 if (order + 2) % 2 == 1 else order + 3
    for w in _windows(yy.size, lo, max_window):
        yh = savgol_filter(yy, w, order)
        df = yy.size * float(savgol_coeffs(w, order)[w // 2])
        r = risk(yy, yh, df, s)
        if best is None or r < best[0]:
            best = (r, w, yh, df)
    r, w, yh, df = best  # type: ignore[misc]
    return DenoiseResult(yh, "sg", {"window": w, "order": order}, r, df)


def auto_fft(y: ArrayLike, sigma: float | None = None) -> DenoiseResult:
    """Cutoff (retained bins) minimizing Cp; df = number of retained bins."""
    yy = _arr(y)
    s = _sigma(yy, sigma)
    n = yy.size
    # the low-pass of the even (mirror) extension keeping k rfft bins is exactly the DCT-II
    # truncation to k coefficients, an orthogonal projection: RSS = sum of removed c_j^2
    c2 = dct(yy, norm="ortho") ** 2
    removed = np.cumsum(c2[::-1])[::-1]  # removed[k] = sum_{j >= k} c_j^2
    ks = np.arange(1, n + 1)
    rss = np.append(removed[1:], 0.0) / n
    risks = rss - s**2 + 2 * s**2 * ks / n
    k = int(ks[np.argmin(risks)])
    return DenoiseResult(
        fft_lowpass(yy, k), "fft", {"cutoff": k}, float(risks[k - 1]), float(min(k, n))
    )


def auto_wavelet(
    y: ArrayLike, sigma: float | None = None, wavelet_name: str = "sym4"
) -> DenoiseResult:
    """SureShrink (soft) with the decomposition level minimizing SURE."""
    yy = _arr(y)
    s = _sigma(yy, sigma)
    best = None
    for lev in range(1, wavelet_level(yy.size, wavelet_name) + 1):
        yh, nnz, _ = _wavelet(yy, wavelet_name, lev, "sure", "soft", "level_independent", None)
        r = risk(yy, yh, nnz, s)
        if best is None or r < best[0]:
            best = (r, lev, yh, nnz)
    r, lev, yh, nnz = best  # type: ignore[misc]
    return DenoiseResult(
        yh, "wavelet", {"wavelet": wavelet_name, "level": lev, "method": "sure"}, r, nnz
    )


def denoise(y: ArrayLike, method: str = "wavelet", **params) -> DenoiseResult:
    """Denoise with a named method ('sa', 'sa_centred', 'sg', 'fft', 'wavelet') and its
    parameters (defaults: seed settings / MATLAB defaults), or 'auto': every method with its
    automatic meta-parameter, returning the one with the lowest estimated risk."""
    yy = _arr(y)
    s = noise_sigma(yy)
    if method == "auto":
        cands = [
            auto_sliding_average(yy, s),
            auto_savitzky_golay(yy, s),
            auto_fft(yy, s),
            auto_wavelet(yy, s),
        ]
        return min(cands, key=lambda c: c.risk)
    if method == "sa":
        yh = sliding_average(yy, params.get("window", 5), "trailing")
        df = yy.size / params.get("window", 5)
    elif method == "sa_centred":
        yh = sliding_average(yy, params.get("window", 5), "centred")
        df = yy.size / params.get("window", 5)
    elif method == "sg":
        w, o = params.get("window", 11), params.get("order", 3)
        yh = savitzky_golay(yy, w, o)
        df = yy.size * float(savgol_coeffs(w, o)[w // 2])
    elif method == "fft":
        k = params.get("cutoff") or fft_cutoff_rule(yy)
        yh = fft_lowpass(yy, k)
        params = {**params, "cutoff": k}
        df = float(min(k, yy.size))
    elif method == "wavelet":
        kw = {
            k: params[k] for k in ("level", "method", "mode", "noise", "threshold") if k in params
        }
        yh, nnz, lev = _wavelet(
            yy,
            params.get("wavelet", "sym4"),
            kw.get("level"),
            kw.get("method", "bayes"),
            kw.get("mode", "soft"),
            kw.get("noise", "level_independent"),
            kw.get("threshold"),
        )
        params = {"wavelet": params.get("wavelet", "sym4"), "level": lev, **kw}
        df = float(nnz)
    else:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    return DenoiseResult(yh, method, dict(params), risk(yy, yh, df, s), df)
