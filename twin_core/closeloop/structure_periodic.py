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
Bonferroni-corrected by the number of frequencies of the (zero-padded) grid searched in that
band: the F statistics of neighbouring grid points are correlated, but their maximum exceeds
that of the Fourier frequencies alone (with the Fourier count, the smallest p fell below 5 % on
13-18 % of records of the simulator's noise; with the grid count 4-6 %).

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

Screw-locked pulsation (order tracking through the twin's blender). A screw feeder's flow
pulses n times per revolution; its screw speed follows the set point and the feeder's
control, so in time the pulsation is not one line but a band (on the open-world benchmark's
2-hour record the API screw runs 3.6-6.2 rpm: its pulsation at n rpm / 60 spreads over
0.06-0.10 Hz, and the blender's phase lag at those frequencies changes by radians between
set points), and the line search above sees only a fraction of its power at any one
frequency. It is a line in the screw's angle: with theta(t) the screw's revolutions from its
reported speed (theta_j = sum_{i<j} rpm_i dt / 60) and the delivered flow
m(t) (1 + a cos(2 pi q theta) + b sin(2 pi q theta)), the change of the predicted reading is,
to first order in (a, b), r = a x_c + b x_s with x = d prediction / d (a, b) through the
model's own blender (central differences of ``LineModel.predict``; the flow's pulsation
averaged over each tick). (a, b) are fitted by weighted least squares on the training window
past the blender's t(F = 0.995) from the record's start (the model holds the first sample
over the past: a pulsation's start-up transient is not in the data) with their sandwich
covariance V under the declared coloured noise, and the Wald statistic
W = beta' V^-1 beta ~ chi2(2) without a pulsation (a linear estimate in Gaussian noise: Wald
1943; order tracking: Fyfe & Munck 1997, Mech. Syst. Signal Process. 11:187), Bonferroni over
the feeders x orders q = 1..``max_order`` tried. The order is then refined as a continuous q
near the integer one: its 95 % interval is the profile {q: W(q) >= max W - 3.84} (the
likelihood-ratio interval of one parameter, Venzon & Moolgavkar 1988), and the period at the
median screw speed of the training window, 60 / (q rpm), is reported with it. The relative
amplitude A = sqrt(a^2 + b^2) has its delta-method interval; the amplitude at the probe
(% w/w) is sqrt(2) x the RMS of the fitted change over the training window (the blender
filters the pulsation by |G(2 pi q rpm / 60)|, which changes with the screw speed) with the
same relative interval. The correction is a x_c + b x_s on the record's own screw speed (the
phase refers to the record's first sample). The line search and the screw-locked search each
run at half the search level when both run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

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
from twin_core.plant.model import LineInputs, LineModel, rtd_kernel


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
    log_p: float  # log of the Bonferroni p (ranks candidates whose p underflows)


def _fit_sinusoid(
    ctx: ResidualContext, r: np.ndarray, span: slice, opt: StructureOptions, level: float
) -> tuple[_Sinusoid | None, MultitaperLines, np.ndarray]:
    """Strongest line of the residual ``r`` on the training window (None: not significant at
    the search ``level``)."""
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
    # Bonferroni over the grid frequencies searched (the zero-padded grid is 2.8-3.8 x finer
    # than the Fourier frequencies; counting only those, the band's smallest p fell below 5 %
    # on 13-18 % of noise records)
    n_indep = float(max(1, int(band.sum())))
    j = int(np.flatnonzero(band)[np.argmax(lines.f_stat[band])])
    log_p = float(stats.f.logsf(lines.f_stat[j], 2, lines.dof)) + math.log(n_indep)
    p_search = min(1.0, math.exp(min(log_p, 0.0)))
    if p_search >= level:
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
            float(stats.f.isf(level / n_indep, 2, lines.dof)),
            fit,
            log_p,
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


# ---------------------------------------------------------------------------------------------
# screw-locked pulsation (see module)
# ---------------------------------------------------------------------------------------------
def screw_revolutions(rpm: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Revolutions of a screw since the first sample at the start and at the end of every
    tick, the reported speed ``rpm`` held over each tick: theta_j = sum_{i<j} rpm_i dt / 60."""
    step = np.asarray(rpm, dtype=float) * dt / 60.0
    start = np.concatenate([[0.0], np.cumsum(step[:-1])])
    return start, start + step


def tick_mean_wave(rev0: np.ndarray, rev1: np.ndarray, order: float) -> np.ndarray:
    """Means of cos(2 pi q theta) and sin(2 pi q theta) over every tick (theta linear from
    ``rev0`` to ``rev1`` within it): ((sin x1 - sin x0) / dx, (cos x0 - cos x1) / dx), n x 2."""
    x0, x1 = 2 * np.pi * order * rev0, 2 * np.pi * order * rev1
    dx = x1 - x0
    small = np.abs(dx) < 1e-9
    safe = np.where(small, 1.0, dx)
    c = np.where(small, np.cos(x0), (np.sin(x1) - np.sin(x0)) / safe)
    s = np.where(small, np.sin(x0), (np.cos(x0) - np.cos(x1)) / safe)
    return np.column_stack([c, s])


def pulsation_design(
    model: LineModel, inputs: LineInputs, feeder: str, order: float, eps: float = 0.05
) -> np.ndarray:
    """d prediction / d (a, b) of a pulsation of ``feeder``'s delivered flow,
    m (1 + a cos(2 pi q theta) + b sin(2 pi q theta)), theta its screw's revolutions (central
    differences of ``model.predict`` at +-``eps``; the prediction is a ratio of convolutions,
    so the difference is exact to O(eps^2)); the first sample, which the model holds over the
    history before the record, is not modulated. n x 2."""
    dt = float(inputs.t_s[1] - inputs.t_s[0])
    wave = tick_mean_wave(*screw_revolutions(inputs.screw_speed_rpm[feeder], dt), order)
    wave[0] = 0.0  # the model extends the first sample into the past: keep that history steady
    base = np.asarray(inputs.flows_kg_h[feeder], dtype=float)
    cols = []
    for k in range(2):
        pred = []
        for sign in (1.0, -1.0):
            flows = dict(inputs.flows_kg_h)
            flows[feeder] = base * (1.0 + sign * eps * wave[:, k])
            pred.append(model.predict(replace(inputs, flows_kg_h=flows)))
        cols.append((pred[0] - pred[1]) / (2 * eps))
    return np.column_stack(cols)


@dataclass(frozen=True)
class ScrewPulsationPredictor:
    """The correction a x_c + b x_s of a screw-locked pulsation (see module) on a record's own
    screw speed."""

    feeder: str
    order: float
    a: float
    b: float

    def __call__(self, data: RunData, model: LineModel) -> np.ndarray:
        x = pulsation_design(model, data.inputs, self.feeder, self.order)
        return x @ np.array([self.a, self.b])


def _screw_feeders(ctx: ResidualContext) -> list[str]:
    """Feeders with a finite, positive screw speed and a flow over the whole record."""
    inp = ctx.data.inputs
    out = []
    for name, rpm in inp.screw_speed_rpm.items():
        v = np.asarray(rpm, dtype=float)
        if (
            name in inp.flows_kg_h
            and v.shape == ctx.t.shape
            and np.all(np.isfinite(v))
            and np.all(v >= 0)
            and np.median(v[ctx.train]) > 0
        ):
            out.append(name)
    return out


@dataclass
class _ScrewLine:
    feeder: str
    order: float
    q_lo: float
    q_hi: float
    rpm: float
    wald: float
    p_search: float
    w_threshold: float
    a: float
    b: float
    amp_rel: float
    se_rel: float
    amp_pct: float
    fit: np.ndarray
    q_grid: np.ndarray
    w_grid: np.ndarray
    others: list[str]
    log_p: float


class _ScrewSearch:
    """Wald statistics of screw-locked pulsations on the training window (designs cached by
    feeder and order: they do not depend on the residual)."""

    def __init__(self, ctx: ResidualContext, opt: StructureOptions) -> None:
        self.ctx = ctx
        self._x: dict[tuple[str, float], np.ndarray] = {}
        self.tries: list[tuple[str, int]] = []
        tk = np.arange(0.0, 3600.0, ctx.dt)
        f = np.cumsum(rtd_kernel(ctx.model.config.blender, tk, ctx.model.effects)) * ctx.dt
        settle = float(tk[np.argmax(f >= 0.995)]) if f[-1] >= 0.995 else float(tk[-1])
        #: the training samples past the blender's t(F = 0.995) from the record's start
        self.mask = ctx.train & (ctx.t >= ctx.t[0] + settle)
        tr = np.flatnonzero(self.mask)
        if tr.size < 60:
            return
        self.revs: dict[str, float] = {}
        for name in _screw_feeders(ctx):
            rev0, rev1 = screw_revolutions(ctx.data.inputs.screw_speed_rpm[name], ctx.dt)
            n_rev = float(rev1[tr[-1]] - rev0[tr[0]])
            self.revs[name] = n_rev
            self.tries += [
                (name, h) for h in range(1, opt.max_order + 1) if h * n_rev >= opt.min_cycles
            ]

    def design(self, feeder: str, order: float) -> np.ndarray:
        key = (feeder, float(order))
        if key not in self._x:
            self._x[key] = pulsation_design(self.ctx.model, self.ctx.data.inputs, feeder, order)
        return self._x[key]

    def wald(
        self, r: np.ndarray, feeder: str, order: float
    ) -> tuple[float, np.ndarray, np.ndarray]:
        """(W, (a, b), their covariance) of the weighted fit r ~ c + a x_c + b x_s."""
        x = self.design(feeder, order)
        cols = np.column_stack([np.ones_like(self.ctx.t), x])
        beta, cov = weighted_fit(self.ctx, cols, r, self.mask)
        v = cov[1:, 1:]
        b = beta[1:]
        try:
            w = float(b @ np.linalg.solve(v, b))
        except np.linalg.LinAlgError:
            w = 0.0
        return max(w, 0.0), b, v


def _fit_screw_locked(search: _ScrewSearch, r: np.ndarray, level: float) -> _ScrewLine | None:
    """The strongest screw-locked pulsation of the residual ``r`` (None: none significant at
    the search ``level``, Bonferroni over the feeders x orders tried)."""
    ctx = search.ctx
    m = len(search.tries)
    if m == 0:
        return None
    scores = [(search.wald(r, f, h)[0], f, h) for f, h in search.tries]
    w0, feeder, h = max(scores)
    p_of = [min(1.0, float(stats.chi2.sf(w, 2)) * m) for w, _, _ in scores]
    p_search = min(p_of)
    if p_search >= level:
        return None
    others = [
        f"{f}, {hh} pulse(s) per revolution (search p {p:.1e})"
        for (w, f, hh), p in zip(scores, p_of)
        if p < level and (f, hh) != (feeder, h)
    ]
    n_rev = search.revs[feeder]
    res = 1.0 / n_rev

    def w_of(q: float) -> float:
        return search.wald(r, feeder, q)[0]

    grid = h + res * np.linspace(-3.0, 3.0, 25)
    w_grid = np.array([w_of(q) for q in grid])
    j = int(np.argmax(w_grid))
    lo_b, hi_b = grid[max(j - 1, 0)], grid[min(j + 1, grid.size - 1)]
    opt_q = optimize.minimize_scalar(
        lambda q: -w_of(q), bounds=(lo_b, hi_b), method="bounded", options={"xatol": res * 1e-3}
    )
    q_hat = float(opt_q.x) if -opt_q.fun >= w_grid[j] else float(grid[j])
    w_max = max(-float(opt_q.fun), float(w_grid[j]))
    cut = w_max - float(stats.chi2.isf(0.05, 1))

    def edge(direction: float) -> float:
        """Where W(q) falls to the cut, from q_hat towards ``direction`` (profile interval)."""
        step = res * 0.05
        q_in = q_hat
        for _ in range(12):
            q_out = q_in + direction * step
            if w_of(q_out) < cut:
                return float(
                    optimize.brentq(
                        lambda q: w_of(q) - cut, *sorted((q_in, q_out)), xtol=res * 1e-4
                    )
                )
            q_in, step = q_out, step * 2.0
        return q_in

    q_lo, q_hi = edge(-1.0), edge(1.0)
    _, ab, v = search.wald(r, feeder, q_hat)
    a, b = float(ab[0]), float(ab[1])
    amp = math.hypot(a, b)
    g = np.array([a, b]) / amp if amp > 0 else np.zeros(2)
    se_rel = float(np.sqrt(max(g @ v @ g, 0.0)))
    fit = search.design(feeder, q_hat) @ np.array([a, b])
    amp_pct = float(np.sqrt(2.0 * np.mean(fit[search.mask] ** 2)))
    rpm = float(np.median(np.asarray(ctx.data.inputs.screw_speed_rpm[feeder])[search.mask]))
    return _ScrewLine(
        feeder,
        q_hat,
        q_lo,
        q_hi,
        rpm,
        w_max,
        p_search,
        float(stats.chi2.isf(level / m, 2)),
        a,
        b,
        amp,
        se_rel,
        amp_pct,
        fit,
        grid,
        w_grid,
        others,
        float(stats.chi2.logsf(w0, 2)) + math.log(m),
    )


def _screw_finding(
    ctx: ResidualContext, s: _ScrewLine, ev: HeldoutEvidence, r: np.ndarray
) -> StructureFinding:
    f_hz = s.order * s.rpm / 60.0
    amp = interval(s.amp_rel, s.se_rel, lo=0.0)
    scale = s.amp_pct / s.amp_rel if s.amp_rel > 0 else 0.0
    summary = (
        f"periodic residual locked to the screw of {s.feeder}: {s.order:.4g} pulse(s) per "
        f"revolution, period {1 / f_hz:.4g} s at {s.rpm:.3g} rpm (it follows the screw speed), "
        f"flow pulsation {100 * s.amp_rel:.3g} % ({s.amp_pct:.3g} % w/w at the probe); "
        f"held-out error {-100 * ev.rel_improvement:+.1f} % with it (empirical)"
    )
    return StructureFinding(
        kind="periodic",
        summary=summary,
        evidence={
            "wald_statistic": s.wald,
            "search_p_value": s.p_search,
            "screw_speed_rpm": s.rpm,
            **ev.as_dict(),
        },
        estimates={
            "pulses_per_rev": (s.order, s.q_lo, s.q_hi),
            "frequency_hz": (f_hz, s.q_lo * s.rpm / 60.0, s.q_hi * s.rpm / 60.0),
            "period_s": (
                60.0 / (s.order * s.rpm),
                60.0 / (s.q_hi * s.rpm),
                60.0 / (s.q_lo * s.rpm),
            ),
            "relative_amplitude": amp,
            "amplitude_pct_w_w": tuple(scale * x for x in amp),
        },
        alternatives=[f"locked to the screw of {o}" for o in s.others],
        curves={
            "freqs_hz": s.q_grid * s.rpm / 60.0,
            "f_stat": s.w_grid / 2.0,
            "dof": math.inf,
            "f_threshold": s.w_threshold / 2.0,
            "f_hz": f_hz,
            "t_s": ctx.t,
            "residual": np.where(ctx.finite, ctx.resid, np.nan),
            "fit": s.fit,
        },
        predictor=ScrewPulsationPredictor(s.feeder, s.order, s.a, s.b),
    )


def find_periodic(
    ctx: ResidualContext, opt: StructureOptions, e0: np.ndarray
) -> list[StructureFinding]:
    """Up to ``opt.max_sinusoids`` periodic components of the residual ``e0`` (see module):
    fixed-frequency lines and screw-locked pulsations, the one with the smaller search p-value
    first, each significant on the training window and passing the held-out test."""
    span = contiguous_span(ctx.train)
    r = np.array(e0, dtype=float)
    out: list[StructureFinding] = []
    level = opt.heldout_level("periodic")
    screws = _ScrewSearch(ctx, opt) if opt.max_order > 0 else None
    n_searches = 2 if screws is not None and screws.tries else 1
    search_level = opt.search_alpha / n_searches
    for _ in range(opt.max_sinusoids):
        s, lines, band = _fit_sinusoid(ctx, r, span, opt, search_level)
        sl = _fit_screw_locked(screws, r, search_level) if n_searches == 2 else None
        # the stronger candidate first (log p: both may underflow); the other if it fails
        cands = sorted((c for c in (s, sl) if c is not None), key=lambda c: c.log_p)
        accepted = None
        for c in cands:
            ev = heldout_evidence(ctx, c.fit, level, opt.min_improvement, e0=r)
            if ev.passed:
                accepted = (c, ev)
                break
        if accepted is None:
            break
        c, ev = accepted
        if isinstance(c, _ScrewLine):
            out.append(_screw_finding(ctx, c, ev, r))
        else:
            out.append(_finding(ctx, opt, c, ev, r, span, lines, band))
        r = r - c.fit
    return out
