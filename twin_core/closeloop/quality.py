"""Data quality before any fit: faults of the recorded series that a model must not explain.

A stuck probe read as a dead zone, a clipped peak read as a gain, a burst of spikes read as a
disturbance: a process effect fitted to a data fault is a confident wrong answer. Every series
the close-loop uses (the NIR reading, every feeder's reported flow and screw speed, and the raw time stamps
of their messages when the record has them) is checked here first; the flagged samples are
reported (kind, series, interval, count) and left out of the identification
(:attr:`DataQuality.exclude`). For an input (a feeder flow) the outlet samples it reaches are
left out: from the fault's start to its end plus the blender's t(F = 0.995).

Kinds (each decided against what the series' own noise makes improbable, so clean data with
the seed's noise gives no flags: measured in ``benchmarks/closeloop_quality.py``):

- ``stuck``: a run of >= ``min_stuck_samples`` consecutive identical values (within
  ``stuck_tolerance``) whose chance under the series' own repeat rate is below
  ``false_alarm`` over the record: n p0^(L - 1) < false_alarm, p0 the share of repeated
  consecutive values outside such runs (0 for a continuous reading, so any run of the minimum
  length; a quantised reading sets its own p0). A series that never moves (an ideal feeder at
  its set point) has p0 = 1 and is not stuck; a feeder flow of exactly 0 (stopped) is a value,
  not a fault.
- ``clipping``: the series' largest (or smallest) value taken by >= ``min_clip_samples``
  samples (or values at or beyond a declared instrument range): saturation at the instrument's
  range. A run at the extreme is clipping, not stuck.
- ``spike_burst``: a cluster of Hampel outliers (``twin_core.rtd.outliers.hampel``, scale
  floored by the declared noise for the NIR; found again with the found ones left out, up to
  three passes, since dense spikes inflate each other's scale) with >= k outliers in w samples, scanned at each
  window length w of ``burst_windows`` (a dense burst inflates the Hampel scale, so only part
  of its spikes are outliers: a longer window still sees the cluster), k the smallest count
  whose binomial chance at the background outlier rate (the declared ``outlier_prob`` of the
  NIR; the series' own rate for a flow) is below ``false_alarm`` / (n x number of windows)
  (a scan statistic with a Bonferroni bound over positions and window lengths). Isolated
  outliers are the seed's noise and are not flagged (the Hampel filter replaces them).
- ``gap``: >= ``min_gap_samples`` expected samples missing (NaN readings; or stamps further
  apart than 1.5 periods with a sequence-number gap).
- ``time_jump``: stamps going backwards, or further apart than 1.5 periods while the sequence
  numbers advance by their usual step (the clock jumped, the data did not stop): every later
  sample of the series is misaligned and left out.
- ``duplicate_stamp``: a stamp repeated (two messages for one instant).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats
from scipy.ndimage import median_filter

from twin_core.closeloop.data import RunData, StreamStamps
from twin_core.plant.model import LineModel, rtd_kernel
from twin_core.plant.nir import noise_sd
from twin_core.rtd.outliers import hampel

__all__ = ["DataFlag", "DataQuality", "QualityOptions", "check_data_quality", "lot_span_s"]

KINDS = ("stuck", "clipping", "spike_burst", "gap", "time_jump", "duplicate_stamp")

#: name of the NIR reading among the checked series
NIR = "nir"


@dataclass(frozen=True)
class DataFlag:
    """A data fault: kind, series (``nir``, ``<feeder>:flow``, ``<feeder>:screw_speed``), interval and sample count."""

    kind: str
    series: str
    t_start_s: float
    t_end_s: float
    n_samples: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "series": self.series,
            "t_start_s": float(self.t_start_s),
            "t_end_s": float(self.t_end_s),
            "n_samples": int(self.n_samples),
        }


@dataclass
class QualityOptions:
    """Thresholds of :func:`check_data_quality` (module docstring)."""

    min_stuck_samples: int = 10
    stuck_tolerance: float = 0.0
    min_clip_samples: int = 3
    burst_windows: tuple[int, ...] = (10, 30, 100)
    #: roughness scan of the NIR (:func:`rough_stretches`): window (samples) and ratio
    rough_window: int = 30
    rough_ratio: float = 10.0
    min_gap_samples: int = 3
    false_alarm: float = 1e-3
    #: the NIR's range (% w/w): readings at or beyond it are clipped; None: from the data
    nir_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.min_stuck_samples < 3:
            raise ValueError(f"min_stuck_samples must be >= 3, got {self.min_stuck_samples}")
        if self.min_clip_samples < 2:
            raise ValueError(f"min_clip_samples must be >= 2, got {self.min_clip_samples}")
        if not self.burst_windows or min(self.burst_windows) < 3:
            raise ValueError(f"burst_windows must be >= 3 samples, got {self.burst_windows}")
        if not 0 < self.false_alarm < 1:
            raise ValueError(f"false_alarm must be in (0, 1), got {self.false_alarm}")


@dataclass
class DataQuality:
    """The flags of a record and the samples left out of the identification."""

    flags: list[DataFlag]
    exclude: np.ndarray
    per_series: dict[str, int] = field(default_factory=dict)

    def to_list(self) -> list[dict[str, Any]]:
        return [f.to_dict() for f in self.flags]


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of each run of True."""
    d = np.diff(np.concatenate([[0], np.asarray(mask, dtype=np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def _merge_runs(runs: list[tuple[int, int]], gap: int) -> list[tuple[int, int]]:
    """Runs [start, end) merged where fewer than ``gap`` samples separate them."""
    out: list[tuple[int, int]] = []
    for a, b in runs:
        if out and a - out[-1][1] < gap:
            out[-1] = (out[-1][0], b)
        else:
            out.append((a, b))
    return out


def _repeat_runs(x: np.ndarray, tol: float) -> tuple[list[tuple[int, int]], np.ndarray]:
    """Runs of identical consecutive values of a finite series: [start, end) in ``x``'s
    indices (a run of L values holds L - 1 repeats), and the repeat flags of the pairs."""
    same = np.abs(np.diff(x)) <= tol
    return [(a, b + 1) for a, b in true_runs(same)], same


def stuck_runs(x: np.ndarray, opt: QualityOptions, exempt_zero: bool) -> list[tuple[int, int]]:
    """Improbable runs of identical values of a finite series (module docstring, ``stuck``)."""
    x = np.asarray(x, dtype=float)
    n = x.size
    if n < opt.min_stuck_samples:
        return []
    runs, same = _repeat_runs(x, opt.stuck_tolerance)
    long_runs = [(a, b) for a, b in runs if b - a >= opt.min_stuck_samples]
    if not long_runs:
        return []
    inside = np.zeros(n - 1, dtype=bool)
    for a, b in long_runs:
        inside[a : b - 1] = True
    outside = ~inside
    p0 = float(same[outside].mean()) if outside.any() else 1.0
    out = []
    for a, b in long_runs:
        if exempt_zero and x[a] == 0.0:
            continue
        chance = n * p0 ** (b - a - 1) if p0 > 0 else 0.0
        if chance < opt.false_alarm:
            out.append((a, b))
    return out


def clipped_mask(
    x: np.ndarray, opt: QualityOptions, limits: tuple[float, float] | None
) -> tuple[np.ndarray, list[float]]:
    """Samples at the series' extreme value, taken >= ``min_clip_samples`` times, or at or
    beyond ``limits`` (module docstring, ``clipping``), and the clip levels; ``x`` finite."""
    x = np.asarray(x, dtype=float)
    at = np.zeros(x.size, dtype=bool)
    levels: list[float] = []
    if limits is not None:
        at |= (x <= limits[0]) | (x >= limits[1])
    for extreme in (x.max(), x.min()):
        hit = np.abs(x - extreme) <= opt.stuck_tolerance
        if hit.sum() >= opt.min_clip_samples or (
            limits is not None and hit.any() and (extreme <= limits[0] or extreme >= limits[1])
        ):
            at |= hit
            levels.append(float(extreme))
    return at, levels


def clipped_runs(
    x: np.ndarray, opt: QualityOptions, limits: tuple[float, float] | None
) -> list[tuple[int, int]]:
    """Runs of clipped samples (:func:`clipped_mask`)."""
    return true_runs(clipped_mask(x, opt, limits)[0])


def censored_stretches(
    x: np.ndarray,
    clipped: np.ndarray,
    levels: list[float],
    sigma: np.ndarray,
    window: int,
) -> list[tuple[int, int]]:
    """Stretches where a clipped reading is censored: the running median of ``window``
    samples within 3 noise SD of a clip level (there the readings that escaped the clip are
    the low tail of their distribution, biased towards the inside of the range: a truncated
    normal), with the clipped samples, merged over gaps shorter than ``window``."""
    if not levels:
        return []
    med = median_filter(np.asarray(x, dtype=float), size=window, mode="nearest")
    near = clipped.copy()
    for level in levels:
        near |= np.abs(med - level) <= 3.0 * sigma
    return [(a, b) for a, b in _merge_runs(true_runs(near), window) if clipped[a:b].any()]


def burst_threshold(window: int, rate: float, n: int, false_alarm: float) -> int:
    """Smallest count k of outliers in ``window`` samples with P(X >= k) < false_alarm / n,
    X ~ Binomial(window, rate): a cluster that the background outlier rate does not make."""
    for k in range(2, window + 1):
        if stats.binom.sf(k - 1, window, rate) < false_alarm / max(n, 1):
            return k
    return window + 1


def iterated_outliers(x: np.ndarray, min_scale: np.ndarray | float, passes: int = 3) -> np.ndarray:
    """Hampel outliers (``pearson`` variant, scale floored by ``min_scale``) found again with
    the ones already found left out, up to ``passes`` times: in a dense burst the spikes
    inflate each other's local scale, so one pass finds only some of them."""
    x = np.asarray(x, dtype=float)
    out = np.zeros(x.size, dtype=bool)
    for _ in range(passes):
        with warnings.catch_warnings():  # windows left without a sample: no verdict there
            warnings.simplefilter("ignore", RuntimeWarning)
            found = hampel(np.where(out, np.nan, x), variant="pearson", min_scale=min_scale).mask
        new = found & ~out
        if not new.any():
            break
        out |= new
    return out


def rough_stretches(
    x: np.ndarray, sigma: np.ndarray, window: int, ratio: float
) -> list[tuple[int, int]]:
    """Stretches of a reading rougher than its noise allows: the mean over ``window`` samples
    of the squared second differences d_i = x_(i+1) - 2 x_i + x_(i-1), divided by their noise
    expectation 6 sigma_i^2 (white noise; the 1/f part and a signal smooth over a few samples
    add little), above ``ratio``. ``x`` without its isolated outliers (a spike s adds 6 s^2);
    NaN marks samples to ignore.
    Finds a spike burst too dense for the Hampel identifier: the statistic is a mean of
    ~window/2 effectively independent chi-square(1) terms, so a ratio of 10 over 30 samples is
    out of reach of the noise (chi-square(15) > 150); an isolated outlier that escaped the
    Hampel filter adds about 6 s^2 / (6 sigma^2 window), < 10 for s < 17 sigma. Each stretch
    is trimmed to its samples with d_i^2 > 9 (6 sigma^2) and their neighbours."""
    x = np.asarray(x, dtype=float)
    if x.size < window + 2:
        return []
    d2 = np.zeros(x.size)
    d2[1:-1] = (x[2:] - 2.0 * x[1:-1] + x[:-2]) ** 2 / (6.0 * np.asarray(sigma)[1:-1] ** 2)
    d2 = np.nan_to_num(d2, nan=0.0)  # NaN: samples left out by the caller
    mean = np.convolve(d2, np.ones(window) / window, mode="same")
    half = window // 2
    out = []
    for a, b in true_runs(mean > ratio):
        lo, hi = max(a - half, 0), min(b + half, x.size)
        rough = lo + np.flatnonzero(d2[lo:hi] > 9.0)
        if rough.size:
            out.append((max(int(rough[0]) - 1, 0), min(int(rough[-1]) + 2, x.size)))
    return out


def burst_runs(
    outliers: np.ndarray, rate: float, opt: QualityOptions
) -> list[tuple[int, int, int]]:
    """Clusters of outliers at any window length of ``opt.burst_windows`` (module docstring,
    ``spike_burst``), merged: (start, end, outlier count)."""
    n = outliers.size
    fa = opt.false_alarm / len(opt.burst_windows)
    hot = np.zeros(n, dtype=bool)
    for w in opt.burst_windows:
        k = burst_threshold(w, rate, n, fa)
        for a, b, _ in spike_bursts(outliers, w, k):
            hot[a:b] = True
    return [(a, b, int(outliers[a:b].sum())) for a, b in true_runs(hot)]


def spike_bursts(outliers: np.ndarray, window: int, k: int) -> list[tuple[int, int, int]]:
    """Clusters of >= k outliers within ``window`` samples: (start, end) over the outliers of
    merged windows, and their count."""
    idx = np.flatnonzero(outliers)
    if idx.size < k:
        return []
    hot = np.zeros(outliers.size, dtype=bool)
    for i in range(idx.size - k + 1):
        if idx[i + k - 1] - idx[i] < window:
            hot[idx[i] : idx[i + k - 1] + 1] = True
    out = []
    for a, b in true_runs(hot):
        n_out = int(outliers[a:b].sum())
        out.append((a, b, n_out))
    return out


def stamp_flags(series: str, stamps: StreamStamps, period_s: float) -> list[DataFlag]:
    """Duplicate stamps, time jumps and gaps of one stream's message stamps (module
    docstring), in arrival order."""
    t = np.asarray(stamps.t_s, dtype=float)
    if t.size < 2:
        return []
    d = np.diff(t)
    seq = None if stamps.seq is None else np.asarray(stamps.seq, dtype=np.int64)
    dseq = np.diff(seq) if seq is not None else None
    flags: list[DataFlag] = []
    for a, b in true_runs(d == 0):
        flags.append(DataFlag("duplicate_stamp", series, float(t[a]), float(t[b]), b - a))
    for i in np.flatnonzero(d < 0):
        flags.append(DataFlag("time_jump", series, float(t[i + 1]), float(t[i]), 1))
    seq_step = int(np.median(dseq)) if dseq is not None else None
    for i in np.flatnonzero(d > 1.5 * period_s):
        missing = int(round(d[i] / period_s)) - 1
        if dseq is not None and dseq[i] == seq_step:
            flags.append(DataFlag("time_jump", series, float(t[i]), float(t[i + 1]), 1))
        else:
            a, b = float(t[i] + period_s), float(t[i + 1] - period_s)
            flags.append(DataFlag("gap", series, a, b, missing))
    return flags


def lot_span_s(model: LineModel, dt_s: float) -> float:
    """The blender's t(F = 0.995) (s): how long an input reaches the outlet."""
    tk = np.arange(0.0, 3600.0, dt_s)
    e = rtd_kernel(model.config.blender, tk, model.effects)
    f = np.cumsum(e) * dt_s
    return float(tk[np.argmax(f >= 0.995)]) if f[-1] >= 0.995 else float(tk[-1])


class _Checker:
    """Collects the flags and the excluded samples of one record."""

    def __init__(self, data: RunData, model: LineModel, opt: QualityOptions) -> None:
        self.data = data
        self.model = model
        self.opt = opt
        self.t = data.t_s
        self.dt = float(self.t[1] - self.t[0])
        self.flags: list[DataFlag] = []
        self.exclude = np.zeros(self.t.size, dtype=bool)
        self.span = lot_span_s(model, self.dt)
        #: per series, the (t_start, t_end) of its stamp gaps (samples held over, not stuck)
        self.gaps: dict[str, list[tuple[float, float]]] = {}

    def in_gap(self, series: str, a: int, b: int) -> bool:
        """Whether samples [a, b) are a stamp gap of the series (the value held over it and
        the last sample before it)."""
        ta, tb = self.t[a] + self.dt, self.t[b - 1]
        return any(
            g0 - self.dt <= ta and tb <= g1 + self.dt for g0, g1 in self.gaps.get(series, [])
        )

    def flag(self, kind: str, series: str, a: int, b: int, n: int, reach: float | None) -> None:
        """Flag samples [a, b) of a series on the record's grid; leave out the outlet samples
        from a to b + ``reach`` s (None: none)."""
        t = self.t
        self.flags.append(DataFlag(kind, series, float(t[a]), float(t[b - 1]), int(n)))
        if reach is not None:
            self.exclude |= (t >= t[a]) & (t <= t[b - 1] + reach)

    def nir(self) -> None:
        """The NIR reading: gaps, stuck runs, clipping, spike bursts."""
        y = self.data.measured
        noise = self.model.config.sensor.noise
        finite = np.isfinite(y)
        step = max(1, int(round(self.model.config.sensor.sample_period_s / self.dt)))
        expected = np.zeros(y.size, dtype=bool)
        first = int(np.argmax(finite))
        expected[first::step] = True
        if NIR not in self.data.stamps:
            for a, b in true_runs(expected & ~finite):
                n_missing = int(expected[a:b].sum())
                if n_missing >= self.opt.min_gap_samples:
                    self.flag("gap", NIR, a, b, n_missing, 0.0)
        idx = np.flatnonzero(finite)
        x = y[idx]
        pred = self.model.predict(self.data.inputs)[idx]
        sigma = noise_sd(pred, noise)
        at_clip, levels = clipped_mask(x, self.opt, self.opt.nir_range)
        clip_mask = np.zeros(x.size, dtype=bool)
        window = max(self.opt.burst_windows)
        for a, b in censored_stretches(x, at_clip, levels, sigma, window):
            clip_mask[a:b] = True
            self.flag("clipping", NIR, idx[a], idx[b - 1] + 1, int(at_clip[a:b].sum()), 0.0)
        for a, b in stuck_runs(x, self.opt, exempt_zero=False):
            if clip_mask[a:b].any():
                continue
            self.flag("stuck", NIR, idx[a], idx[b - 1] + 1, b - a, 0.0)
        # outliers and roughness of the residual of the declared model: the tracer peaks'
        # own shape (which also hides an outlier on a peak from a Hampel window on the
        # reading) is the model's, not the noise's
        resid = x - pred
        out = iterated_outliers(resid, sigma) & ~clip_mask
        rate = max(noise.outlier_prob, 1e-4)
        hot = np.zeros(x.size, dtype=bool)
        for a, b, _ in burst_runs(out, rate, self.opt):
            hot[a:b] = True
        resid[out | clip_mask] = np.nan  # outliers and clip edges are not roughness
        for a, b in rough_stretches(resid, sigma, self.opt.rough_window, self.opt.rough_ratio):
            hot[a:b] = True
        gap = min(self.opt.burst_windows)
        for a, b in _merge_runs(true_runs(hot), gap):
            self.flag("spike_burst", NIR, idx[a], idx[b - 1] + 1, b - a, 0.0)

    def flows(self) -> None:
        """Every feeder's reported flow and screw speed: stuck runs (not while refilling),
        clipping, spike bursts; the outlet samples a flow fault reaches are left out (the
        screw speed does not enter the prediction: flagged, nothing left out)."""
        inp = self.data.inputs
        for feeder, q in inp.flows_kg_h.items():
            self.series_faults(f"{feeder}:flow", q, inp.refilling.get(feeder), self.span)
        for feeder, rpm in inp.screw_speed_rpm.items():
            rpm = np.asarray(rpm, dtype=float)
            if rpm.size == self.t.size and np.all(np.isfinite(rpm)):
                refill = inp.refilling.get(feeder)
                self.series_faults(f"{feeder}:screw_speed", rpm, refill, None, held=True)

    def series_faults(
        self,
        name: str,
        q: np.ndarray,
        refill: np.ndarray | None,
        reach: float | None,
        held: bool = False,
    ) -> None:
        """Stuck runs (not while refilling, not a stamp gap's held value), clipping and spike
        bursts of one input series; ``reach`` (s) of outlet samples left out after each
        (None: flagged only). ``held``: the series is held constant from a refill until the
        feeder is back in gravimetric mode (a screw speed in volumetric mode), so a run that
        starts in a refill is not stuck."""
        runs = stuck_runs(q, self.opt, exempt_zero=True)
        for a, b in runs:
            if refill is not None and refill.size:
                if refill[a:b].all() or (held and refill[a:b].any()):
                    continue
            if self.in_gap(name, a, b):
                continue
            self.flag("stuck", name, a, b, b - a, reach)
        if np.ptp(q) > 0:
            for a, b in clipped_runs(q, self.opt, None):
                if q[a] == 0.0 or any(a >= s and b <= e for s, e in runs):
                    continue
                self.flag("clipping", name, a, b, b - a, reach)
        res = hampel(q, variant="seed")
        rate = max(res.count / q.size, 1e-4)
        for a, b, n_out in burst_runs(res.mask, rate, self.opt):
            self.flag("spike_burst", name, a, b, n_out, reach)

    def stamps(self) -> None:
        """Duplicates, time jumps and gaps of the raw message stamps (when the record has
        them); after a time jump the series' samples are misaligned and left out."""
        period = {NIR: self.model.config.sensor.sample_period_s}
        for series, st in self.data.stamps.items():
            flags = stamp_flags(series, st, period.get(series, self.dt))
            reach = 0.0 if series == NIR else self.span
            for f in flags:
                if f.kind == "gap" and f.n_samples < self.opt.min_gap_samples:
                    continue
                if f.kind == "gap":
                    self.gaps.setdefault(series, []).append((f.t_start_s, f.t_end_s))
                self.flags.append(f)
                end = math.inf if f.kind == "time_jump" else f.t_end_s + reach
                self.exclude |= (self.t >= min(f.t_start_s, f.t_end_s)) & (self.t <= end)


def check_data_quality(
    data: RunData, model: LineModel, options: QualityOptions | None = None
) -> DataQuality:
    """Flag the data faults of a record and the samples to leave out (module docstring)."""
    opt = options or QualityOptions()
    c = _Checker(data, model, opt)
    c.stamps()
    c.nir()
    c.flows()
    flags = sorted(c.flags, key=lambda f: (f.t_start_s, f.series, f.kind))
    per: dict[str, int] = {}
    for f in flags:
        per[f.series] = per.get(f.series, 0) + 1
    return DataQuality(flags, c.exclude, per)
