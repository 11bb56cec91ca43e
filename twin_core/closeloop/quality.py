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

Each flag says what it saw and where (``detail``: the values, lengths and stamps behind it).

A series is judged with its context: timing of a plant's messages that is not a fault of the
readings is repaired and noted, never flagged (``DataQuality.notes``, ``action`` ``repaired``
or ``noted``; they do not make the status ``data_quality``):

- ``refill_hold``: a feeder's flow held over a refill (a loss-in-weight controller freezes
  its load-cell flow while the hopper fills) whose hold starts or ends up to
  ``max_skew_s`` off the refill flag (flag and value from different PLC scans): the
  refill's, not a stuck sensor;
- ``missing_tick``: fewer than ``min_gap_samples`` consecutive messages missing (sequence
  numbers skip): the tick held for a flow, left empty for the NIR; counted per source;
- ``duplicate_tick``: a message received twice (same stamp, sequence number and values):
  the copy dropped by the record; counted per source;
- ``jitter``: stamps scattered around the source's regular grid (by up to its period): put
  on the nearest tick; time jumps and gaps are judged against that scatter (a jump is a
  step beyond four robust standard deviations of the stamp intervals' own scatter and half
  a period; a gap is what the sequence numbers skip);
- ``irregular_sampling``: stamps that wander off any regular grid (their offset from the
  sequence numbers' grid spreads over more than two periods, :func:`sampling_kind`): each
  reading on its nearest tick (two on one tick: the NIR keeps the nearer), a tick without one
  held for a flow, empty for the NIR;
- ``clock_offset``: a source's clock off the common clock (:func:`estimate_clock_offsets`,
  from the arrival order of the messages): the record put the source back on the common
  clock; reported with its interval (``DataQuality.clock_offsets``), not left to the
  identification as a transport delay.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats
from scipy.ndimage import median_filter

from twin_core.closeloop.data import ClockOffset, RunData, StreamStamps
from twin_core.plant.model import LineModel, rtd_kernel
from twin_core.plant.nir import noise_sd
from twin_core.rtd.outliers import hampel

__all__ = [
    "DataFlag",
    "DataQuality",
    "QualityOptions",
    "check_data_quality",
    "estimate_clock_offsets",
    "lot_span_s",
]

KINDS = ("stuck", "clipping", "spike_burst", "gap", "time_jump", "duplicate_stamp")
#: repairs and notes of the timing of a plant's messages (module docstring)
NOTE_KINDS = (
    "refill_hold",
    "missing_tick",
    "duplicate_tick",
    "jitter",
    "irregular_sampling",
    "clock_offset",
)

#: name of the NIR reading among the checked series
NIR = "nir"


@dataclass(frozen=True)
class DataFlag:
    """A data fault or a repair: kind, series (``nir``, ``<feeder>:flow``,
    ``<feeder>:screw_speed``), interval and sample count; ``detail``: what was seen there;
    ``action``: ``left_out`` (a fault: its samples left out), ``repaired`` or ``noted`` (timing
    of the messages, module docstring)."""

    kind: str
    series: str
    t_start_s: float
    t_end_s: float
    n_samples: int
    detail: str = ""
    action: str = "left_out"

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "series": self.series,
            "t_start_s": float(self.t_start_s),
            "t_end_s": float(self.t_end_s),
            "n_samples": int(self.n_samples),
            "detail": self.detail,
            "action": self.action,
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
    #: the skew (s) between a value and its flag that the data path makes plausible (PLC scans,
    #: historian stamps): a hold that touches a refill within it is the refill's
    max_skew_s: float = 5.0
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
    """The flags of a record and the samples left out of the identification; the repairs and
    notes of its timing (``notes``, module docstring) and the clock offsets the record
    corrected."""

    flags: list[DataFlag]
    exclude: np.ndarray
    per_series: dict[str, int] = field(default_factory=dict)
    notes: list[DataFlag] = field(default_factory=list)
    clock_offsets: list[ClockOffset] = field(default_factory=list)

    def to_list(self) -> list[dict[str, Any]]:
        """Flags, then notes (their ``action`` tells them apart)."""
        return [f.to_dict() for f in self.flags] + [n.to_dict() for n in self.notes]


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


def _stamp_excess(
    t: np.ndarray, seq: np.ndarray | None, period_s: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """Each stamp interval's excess over what the sequence numbers say (without them: over the
    nearest whole number of periods), the number of periods each interval spans, and the
    tolerance of a time jump: max(half a period, 4 robust SD of the excess), the stream's own
    stamp scatter (jitter, irregular sampling) is not a jump."""
    d = np.diff(t)
    if seq is not None:
        dseq = np.diff(seq)
        step = max(int(np.median(dseq)), 1) if dseq.size else 1
        periods = dseq / step
    else:
        periods = np.maximum(np.round(d / period_s), 1.0)
    x = d - period_s * periods
    ok = d != 0  # a repeated stamp is told apart on its own
    scale = 0.0
    if ok.sum() >= 10:
        xo = x[ok]
        scale = 1.4826 * float(np.median(np.abs(xo - np.median(xo))))
    return x, periods, max(0.5 * period_s, 4.0 * scale)


def stamp_flags(series: str, stamps: StreamStamps, period_s: float) -> list[DataFlag]:
    """Duplicate stamps, time jumps and gaps of one stream's message stamps (module
    docstring), in arrival order. A time jump is a stamp interval off what the sequence numbers
    say by more than the stream's own scatter allows (:func:`_stamp_excess`) or a stamp going
    backwards; a gap is where the sequence numbers skip (without them: stamps more than 1.5
    periods apart)."""
    t = np.asarray(stamps.t_s, dtype=float)
    if t.size < 2:
        return []
    d = np.diff(t)
    seq = None if stamps.seq is None else np.asarray(stamps.seq, dtype=np.int64)
    x, periods, tol = _stamp_excess(t, seq, period_s)
    flags: list[DataFlag] = []
    for a, b in true_runs(d == 0):
        flags.append(
            DataFlag(
                "duplicate_stamp",
                series,
                float(t[a]),
                float(t[b]),
                b - a,
                f"{b - a + 1} messages stamped {t[a]:.3f} s",
            )
        )
    jump = (d < 0) | ((np.abs(x) > tol) & (d != 0))
    for i in np.flatnonzero(jump):
        lo, hi = sorted((float(t[i]), float(t[i + 1])))
        flags.append(
            DataFlag(
                "time_jump",
                series,
                lo,
                hi,
                1,
                f"stamps {t[i]:.3f} -> {t[i + 1]:.3f} s where the sequence numbers say "
                f"{period_s * periods[i]:.3f} s later (scatter allows +-{tol:.2f} s)",
            )
        )
    gap = (periods > 1.5) if seq is not None else (d > 1.5 * period_s)
    for i in np.flatnonzero(gap & ~jump):
        missing = int(round(periods[i])) - 1 if seq is not None else int(round(d[i] / period_s)) - 1
        if missing < 1:
            continue
        a, b = float(t[i] + period_s), float(t[i + 1] - period_s)
        flags.append(
            DataFlag(
                "gap",
                series,
                a,
                b,
                missing,
                f"{missing} messages missing between the stamps {t[i]:.3f} and {t[i + 1]:.3f} s",
            )
        )
    return flags


def stamp_notes(
    series: str, stamps: StreamStamps, period_s: float, min_gap_samples: int
) -> list[DataFlag]:
    """The timing of one stream that is repaired, not flagged (module docstring): missing
    ticks (gaps shorter than ``min_gap_samples``), re-sent messages the record dropped, stamp
    jitter, irregular sampling."""
    t = np.asarray(stamps.t_s, dtype=float)
    notes: list[DataFlag] = []
    if stamps.resent.size:
        r = stamps.resent
        notes.append(
            DataFlag(
                "duplicate_tick",
                series,
                float(r.min()),
                float(r.max()),
                int(r.size),
                f"{r.size} messages received twice (same stamp, sequence number and values) "
                f"between {r.min():.1f} and {r.max():.1f} s: the copies dropped",
                "repaired",
            )
        )
    if t.size < 10:
        return notes
    seq = None if stamps.seq is None else np.asarray(stamps.seq, dtype=np.int64)
    d = np.diff(t)
    x, periods, tol = _stamp_excess(t, seq, period_s)
    small = [
        i
        for i in np.flatnonzero(periods > 1.5 if seq is not None else d > 1.5 * period_s)
        if 1 <= int(round(periods[i] if seq is not None else d[i] / period_s)) - 1 < min_gap_samples
        and abs(x[i]) <= tol
    ]
    if small:
        n = sum(int(round(periods[i] if seq is not None else d[i] / period_s)) - 1 for i in small)
        what = "left empty" if series == NIR else "held from the tick before"
        notes.append(
            DataFlag(
                "missing_tick",
                series,
                float(t[small[0]] + period_s),
                float(t[small[-1] + 1] - period_s),
                n,
                f"{n} ticks missing in {len(small)} places of fewer than {min_gap_samples} "
                f"(sequence numbers skip), {what}",
                "repaired",
            )
        )
    kind, size = sampling_kind(stamps, period_s)
    ok = (np.abs(x) <= tol) & (d != 0)
    dd = d[ok & (periods == 1)] if seq is not None else d[ok]
    what = "each reading on its nearest tick"
    if kind == "irregular":
        notes.append(
            DataFlag(
                "irregular_sampling",
                series,
                float(t[0]),
                float(t[-1]),
                int(t.size),
                f"stamps wander {size:.1f} s off a regular {period_s:g} s grid, intervals "
                f"{dd.min():.2f}-{dd.max():.2f} s: {what}",
                "repaired",
            )
        )
    elif kind == "jitter":
        notes.append(
            DataFlag(
                "jitter",
                series,
                float(t[0]),
                float(t[-1]),
                int(t.size),
                f"stamps scatter up to {size:.2f} s (99 %) around a regular {period_s:g} s "
                "grid: each reading on its nearest tick",
                "repaired",
            )
        )
    return notes


def sampling_kind(stamps: StreamStamps, period_s: float) -> tuple[str | None, float]:
    """How a stream's stamps sit on its regular grid: ``("irregular", spread)`` when they
    wander off the sequence numbers' grid by more than two periods over the record (0.5-99.5 %
    range, clock jumps left out: irregular sampling), ``("jitter", q99)`` when they scatter
    around it by more than 5 % of a period, else ``(None, 0)``."""
    t = np.asarray(stamps.t_s, dtype=float)
    if t.size < 10:
        return None, 0.0
    seq = None if stamps.seq is None else np.asarray(stamps.seq, dtype=np.int64)
    d = np.diff(t)
    x, _, tol = _stamp_excess(t, seq, period_s)
    ok = (np.abs(x) <= tol) & (d != 0)
    wander = np.concatenate([[0.0], np.cumsum(np.where(ok, x, 0.0))])
    wander -= np.median(wander)
    spread = float(np.quantile(wander, 0.995) - np.quantile(wander, 0.005))
    if spread > 2.0 * period_s and seq is not None:
        return "irregular", spread
    j = float(np.quantile(np.abs(wander), 0.99))
    if j > 0.05 * period_s:
        return "jitter", j
    return None, 0.0


def _phase(t: np.ndarray, period_s: float) -> tuple[float, float]:
    """Circular mean of the stamps modulo the period, in [0, period), and its resultant
    length (1: every stamp on one grid; ~0: no grid)."""
    z = np.exp(2j * np.pi * np.asarray(t, dtype=float) / period_s)
    m = complex(np.mean(z)) if z.size else 0j
    return float((np.angle(m) / (2 * np.pi) * period_s) % period_s), float(abs(m))


def _order_bounds(s: StreamStamps, r: StreamStamps) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of stream ``s``'s clock minus stream ``r``'s from the arrival order, per message
    of ``s``: a message stamped s_i that arrived between messages of ``r`` stamped r_lo and
    r_hi was made between those instants, so its offset lies in [s_i - r_hi, s_i - r_lo]."""
    ra = np.asarray(r.arrival)
    order = np.argsort(ra, kind="stable")
    ra, rt = ra[order], np.asarray(r.t_s)[order]
    k = np.searchsorted(ra, np.asarray(s.arrival), side="left")
    ok = (k > 0) & (k < ra.size)
    st = np.asarray(s.t_s)[ok]
    return st - rt[k[ok]], st - rt[k[ok] - 1]


def _order_interval(s: StreamStamps, r: StreamStamps) -> tuple[float, float, int]:
    """:func:`_order_bounds` summarised: the medians of the bounds over the messages (robust
    to jitter and to a few late messages), and how many."""
    lo, hi = _order_bounds(s, r)
    if not lo.size:
        return -math.inf, math.inf, 0
    return float(np.median(lo)), float(np.median(hi)), int(lo.size)


def estimate_clock_offsets(
    stamps: Mapping[str, StreamStamps],
    period_s: float,
    margin: float = 0.1,
    min_share: float = 0.9,
) -> list[ClockOffset]:
    """Sources whose clock is off the common clock of the record, from the arrival order of
    the messages (each stream's ``arrival``).

    Against a reference stream R, a stream S's offset lies in the interval of
    :func:`_order_interval` (one period wide for sources sampled on one grid), widened by
    ``margin`` periods. The reference is the stream with which most streams agree (intervals
    holding 0; ties: the first stream): the clock most sources share. A stream whose interval
    excludes 0 is off: its offset is the value in (low, high] that has the stream's own sample
    phase against the reference's (the circular mean of the stamps modulo the period; on a
    tie, the upper end: a source's message arrives after the reference's of the same instant),
    or the interval's middle when its stamps have no phase (irregular or heavily jittered).
    The arrival order resolves an offset to a period: a sub-period offset is not reported.
    An offset is reported only if it holds over the record (within the bounds of at least
    ``min_share`` of the messages, widened by half a period): a clock that jumps is a
    ``time_jump`` of :func:`stamp_flags`, not an offset. Streams without ``arrival`` are left
    out."""
    names = [k for k, v in stamps.items() if v.arrival is not None and v.t_s.size >= 10]
    if len(names) < 2:
        return []
    m = margin * period_s
    iv = {(a, b): _order_interval(stamps[a], stamps[b]) for a in names for b in names if a != b}

    def agree(ref: str) -> int:
        return sum(1 for s in names if s == ref or iv[(s, ref)][0] - m <= 0 <= iv[(s, ref)][1] + m)

    ref = max(names, key=lambda r: (agree(r), -names.index(r)))
    p_ref, len_ref = _phase(stamps[ref].t_s, period_s)
    out = []
    for s in names:
        if s == ref:
            continue
        lo, hi, n = iv[(s, ref)]
        if not math.isfinite(lo) or lo - m <= 0 <= hi + m:
            continue
        p_s, len_s = _phase(stamps[s].t_s, period_s)
        if min(len_s, len_ref) >= 0.5:
            dphi = (p_s - p_ref) % period_s
            off = dphi + period_s * math.floor((hi + 1e-6 * period_s - dphi) / period_s)
        else:
            off = 0.5 * (lo + hi)
        # a clock offset holds over the record: most messages' own bounds (widened by half a
        # period of jitter) hold it; a clock that jumps (time_jump) is not put back here
        lo_i, hi_i = _order_bounds(stamps[s], stamps[ref])
        held = (lo_i - 0.5 * period_s - m <= off) & (off <= hi_i + 0.5 * period_s + m)
        if held.mean() < min_share:
            continue
        out.append(ClockOffset(s, float(off), lo - m, hi + m, n, ref))
    return out


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
        #: repairs and notes of the messages' timing (module docstring)
        self.notes: list[DataFlag] = []

    def in_gap(self, series: str, a: int, b: int) -> bool:
        """Whether samples [a, b) are a stamp gap of the series (the value held over it and
        the last sample before it)."""
        ta, tb = self.t[a] + self.dt, self.t[b - 1]
        return any(
            g0 - self.dt <= ta and tb <= g1 + self.dt for g0, g1 in self.gaps.get(series, [])
        )

    def flag(
        self,
        kind: str,
        series: str,
        a: int,
        b: int,
        n: int,
        reach: float | None,
        detail: str = "",
    ) -> None:
        """Flag samples [a, b) of a series on the record's grid (``detail``: what was seen);
        leave out the outlet samples from a to b + ``reach`` s (None: none)."""
        t = self.t
        self.flags.append(DataFlag(kind, series, float(t[a]), float(t[b - 1]), int(n), detail))
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
                    self.flag("gap", NIR, a, b, n_missing, 0.0, f"{n_missing} readings missing")
        idx = np.flatnonzero(finite)
        x = y[idx]
        pred = self.model.predict(self.data.inputs)[idx]
        sigma = noise_sd(pred, noise)
        at_clip, levels = clipped_mask(x, self.opt, self.opt.nir_range)
        clip_mask = np.zeros(x.size, dtype=bool)
        window = max(self.opt.burst_windows)
        for a, b in censored_stretches(x, at_clip, levels, sigma, window):
            clip_mask[a:b] = True
            n_at = int(at_clip[a:b].sum())
            lv = ", ".join(f"{v:.3f}" for v in levels)
            self.flag("clipping", NIR, idx[a], idx[b - 1] + 1, n_at, 0.0,
                      f"{n_at} readings at the clip level {lv} % w/w, censored around them")  # fmt: skip
        for a, b in stuck_runs(x, self.opt, exempt_zero=False):
            if clip_mask[a:b].any():
                continue
            self.flag("stuck", NIR, idx[a], idx[b - 1] + 1, b - a, 0.0,
                      f"{b - a} identical readings {x[a]:.4f} % w/w")  # fmt: skip
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
            n_out = int(out[a:b].sum())
            self.flag("spike_burst", NIR, idx[a], idx[b - 1] + 1, b - a, 0.0,
                      f"{n_out} outliers of the declared model's residual in {b - a} readings "
                      "or a stretch rougher than the noise")  # fmt: skip

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
        t = self.t
        for a, b in runs:
            if refill is not None and refill.size:
                if held and refill[a:b].any():
                    continue
                touched = self.refill_of(refill, a, b)
                if touched is not None:
                    self.note_hold(name, q, refill, a, b, touched)
                    continue
            if self.in_gap(name, a, b):
                continue
            self.flag("stuck", name, a, b, b - a, reach,
                      f"{b - a} identical values {q[a]:.4g} from {t[a]:.1f} to {t[b - 1]:.1f} s"
                      + self.refill_context(refill, a, b))  # fmt: skip
        if np.ptp(q) > 0:
            for a, b in clipped_runs(q, self.opt, None):
                if q[a] == 0.0 or any(a >= s and b <= e for s, e in runs):
                    continue
                self.flag("clipping", name, a, b, b - a, reach,
                          f"{b - a} values at the series' extreme {q[a]:.4g}")  # fmt: skip
        res = hampel(q, variant="seed")
        rate = max(res.count / q.size, 1e-4)
        for a, b, n_out in burst_runs(res.mask, rate, self.opt):
            self.flag("spike_burst", name, a, b, n_out, reach,
                      f"{n_out} Hampel outliers in {b - a} samples (background rate {rate:.1e})")  # fmt: skip

    def refill_of(self, refill: np.ndarray, a: int, b: int) -> tuple[int, int] | None:
        """The refill [start, end) whose hold the run [a, b) of identical values is: it
        overlaps the refill flag and starts and ends within ``max_skew_s`` of it (module
        docstring, ``refill_hold``); None: no such refill."""
        skew = int(math.floor(self.opt.max_skew_s / self.dt + 1e-9))
        for s, e in true_runs(refill):
            if s < b and a < e and a >= s - skew and b <= e + skew:
                return s, e
        return None

    def refill_context(self, refill: np.ndarray | None, a: int, b: int) -> str:
        """Words on the refills next to a stuck run (why it is not a refill's hold)."""
        if refill is None or not refill.size:
            return ""
        near = [(s, e) for s, e in true_runs(refill) if s < b + 60 and a < e + 60]
        if not near:
            return ""
        s, e = near[0]
        return (f"; the refill flagged {self.t[s]:.1f}-{self.t[e - 1]:.1f} s is more than "
                f"{self.opt.max_skew_s:g} s from its ends")  # fmt: skip

    def note_hold(
        self, name: str, q: np.ndarray, refill: np.ndarray, a: int, b: int, r: tuple[int, int]
    ) -> None:
        """Note a run of identical values that is a refill's hold (:meth:`refill_of`)."""
        s, e = r
        t = self.t

        def side(n: int) -> str:
            """``n`` samples off the flag's edge, in words."""
            if n == 0:
                return "with it"
            s = "s" if abs(n) > 1 else ""
            return f"{abs(n)} sample{s} {'before' if n < 0 else 'after'} it"

        self.notes.append(
            DataFlag(
                "refill_hold",
                name,
                float(t[a]),
                float(t[b - 1]),
                b - a,
                f"value held at {q[a]:.4g} for {b - a} samples ({t[a]:.1f}-{t[b - 1]:.1f} s) over "
                f"the refill flagged {t[s]:.1f}-{t[e - 1]:.1f} s: starts {side(a - s)}, "
                f"ends {side(b - e)}; the refill's hold (skew <= {self.opt.max_skew_s:g} s), "
                "not a stuck sensor",
                "noted",
            )
        )

    def stamps(self) -> None:
        """Duplicates, time jumps and gaps of the raw message stamps (when the record has
        them); after a time jump the series' samples are misaligned and left out."""
        period = {NIR: self.model.config.sensor.sample_period_s}
        for series, st in self.data.stamps.items():
            flags = stamp_flags(series, st, period.get(series, self.dt))
            self.notes += stamp_notes(
                series, st, period.get(series, self.dt), self.opt.min_gap_samples
            )
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
    for co in data.clock_offsets:
        st = data.stamps.get(co.series)
        t0, t1 = (float(st.t_s.min()), float(st.t_s.max())) if st and st.t_s.size else (0.0, 0.0)
        c.notes.append(
            DataFlag(
                "clock_offset",
                co.series,
                t0,
                t1,
                co.n_messages,
                f"stamps {co.offset_s:+.2f} s [{co.low_s:+.2f}, {co.high_s:+.2f}] off the clock "
                f"of {co.reference} (arrival order of {co.n_messages} messages)"
                + (": put back on it" if co.applied else ""),
                "repaired" if co.applied else "noted",
            )
        )
    flags = sorted(c.flags, key=lambda f: (f.t_start_s, f.series, f.kind))
    notes = sorted(c.notes, key=lambda f: (f.t_start_s, f.series, f.kind))
    per: dict[str, int] = {}
    for f in flags:
        per[f.series] = per.get(f.series, 0) + 1
    return DataQuality(flags, c.exclude, per, notes, list(data.clock_offsets))
