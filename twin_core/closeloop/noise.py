"""The NIR noise levels estimated from the recording itself (instead of the declared ones).

The close-loop's decisions weigh the residual with the probe's noise (white, signal-proportional
and 1/f, ``twin_core.plant.NIRNoise``); a real probe's levels are seldom known well. On the
*quiet* samples of a record -- away from every event (refills, tracer pulses, disturbances)
by the blender's lot span, where the declared model's structural errors have
little to show -- the residual r = measured - predicted is mostly probe noise. Per contiguous
quiet segment (Hampel outliers replaced, mean removed) its periodogram is taken, and over all
segments the one-sided spectral density is fitted by non-negative least squares as

    S(f) = w + p1 / f

(white plus 1/f noise; the split of ``twin_core.rtd.noise.characterize``, after Timmer & Koenig
1995 for the 1/f process). The white-like variance w fs / 2 sets the level of the declared
white + proportional pair (the probe's signal hardly moves in quiet segments, so the two cannot
be told apart there: both are scaled by one factor, keeping the declared shape), and p1 gives
the 1/f standard deviation over the whole record, pink_sd^2 = p1 H(N/2) with H the harmonic
number (the discrete band 1/N .. 1/2 of ``twin_core.rtd.noise.pink_noise``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import fft as sp_fft
from scipy.optimize import nnls
from scipy.signal import periodogram

from schemas.line import LineConfig, NIRNoise
from twin_core.closeloop.data import RunData
from twin_core.plant.model import LineModel, rtd_kernel
from twin_core.rtd.outliers import hampel


@dataclass
class NoiseEstimate:
    """Estimated NIR noise: the ``noise`` to use and how it was found."""

    noise: NIRNoise
    white_factor: float
    pink_sd: float
    n_quiet: int
    n_segments: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "white_sd": float(self.noise.white_sd),
            "pink_sd": float(self.noise.pink_sd),
            "proportional_rel": float(self.noise.proportional_rel),
            "white_factor": float(self.white_factor),
            "n_quiet": int(self.n_quiet),
            "n_segments": int(self.n_segments),
        }


def quiet_mask(data: RunData, config: LineConfig, margin_s: float = 30.0) -> np.ndarray:
    """Samples at least ``margin_s`` + the blender's t(F = 0.995) after, and 5 s before, every
    event and tracer pulse, and past the first t(F = 0.995) of the record. (Flow changes are
    the model's inputs and stay in.)"""
    t = data.t_s
    dt = float(t[1] - t[0])
    tk = np.arange(0.0, 3600.0, dt)
    e = rtd_kernel(config.blender, tk)
    f = np.cumsum(e) * dt
    span = float(tk[np.argmax(f >= 0.995)]) if f[-1] >= 0.995 else float(tk[-1])
    m = np.isfinite(data.measured) & (t >= t[0] + span)
    events = list(data.events)
    for p in data.inputs.tracers:
        events.append({"t_s": p.t_s})
    for ev in events:
        t0 = float(ev["t_s"])
        m &= ~((t >= t0 - 5.0) & (t < t0 + span + margin_s))
    return m


def _segments(mask: np.ndarray, min_len: int) -> list[tuple[int, int]]:
    d = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return [(a, b) for a, b in zip(starts, ends) if b - a >= min_len]


def estimate_nir_noise(
    data: RunData, model: LineModel, min_segment: int = 64, margin_s: float = 30.0
) -> NoiseEstimate:
    """Estimate the NIR noise levels from the quiet samples of ``data`` (see the module).

    Returns the declared noise with ``white_sd`` and ``proportional_rel`` scaled by the
    estimated white-like level and ``pink_sd`` replaced by its estimate. Raises ValueError when
    the record has fewer than ``4 * min_segment`` quiet samples in segments of ``min_segment``.
    """
    cfg = model.config
    declared = cfg.sensor.noise
    pred = model.predict(data.inputs)
    r = data.measured - pred
    segs = _segments(quiet_mask(data, cfg, margin_s), min_segment)
    n_quiet = int(sum(b - a for a, b in segs))
    if n_quiet < 4 * min_segment:
        raise ValueError(
            f"record has {n_quiet} quiet samples in segments of >= {min_segment}; need "
            f">= {4 * min_segment} to estimate the noise (declare it instead)"
        )
    dt = float(data.t_s[1] - data.t_s[0])
    fs = 1.0 / dt
    fx, px, wts = [], [], []
    decl_var = []
    for a, b in segs:
        seg = hampel(r[a:b], variant="pearson").y
        f, p = periodogram(seg, fs=fs, detrend="constant", scaling="density")
        fx.append(f[1:])
        px.append(p[1:])
        wts.append(np.full(f.size - 1, 1.0))
        decl_var.append(declared.white_sd**2 + (declared.proportional_rel * np.abs(pred[a:b])) ** 2)
    f_all = np.concatenate(fx)
    p_all = np.concatenate(px)
    (w, p1), _ = nnls(np.column_stack([np.ones_like(f_all), 1.0 / f_all]), p_all)
    var_white = w * fs / 2.0
    decl = float(np.mean(np.concatenate(decl_var)))
    k = float(np.sqrt(var_white / decl)) if decl > 0 else 1.0
    n = data.t_s.size
    harmonic = float(np.log(max(n // 2, 1)) + np.euler_gamma)
    pink = float(np.sqrt(p1 * fs * dt * harmonic)) if p1 > 0 else 0.0
    noise = declared.model_copy(
        update={
            "white_sd": declared.white_sd * k if decl > 0 else float(np.sqrt(var_white)),
            "proportional_rel": declared.proportional_rel * k,
            "pink_sd": pink,
        }
    )
    return NoiseEstimate(noise, k, pink, n_quiet, len(segs))


def with_estimated_noise(data: RunData, model: LineModel) -> tuple[LineModel, NoiseEstimate]:
    """The model with its sensor noise replaced by :func:`estimate_nir_noise` (same effects)."""
    est = estimate_nir_noise(data, model)
    cfg = model.config
    sensor = cfg.sensor.model_copy(update={"noise": est.noise})
    return LineModel(cfg.model_copy(update={"sensor": sensor}), list(model.effects)), est


# ---------------------------------------------------------------------------------------------
# innovations: the residual whitened under the (declared or estimated) coloured noise
# ---------------------------------------------------------------------------------------------
#: longest linear predictor of the whitening (samples): the 1/f part correlates far back; with
#: 512 the trend and whiteness tests of pure seed noise hold their level on 2-hour records
WHITEN_ORDER = 512


def pink_autocorrelation(n_record: int, n_lags: int) -> np.ndarray:
    """Autocorrelation c(k), k = 0..n_lags, of the 1/f process of
    ``twin_core.rtd.noise.pink_noise`` over a record of ``n_record`` samples.

    The generator draws complex Fourier coefficients of power proportional to 1/f_j on the
    bins j = 1..n/2 (none at f = 0), so the process is periodic over the record with
    autocovariance g(k) = sum_j P_j cos(2 pi j k / n), P_j ~ 1/f_j (Wiener-Khinchin; Timmer &
    Koenig 1995); c = g / g(0).
    """
    n = int(n_record)
    if n < 2:
        raise ValueError(f"n_record must be >= 2, got {n_record!r}")
    f = np.fft.rfftfreq(n)
    power = np.zeros_like(f)
    power[1:] = 2.0 / f[1:]
    g = np.fft.irfft(power, n)
    lags = np.arange(int(n_lags) + 1) % n
    return g[lags] / g[0]


def levinson_durbin(r: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Linear predictors of every order from an autocovariance r[0..order] (Levinson 1947,
    Durbin 1960): x_t = sum_{k=1..m} phi[m, k-1] x_{t-k} + e_t with E e_t^2 = v[m].

    Returns (phi, v): phi is (order + 1, order), row m holding the order-m coefficients;
    v the prediction-error variances of orders 0..order.
    """
    r = np.asarray(r, dtype=float)
    p = int(order)
    if r.size < p + 1 or r[0] <= 0:
        raise ValueError(f"r must hold >= order + 1 = {p + 1} values with r[0] > 0")
    phi = np.zeros((p + 1, max(p, 1)))
    v = np.empty(p + 1)
    v[0] = r[0]
    cur = np.zeros(0)
    for m in range(1, p + 1):
        k = (r[m] - cur @ r[m - 1 : 0 : -1]) / v[m - 1]
        cur = np.concatenate([cur - k * cur[::-1], [k]])
        v[m] = v[m - 1] * (1.0 - k * k)
        phi[m, :m] = cur
    return phi, v


class NoiseWhitener:
    """Innovations of a residual under the NIR noise (white + proportional + 1/f).

    With sigma(t) the noise standard deviation (``twin_core.plant.nir.noise_sd``), z = r / sigma
    has unit variance and, at lags k >= 1, the correlation rho(k) = pink_sd^2 c(k) / s^2 of its
    1/f part (:func:`pink_autocorrelation`; s^2 the median of sigma^2: the proportional part
    makes the level vary a little, which the correlation ignores). The innovations

        e_t = (z_t - sum_{k=1..m} phi_{m,k} z_{t-k}) / sqrt(v_m),  m = min(t, order)

    (the Levinson-Durbin predictors of that correlation, :func:`levinson_durbin`) are, under the
    noise, independent N(0, 1): the Cholesky factor of the Toeplitz covariance for the first
    ``order`` samples, a causal FIR filter after. Causal, so an innovation depends on the past
    only: the held-out innovations of a model fitted on the earlier training window are
    independent of the fit, which makes the held-out tests exact (and the fit generalised least
    squares). Without 1/f noise the innovations are z.
    """

    def __init__(
        self,
        sigma: np.ndarray,
        noise: NIRNoise,
        n_record: int | None = None,
        order: int = WHITEN_ORDER,
    ) -> None:
        s = np.asarray(sigma, dtype=float)
        n = s.size
        self.n = n
        self.sigma = s
        self.n_record = int(n_record or n)
        if self.n_record < n:
            raise ValueError(f"n_record must be >= {n} (the record), got {n_record!r}")
        s2 = float(np.median(s**2))
        share = noise.pink_sd**2 / s2 if s2 > 0 else 0.0
        self.share = float(min(share, 1.0))
        self.order = int(min(order, n - 1)) if share > 0 else 0
        if self.order == 0:
            self._fir = None
            return
        rho = share * pink_autocorrelation(self.n_record, self.order)
        rho[0] = 1.0
        phi, v = levinson_durbin(rho, self.order)
        p = self.order
        b = np.concatenate([[1.0], -phi[p, :p]]) / np.sqrt(v[p])
        head = np.zeros((p, p))
        for t in range(p):
            head[t, t] = 1.0
            if t:
                head[t, :t] = -phi[t, :t][::-1]
            head[t] /= np.sqrt(v[t])
        self._head = head
        self._nfft = sp_fft.next_fast_len(n + p, real=True)
        self._fir = sp_fft.rfft(b, self._nfft)

    def __call__(self, z: np.ndarray, exact_head: bool = True) -> np.ndarray:
        """Innovations of ``z`` (length ``n``; fill samples left out with 0 first).

        ``exact_head=False`` filters the first ``order`` samples with the full-order predictor
        too, as if the record were preceded by zeros (no p x p product: the fits' objective;
        their variance is then up to 1 / v_order, a few per cent, too high).
        """
        z = np.asarray(z, dtype=float)
        if z.shape != (self.n,):
            raise ValueError(f"z must have shape ({self.n},), got {z.shape}")
        if self._fir is None:
            return z.copy()
        e = sp_fft.irfft(sp_fft.rfft(z, self._nfft) * self._fir, self._nfft)[: self.n]
        if exact_head:
            p = self.order
            e[:p] = self._head @ z[:p]
        return e

    def gram(self, a: np.ndarray) -> np.ndarray:
        """A'CA for the columns of ``a`` (n x k), C = S R S the covariance these innovations
        whiten: S = diag(sigma), R = (1 - s) I + s C_pink with s the 1/f share of the variance
        and C_pink the correlation of :func:`pink_autocorrelation` (circulant over
        ``n_record``, so A'C_pink A = Re(F^H diag(lambda) F) / g(0), F = rfft(A) on
        ``n_record`` points, lambda the 1/f power; Wiener-Khinchin). The variance of linear
        estimates A'r under the noise (sandwich covariances; White 1980 with C coloured)."""
        a = np.asarray(a, dtype=float)
        if a.ndim == 1:
            a = a[:, None]
        if a.shape[0] != self.n:
            raise ValueError(f"a must have {self.n} rows, got {a.shape[0]}")
        sa = a * self.sigma[:, None]
        g = (1.0 - self.share) * (sa.T @ sa)
        if self.share > 0:
            big_n = self.n_record
            f = np.fft.rfftfreq(big_n)
            lam = np.zeros_like(f)
            lam[1:] = 2.0 / f[1:]
            mult = np.full(f.size, 2.0)
            mult[0] = 1.0
            if big_n % 2 == 0:
                mult[-1] = 1.0
            g0 = float(np.sum(mult * lam)) / big_n
            w = mult * lam / (big_n * g0)
            fa = np.fft.rfft(sa, big_n, axis=0)
            g += self.share * np.real((fa.conj() * w[:, None]).T @ fa)
        return 0.5 * (g + g.T)
