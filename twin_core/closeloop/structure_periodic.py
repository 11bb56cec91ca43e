"""Periodic content in the residual: frequency, amplitude, the input it is coherent with.

Detection is Thomson's harmonic F-test (Thomson 1982, Proc. IEEE 70:1055; Percival & Walden,
Spectral Analysis for Physical Applications, 1993, sec. 10.11) on the training window of the
residual r_t. With K = 2 NW - 1 discrete prolate spheroidal tapers v_k (unit energy, time-
bandwidth NW), eigencoefficients Y_k(f) = sum_t v_k(t) r_t exp(-i 2 pi f t) and
U_k = sum_t v_k(t):

    mu(f) = sum_k U_k Y_k(f) / sum_k U_k^2                      (line amplitude, A/2 e^{i phi})
    F(f)  = (K - 1) |mu|^2 sum_k U_k^2 / sum_k |Y_k(f) - mu U_k|^2  ~  F(2, 2K - 2)

under "no line at f" with a spectrum locally flat over [f - W, f + W], W = NW / T: the
background is estimated at each frequency from the same K eigencoefficients, so the 1/f
(and proportional) background of the NIR noise is allowed for. The search covers f from
max(``min_cycles`` / T, 2 W) to the Nyquist frequency less W; the smallest p-value is
Bonferroni-corrected by the number of independent Fourier frequencies in that band.

The line is then refined (the frequency maximising |mu(f)|), fitted by weighted least squares
r = c + a cos(2 pi f t) + b sin(2 pi f t) on the training window (amplitude A = sqrt(a^2 + b^2)
with its sandwich standard error under the declared noise, delta method), and its frequency
standard error is the Cramer-Rao bound for a sinusoid in noise of the local level
sigma_loc^2 = sum_k |Y_k - mu U_k|^2 / (K - 1):
var(f) = 12 sigma_loc^2 fs^2 / ((2 pi)^2 A^2 N (N^2 - 1)) (Rife & Boorstyn 1974).

Coherent input: the magnitude-squared coherence (Welch, Hann, non-overlapping segments of
4 periods, at least 32 samples, at least 4 segments) of the residual with every feeder flow and
screw speed at f; without coherence an estimate C over L segments exceeds c with probability
(1 - c)^(L - 1) (Carter 1987, Proc. IEEE 75:236), its p-value. And the match of f with the
screw rotation of a feeder (h x rpm / 60, h = 1..3, folded into the Nyquist band) within the
frequency uncertainty: a pulsation locked to a screw (or an alias of one).

The correction for prediction is the fitted sinusoid A cos(2 pi f t + phi) in plant time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import optimize, signal, stats

from twin_core.closeloop.data import RunData
from twin_core.closeloop.structure_base import (
    HeldoutEvidence,
    ResidualContext,
    StructureFinding,
    StructureOptions,
    contiguous_span,
    heldout_evidence,
    interval,
    weighted_fit,
)
from twin_core.plant.model import LineModel


@dataclass
class MultitaperLines:
    """Harmonic F-test on a grid of frequencies (see module)."""

    freqs_hz: np.ndarray
    f_stat: np.ndarray
    mu: np.ndarray
    background: np.ndarray
    tapers: np.ndarray
    u0: np.ndarray
    dof: int


def multitaper_ftest(x: np.ndarray, dt: float, nw: float) -> MultitaperLines:
    """Thomson's harmonic F statistic of the series ``x`` (step ``dt``) on the Fourier grid
    zero-padded to >= 2 N; ``background`` is the local noise variance per sample,
    sum_k |Y_k - mu U_k|^2 / (K - 1)."""
    x = np.asarray(x, dtype=float)
    n = x.size
    k = max(2, int(round(2 * nw)) - 1)
    tapers = signal.windows.dpss(n, nw, Kmax=k)
    u0 = tapers.sum(axis=1)
    nfft = int(2 ** math.ceil(math.log2(2 * n)))
    y = np.fft.rfft(tapers * x[None, :], n=nfft, axis=1)
    su2 = float(np.sum(u0**2))
    mu = (u0[:, None] * y).sum(axis=0) / su2
    rss = np.sum(np.abs(y - mu[None, :] * u0[:, None]) ** 2, axis=0)
    f_stat = (k - 1) * np.abs(mu) ** 2 * su2 / np.maximum(rss, 1e-300)
    return MultitaperLines(
        np.fft.rfftfreq(nfft, d=dt), f_stat, mu, rss / (k - 1), tapers, u0, 2 * k - 2
    )


def _mu_at(lines: MultitaperLines, x: np.ndarray, f_hz: float, dt: float) -> complex:
    """mu(f) off the grid (direct sums)."""
    e = np.exp(-2j * np.pi * f_hz * dt * np.arange(x.size))
    yk = lines.tapers @ (x * e)
    return complex(np.sum(lines.u0 * yk) / np.sum(lines.u0**2))


def refine_frequency(lines: MultitaperLines, x: np.ndarray, j: int, dt: float) -> float:
    """The frequency maximising |mu(f)| within one grid step of grid index ``j``."""
    df = float(lines.freqs_hz[1] - lines.freqs_hz[0])
    f0 = float(lines.freqs_hz[j])
    res = optimize.minimize_scalar(
        lambda f: -abs(_mu_at(lines, x, f, dt)),
        bounds=(max(f0 - df, df / 4), f0 + df),
        method="bounded",
        options={"xatol": df * 1e-3},
    )
    return float(res.x) if -res.fun >= abs(lines.mu[j]) else f0


def coherence_at(x: np.ndarray, u: np.ndarray, nper: int, k: int) -> float:
    """Magnitude-squared coherence |S_xu|^2 / (S_xx S_uu) of ``x`` and ``u`` at the Fourier
    bin ``k`` of non-overlapping segments of ``nper`` samples, each linearly detrended and
    Hann-windowed (Welch's estimate at one frequency; ``scipy.signal.coherence`` with
    ``noverlap=0, detrend="linear"``, without its full spectrum)."""
    n_seg = x.size // nper
    j = np.arange(nper, dtype=float)
    q, _ = np.linalg.qr(np.column_stack([np.ones(nper), j]))
    win = signal.windows.hann(nper, sym=False)
    wave = win * np.exp(-2j * np.pi * k * j / nper)

    def coefs(v: np.ndarray) -> np.ndarray:
        seg = v[: n_seg * nper].reshape(n_seg, nper)
        return (seg - (seg @ q) @ q.T) @ wave

    cx, cu = coefs(np.asarray(x, float)), coefs(np.asarray(u, float))
    sxu = np.mean(cx * cu.conj())
    sxx, suu = np.mean(np.abs(cx) ** 2), np.mean(np.abs(cu) ** 2)
    return float(abs(sxu) ** 2 / (sxx * suu)) if sxx > 0 and suu > 0 else 0.0


def coherent_inputs(
    ctx: ResidualContext, r: np.ndarray, span: slice, f_hz: float
) -> list[tuple[str, float, float]]:
    """Magnitude-squared coherence of the residual ``r`` with every feeder flow and screw
    speed at ``f_hz`` over ``span``: [(input, MSC, p)], most coherent first (see module)."""
    dt = ctx.dt
    n = span.stop - span.start
    nper = int(min(n // 4, max(math.ceil(4.0 / (f_hz * dt)), 32)))
    if nper < 16:
        return []
    n_seg = n // nper
    kbin = int(round(f_hz * dt * nper))
    inp = ctx.data.inputs
    series = dict(inp.flows_kg_h)
    series.update({f"{name}:screw_speed": v for name, v in inp.screw_speed_rpm.items()})
    out = []
    for name, u in series.items():
        u = np.asarray(u, dtype=float)[span]
        if not np.all(np.isfinite(u)) or np.std(u) == 0:
            continue
        msc = coherence_at(r[span], u, nper, kbin)
        out.append((name, msc, float((1.0 - msc) ** (n_seg - 1))))
    return sorted(out, key=lambda x: x[2])


def screw_rotation_match(
    ctx: ResidualContext, f_hz: float, tol_hz: float, span: slice
) -> list[str]:
    """Feeders whose screw rotation h x median(rpm) / 60 (h = 1..3, folded into [0, fs / 2])
    is within ``tol_hz`` of ``f_hz``."""
    fs = 1.0 / ctx.dt
    out = []
    for name, rpm in ctx.data.inputs.screw_speed_rpm.items():
        v = np.asarray(rpm, dtype=float)[span]
        if not np.all(np.isfinite(v)) or np.median(v) <= 0:
            continue
        f_rot = float(np.median(v)) / 60.0
        for h in (1, 2, 3):
            fa = abs(((h * f_rot + fs / 2) % fs) - fs / 2)
            if abs(fa - f_hz) <= tol_hz:
                out.append(f"{h}x the screw rotation of {name} ({np.median(v):.3g} rpm)")
                break
    return out


@dataclass
class _Sinusoid:
    f_hz: float
    se_f: float
    amp: float
    se_amp: float
    phase_abs: float
    f_stat: float
    p_search: float
    sigma_loc: float
    f_threshold: float  # F at the search level (Bonferroni)
    fit: np.ndarray  # fitted sinusoid on the whole grid (no constant)


def _fit_sinusoid(
    ctx: ResidualContext, r: np.ndarray, span: slice, opt: StructureOptions
) -> tuple[_Sinusoid | None, MultitaperLines, np.ndarray]:
    """Strongest line of the residual ``r`` on the training window (None: not significant)."""
    dt = ctx.dt
    x = np.where(ctx.train[span], r[span], 0.0)
    x = np.where(ctx.train[span], x - x[ctx.train[span]].mean(), 0.0)
    n = x.size
    lines = multitaper_ftest(x, dt, opt.nw)
    t_span = n * dt
    w_hz = opt.nw / t_span
    f_lo = max(opt.min_cycles / t_span, 2 * w_hz)
    f_hi = 0.5 / dt - w_hz
    band = (lines.freqs_hz >= f_lo) & (lines.freqs_hz <= f_hi)
    if not band.any():
        return None, lines, band
    n_indep = max(1.0, (f_hi - f_lo) * t_span)
    j = int(np.flatnonzero(band)[np.argmax(lines.f_stat[band])])
    p_one = float(stats.f.sf(lines.f_stat[j], 2, lines.dof))
    p_search = min(1.0, p_one * n_indep)
    if p_search >= opt.search_alpha:
        return None, lines, band
    f_hz = refine_frequency(lines, x, j, dt)
    t = ctx.t
    t_ref = float(t[span.start])
    arg = 2 * np.pi * f_hz * (t - t_ref)
    cols = np.column_stack([np.ones_like(t), np.cos(arg), np.sin(arg)])
    beta, cov = weighted_fit(ctx, cols, r, ctx.train)
    a, b = float(beta[1]), float(beta[2])
    amp = math.hypot(a, b)
    g = np.array([a, b]) / amp if amp > 0 else np.zeros(2)
    se_amp = float(np.sqrt(max(g @ cov[1:, 1:] @ g, 0.0)))
    phase = math.atan2(-b, a)
    sigma_loc = float(np.sqrt(lines.background[j]))
    n_tr = int(ctx.train[span].sum())
    var_w = 12.0 * sigma_loc**2 / (amp**2 * n_tr * (n_tr**2 - 1.0)) if amp > 0 else math.inf
    se_f = math.sqrt(var_w) / (2 * np.pi * dt)
    fit = a * np.cos(arg) + b * np.sin(arg)
    return (
        _Sinusoid(
            f_hz,
            se_f,
            amp,
            se_amp,
            phase - 2 * np.pi * f_hz * t_ref,
            float(lines.f_stat[j]),
            p_search,
            sigma_loc,
            float(stats.f.isf(opt.search_alpha / n_indep, 2, lines.dof)),
            fit,
        ),
        lines,
        band,
    )


@dataclass(frozen=True)
class SinusoidPredictor:
    """The correction A cos(2 pi f t + phi) in plant time t (s)."""

    amplitude: float
    f_hz: float
    phase_abs: float

    def __call__(self, data: RunData, model: LineModel) -> np.ndarray:
        return self.amplitude * np.cos(2 * np.pi * self.f_hz * data.t_s + self.phase_abs)


def _finding(
    ctx: ResidualContext,
    opt: StructureOptions,
    s: _Sinusoid,
    ev: HeldoutEvidence,
    r: np.ndarray,
    span: slice,
    lines: MultitaperLines,
    band: np.ndarray,
) -> StructureFinding:
    coh = coherent_inputs(ctx, r, span, s.f_hz)
    n_inputs = max(len(coh), 1)
    sig = [c for c in coh if c[2] < 0.05 / n_inputs]
    t_span = (span.stop - span.start) * ctx.dt
    rot = screw_rotation_match(ctx, s.f_hz, max(3 * s.se_f, opt.nw / t_span), span)
    if sig:
        source = f"coherent with {sig[0][0]} (MSC {sig[0][1]:.2f})"
    elif rot:
        source = f"at {rot[0]}"
    else:
        source = "no input coherent (probe side or an unmeasured source)"
    f_lo, f_hi = s.f_hz - 1.96 * s.se_f, s.f_hz + 1.96 * s.se_f
    summary = (
        f"periodic residual: period {1 / s.f_hz:.4g} s ({s.f_hz:.5f} Hz), amplitude "
        f"{s.amp:.3g} % w/w, {source}; held-out error {-100 * ev.rel_improvement:+.1f} % "
        "with the sinusoid (empirical)"
    )
    evidence = {
        "f_statistic": s.f_stat,
        "search_p_value": s.p_search,
        "local_noise_sd": s.sigma_loc,
        "bandwidth_hz": opt.nw / t_span,
        **ev.as_dict(),
    }
    if coh:
        evidence["coherence"] = coh[0][1]
        evidence["coherence_p_value"] = coh[0][2]
    alternatives = [f"coherent with {c[0]} (MSC {c[1]:.2f})" for c in sig[1:]] + rot[
        (0 if sig else 1) :
    ]
    return StructureFinding(
        kind="periodic",
        summary=summary,
        evidence=evidence,
        estimates={
            "frequency_hz": interval(s.f_hz, s.se_f, lo=0.0),
            "period_s": (1 / s.f_hz, 1 / f_hi, 1 / f_lo if f_lo > 0 else math.inf),
            "amplitude_pct_w_w": interval(s.amp, s.se_amp, lo=0.0),
        },
        alternatives=alternatives,
        curves={
            "freqs_hz": lines.freqs_hz[band],
            "f_stat": lines.f_stat[band],
            "dof": lines.dof,
            "f_threshold": s.f_threshold,
            "f_hz": s.f_hz,
            "t_s": ctx.t,
            "residual": np.where(ctx.finite, ctx.resid, np.nan),
            "fit": s.fit,
        },
        predictor=SinusoidPredictor(s.amp, s.f_hz, s.phase_abs),
    )


def find_periodic(
    ctx: ResidualContext, opt: StructureOptions, e0: np.ndarray
) -> list[StructureFinding]:
    """Up to ``opt.max_sinusoids`` sinusoids in the residual ``e0`` (see module), each
    significant on the training window and passing the held-out test."""
    span = contiguous_span(ctx.train)
    r = np.array(e0, dtype=float)
    out: list[StructureFinding] = []
    level = opt.heldout_level("periodic")
    for _ in range(opt.max_sinusoids):
        s, lines, band = _fit_sinusoid(ctx, r, span, opt)
        if s is None:
            break
        ev = heldout_evidence(ctx, s.fit, level, opt.min_improvement, e0=r)
        if not ev.passed:
            break
        out.append(_finding(ctx, opt, s, ev, r, span, lines, band))
        r = r - s.fit
    return out
