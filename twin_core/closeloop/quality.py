"""Data quality before any fit: faults of the recorded series that a model must not explain.

A stuck probe read as a dead zone, a clipped peak read as a gain, a burst of spikes read as a
disturbance: a process effect fitted to a data fault is a confident wrong answer. Every series
the close-loop uses (the NIR reading and every feeder's reported flow, and the raw time stamps
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
  floored by the declared noise for the NIR) with >= k outliers in ``burst_window`` samples,
  k the smallest count whose binomial chance at the background outlier rate (the declared
  ``outlier_prob`` of the NIR; the series' own rate for a flow) is below
  ``false_alarm`` / n. Isolated outliers are the seed's noise and are not flagged (the Hampel
  filter replaces them).
- ``gap``: >= ``min_gap_samples`` expected samples missing (NaN readings; or stamps further
  apart than 1.5 periods with a sequence-number gap).
- ``time_jump``: stamps going backwards, or further apart than 1.5 periods while the sequence
  numbers advance by their usual step (the clock jumped, the data did not stop): every later
  sample of the series is misaligned and left out.
- ``duplicate_stamp``: a stamp repeated (two messages for one instant).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

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
    """A data fault: kind, series (``nir``, ``<feeder>:flow``), interval and sample count."""

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
    burst_window: int = 10
    min_gap_samples: int = 3
    false_alarm: float = 1e-3
    #: the NIR's range (% w/w): readings at or beyond it are clipped; None: from the data
    nir_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.min_stuck_samples < 3:
            raise ValueError(f"min_stuck_samples must be >= 3, got {self.min_stuck_samples}")
        if self.min_clip_samples < 2:
            raise ValueError(f"min_clip_samples must be >= 2, got {self.min_clip_samples}")
        if self.burst_window < 3:
            raise ValueError(f"burst_window must be >= 3, got {self.burst_window}")
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


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of each run of True."""
    d = np.diff(np.concatenate([[0], np.asarray(mask, dtype=np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def _repeat_runs(x: np.ndarray, tol: float) -> tuple[list[tuple[int, int]], np.ndarray]:
    """Runs of identical consecutive values of a finite series: [start, end) in ``x``'s
    indices (a run of L values holds L - 1 repeats), and the repeat flags of the pairs."""
    same = np.abs(np.diff(x)) <= tol
    return [(a, b + 1) for a, b in _runs(same)], same


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


def clipped_runs(
    x: np.ndarray, opt: QualityOptions, limits: tuple[float, float] | None
) -> list[tuple[int, int]]:
    """Runs of samples at the series' extreme value, taken >= ``min_clip_samples`` times, or at
    or beyond ``limits`` (module docstring, ``clipping``); ``x`` finite."""
    x = np.asarray(x, dtype=float)
    at = np.zeros(x.size, dtype=bool)
    if limits is not None:
        at |= (x <= limits[0]) | (x >= limits[1])
    for extreme in (x.max(), x.min()):
        hit = np.abs(x - extreme) <= opt.stuck_tolerance
        if hit.sum() >= opt.min_clip_samples:
            at |= hit
    return _runs(at)


def burst_threshold(window: int, rate: float, n: int, false_alarm: float) -> int:
    """Smallest count k of outliers in ``window`` samples with P(X >= k) < false_alarm / n,
    X ~ Binomial(window, rate): a cluster that the background outlier rate does not make."""
    for k in range(2, window + 1):
        if stats.binom.sf(k - 1, window, rate) < false_alarm / max(n, 1):
            return k
    return window + 1


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
    for a, b in _runs(hot):
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
    for a, b in _runs(d == 0):
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

    def flag(self, kind: str, series: str, a: int, b: int, n: int, reach: float) -> None:
        """Flag samples [a, b) of a series on the record's grid; leave out the outlet samples
        from a to b + ``reach`` s."""
        t = self.t
        self.flags.append(DataFlag(kind, series, float(t[a]), float(t[b - 1]), int(n)))
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
            for a, b in _runs(expected & ~finite):
                n_missing = int(expected[a:b].sum())
                if n_missing >= self.opt.min_gap_samples:
                    self.flag("gap", NIR, a, b, n_missing, 0.0)
        idx = np.flatnonzero(finite)
        x = y[idx]
        clipped = clipped_runs(x, self.opt, self.opt.nir_range)
        clip_mask = np.zeros(x.size, dtype=bool)
        for a, b in clipped:
            clip_mask[a:b] = True
            self.flag("clipping", NIR, idx[a], idx[b - 1] + 1, b - a, 0.0)
        for a, b in stuck_runs(x, self.opt, exempt_zero=False):
            if clip_mask[a:b].any():
                continue
            self.flag("stuck", NIR, idx[a], idx[b - 1] + 1, b - a, 0.0)
        sigma = noise_sd(self.model.predict(self.data.inputs)[idx], noise)
        out = hampel(x, variant="pearson", min_scale=sigma).mask
        rate = max(noise.outlier_prob, 1e-4)
        k = burst_threshold(self.opt.burst_window, rate, x.size, self.opt.false_alarm)
        for a, b, n_out in spike_bursts(out, self.opt.burst_window, k):
            self.flag("spike_burst", NIR, idx[a], idx[b - 1] + 1, n_out, 0.0)

    def flows(self) -> None:
        """Every feeder's reported flow: stuck runs (not while refilling), clipping, spike
        bursts; the outlet samples each fault reaches are left out."""
        inp = self.data.inputs
        for feeder, q in inp.flows_kg_h.items():
            name = f"{feeder}:flow"
            refill = inp.refilling.get(feeder)
            runs = stuck_runs(q, self.opt, exempt_zero=True)
            for a, b in runs:
                if refill is not None and refill.size and refill[a:b].all():
                    continue
                self.flag("stuck", name, a, b, b - a, self.span)
            if np.ptp(q) > 0:
                for a, b in clipped_runs(q, self.opt, None):
                    if q[a] == 0.0 or any(a >= s and b <= e for s, e in runs):
                        continue
                    self.flag("clipping", name, a, b, b - a, self.span)
            res = hampel(q, variant="seed")
            rate = max(res.count / q.size, 1e-4)
            k = burst_threshold(self.opt.burst_window, rate, q.size, self.opt.false_alarm)
            for a, b, n_out in spike_bursts(res.mask, self.opt.burst_window, k):
                self.flag("spike_burst", name, a, b, n_out, self.span)

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
                self.flags.append(f)
                end = math.inf if f.kind == "time_jump" else f.t_end_s + reach
                self.exclude |= (self.t >= min(f.t_start_s, f.t_end_s)) & (self.t <= end)


def check_data_quality(
    data: RunData, model: LineModel, options: QualityOptions | None = None
) -> DataQuality:
    """Flag the data faults of a record and the samples to leave out (module docstring)."""
    opt = options or QualityOptions()
    c = _Checker(data, model, opt)
    c.nir()
    c.flows()
    c.stamps()
    flags = sorted(c.flags, key=lambda f: (f.t_start_s, f.series, f.kind))
    per: dict[str, int] = {}
    for f in flags:
        per[f.series] = per.get(f.series, 0) + 1
    return DataQuality(flags, c.exclude, per)
