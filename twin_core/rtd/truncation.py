"""Truncation of tracer profiles (seed 6.2.2.3), keeping the number of samples.

- ``truncate_time``: values after t_cut are set to zero (6.2.2.3.2);
- ``truncate_level``: values below an absolute concentration level (e.g. 0.125-2 % w/w) are
  set to zero (6.2.2.3.3); ``truncate_relative``: the level is a fraction of the peak height
  (1.25-10 %, Fig. 6.17 / Table 6.2);
- ``pat_level`` / ``truncate_pat``: the level mu + k sigma of a baseline window where no tracer
  is present (k = 3; 6.2.4 third approach). The seed took t > 120 s; by default the window is
  relative to the profile (``baseline_windows``): it starts ``BASELINE_FWHM`` full widths at
  half maximum after the peak, so a short record or a slow system gets its own window;
- ``baseline_windows``: the samples before the tracer arrives and after it has left, found on
  a median-smoothed copy; a signal that does not come back to the level it started from (or
  is still changing at the end of the record) is refused with an error naming it; a record
  shorter than the window whose end is back at the level before the tracer within the noise
  is complete however short (its end is the window);
- ``two_peak_profiles``: the superposed-Gaussian construction of 6.2.2.3.1 (main peak plus
  a tail peak), for the "do tails matter?" case.
Zeroed samples stay in the array (same length), so E = C / int C of the truncated profile is
renormalized by its reduced area, as in the seed's Fig. 6.18A.

``parse_spec`` reads the CLI form: ``time:50``, ``level:0.5``, ``rel:0.0375``, ``pat`` (k = 3),
``pat:3`` or ``pat:3@120`` (k sigma from t >= 120 s, the seed's absolute window).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import median_filter

from twin_core.rtd.denoise import noise_sigma

__all__ = [
    "truncate_time",
    "truncate_level",
    "truncate_relative",
    "pat_level",
    "truncate_pat",
    "two_peak_profiles",
    "baseline_correct",
    "BaselineWindows",
    "baseline_windows",
    "PAT_K",
    "SEED_PAT_BASELINE_S",
    "trim",
    "TruncationSpec",
    "parse_spec",
]


def _y(y: ArrayLike) -> NDArray[np.float64]:
    yy = np.asarray(y, dtype=float)
    if yy.ndim != 1:
        raise ValueError(f"y must be 1-D, got shape {yy.shape}")
    if not np.all(np.isfinite(yy)):
        raise ValueError("y must be finite, got NaN or inf")
    return yy


def truncate_time(t: ArrayLike, y: ArrayLike, t_cut: float) -> NDArray[np.float64]:
    """Zero every sample with t > t_cut (same length)."""
    tt, yy = np.asarray(t, float), _y(y)
    if not np.isfinite(t_cut):
        raise ValueError(f"t_cut must be finite, got {t_cut!r}")
    out = yy.copy()
    out[tt > t_cut] = 0.0
    return out


def truncate_level(y: ArrayLike, level: float) -> NDArray[np.float64]:
    """Zero every sample below the absolute `level` (same length)."""
    yy = _y(y)
    if not np.isfinite(level) or level < 0:
        raise ValueError(f"level must be finite and >= 0, got {level!r}")
    return np.where(yy < level, 0.0, yy)


def truncate_relative(y: ArrayLike, fraction: float) -> NDArray[np.float64]:
    """Zero every sample below `fraction` of the peak height (fraction in [0, 1))."""
    yy = _y(y)
    if not 0 <= fraction < 1:
        raise ValueError(f"fraction must be in [0, 1), got {fraction!r}")
    return (
        truncate_level(yy, fraction * float(np.max(yy))) if fraction > 0 else np.clip(yy, 0, None)
    )


#: default k of the PAT level mu + k sigma (the seed's)
PAT_K = 3.0
#: the seed's absolute PAT baseline window: t >= 120 s
SEED_PAT_BASELINE_S = 120.0
#: the baseline window starts this many FWHM after the peak
BASELINE_FWHM = 5.0
#: a signal has returned when its end level is within this fraction of the peak height (or
#: 4 baseline standard deviations, whichever is larger) of its starting level
RETURN_FRACTION = 0.05
#: fewest samples of a baseline window
MIN_BASELINE_SAMPLES = 5
#: a record too short for the window BASELINE_FWHM widths after the peak is complete in fact
#: when the median of its last samples (as many as a window needs) is within RETURN_NOISE_K
#: noise sd (``denoise.noise_sigma``, the wavelet estimate of the denoising) or
#: RETURN_NOISE_FLOOR of the peak height (a noise-free record) of the level before the tracer
RETURN_NOISE_K = 3.0
RETURN_NOISE_FLOOR = 0.01


@dataclass(frozen=True)
class BaselineWindows:
    """Samples before the tracer arrives (``pre``, possibly none) and after it has left
    (``post``), with the peak time, FWHM and peak height above the starting level."""

    pre: NDArray[np.bool_]
    post: NDArray[np.bool_]
    t_peak: float
    fwhm: float
    height: float
    short: str = ""
    """when the post window is the tail of a record shorter than ``BASELINE_FWHM`` widths after
    its peak, back at the baseline within the noise: what was judged, in words"""

    @property
    def both(self) -> NDArray[np.bool_]:
        return self.pre | self.post

    @property
    def t_post(self) -> float:
        """Start of the post window (s)."""
        return self.t_peak + BASELINE_FWHM * self.fwhm


def _smooth(y: NDArray) -> NDArray[np.float64]:
    size = max(5, (y.size // 50) | 1)
    return median_filter(y, size=size, mode="nearest")


def baseline_windows(t: ArrayLike, y: ArrayLike, name: str = "signal") -> BaselineWindows:
    """Baseline windows of a tracer profile (module docstring). ValueError naming ``name`` if
    the profile has no peak, ends before ``BASELINE_FWHM`` widths after its peak, or ends at a
    level that differs from its start by more than max(``RETURN_FRACTION`` x height,
    4 sd of the end window); without a window before the tracer, the end window must be flat
    to within the same tolerance."""
    tt, yy = np.asarray(t, float), _y(y)
    if tt.shape != yy.shape or tt.size < 10:
        raise ValueError(f"t and y must be 1-D of equal shape with >= 10 samples, got {tt.shape}")
    ys = _smooth(yy)
    n_edge = max(3, tt.size // 20)
    start = float(np.median(ys[:n_edge]))
    end = float(np.median(ys[-max(3, tt.size // 10) :]))
    ref = min(start, end)
    i_peak = int(np.argmax(ys))
    height = float(ys[i_peak] - ref)
    if not height > 0:
        raise ValueError(f"{name} has no peak above its baseline (height {height:.3g})")
    above = ys - ref >= 0.5 * height
    left = i_peak
    while left > 0 and above[left - 1]:
        left -= 1
    right = i_peak
    while right < tt.size - 1 and above[right + 1]:
        right += 1
    dt = float(np.median(np.diff(tt)))
    fwhm = max(float(tt[right] - tt[left]), dt)
    t_peak = float(tt[i_peak])
    post = tt >= t_peak + BASELINE_FWHM * fwhm
    need = max(MIN_BASELINE_SAMPLES, tt.size // 20)
    rise = int(np.argmax(ys - ref > 0.05 * height))
    pre = tt <= tt[rise] - fwhm
    short = ""
    if post.sum() < need:
        # a short record: complete when its last samples are back at the level before the
        # tracer within the noise (the start of the record when no pre window fits)
        level = (
            float(np.mean(yy[pre]))
            if pre.sum() >= MIN_BASELINE_SAMPLES
            else float(np.median(yy[: max(rise, n_edge)]))
        )
        last = max(need, tt.size // 10)
        end_window = np.arange(tt.size) >= tt.size - last
        t_end = float(tt[end_window][0])
        tol = max(RETURN_NOISE_K * noise_sigma(yy), RETURN_NOISE_FLOOR * height)
        at = float(np.median(yy[end_window]))
        if t_end < t_peak + fwhm or abs(at - level) > tol:
            seen = (
                f"its last {last} samples (from {t_end:.3g} s) are {at - level:+.3g} from "
                f"the level before the tracer ({level:.3g}; within the noise: {tol:.3g})"
                if t_end >= t_peak + fwhm
                else f"its last {last} samples start less than a peak width after the peak"
            )
            raise ValueError(
                f"{name} does not return to its baseline within the record: the baseline "
                f"window starts {BASELINE_FWHM:g} peak widths ({fwhm:.3g} s) after the peak at "
                f"{t_peak:.3g} s, at {t_peak + BASELINE_FWHM * fwhm:.3g} s, and the record ends "
                f"at {tt[-1]:.3g} s ({int(post.sum())} samples, need {need}); {seen}; measure "
                "longer"
            )
        post = end_window
        short = (
            f"the record ends {(tt[-1] - t_peak) / fwhm:.1f} peak widths after the peak (short "
            f"of {BASELINE_FWHM:g}); it is complete: its last {last} samples (from {t_end:.3g}"
            f" s) are {at - level:+.3g} from the level before the tracer, within the noise "
            f"({tol:.3g}: {RETURN_NOISE_K:g} sd, wavelet estimate)"
        )
    post_y = yy[post]
    tol = max(RETURN_FRACTION * height, 4.0 * float(np.std(post_y, ddof=1)))
    if pre.sum() >= MIN_BASELINE_SAMPLES:
        gap = float(np.mean(post_y) - np.mean(yy[pre]))
        if abs(gap) > tol:
            raise ValueError(
                f"{name} does not return to its baseline: after {t_peak + BASELINE_FWHM * fwhm:.3g}"
                f" s its mean is {np.mean(post_y):.4g}, {gap:+.3g} from the level before the "
                f"tracer ({np.mean(yy[pre]):.4g}; tolerance {tol:.3g})"
            )
    else:
        tp = tt[post]
        slope = np.polyfit(tp, post_y, 1)[0]
        drift = float(slope * (tp[-1] - tp[0]))
        if abs(drift) > tol:
            raise ValueError(
                f"{name} does not return to its baseline: it still changes by {drift:+.3g} "
                f"over its last {tp[-1] - tp[0]:.3g} s (tolerance {tol:.3g})"
            )
    return BaselineWindows(pre, post, t_peak, fwhm, height, short)


def pat_level(
    t: ArrayLike, y: ArrayLike, k: float = PAT_K, t_baseline: float | None = None
) -> tuple[float, float, float]:
    """(level, mu, sigma): mu + k sigma of the baseline window, t >= ``t_baseline`` if given
    (the seed: 120 s), else the post window of :func:`baseline_windows`."""
    tt, yy = np.asarray(t, float), _y(y)
    if not k >= 0:
        raise ValueError(f"k must be >= 0, got {k!r}")
    window = baseline_windows(tt, yy).post if t_baseline is None else tt >= t_baseline
    base = yy[window]
    if base.size < MIN_BASELINE_SAMPLES:
        raise ValueError(
            f"t_baseline leaves {base.size} baseline samples (need >= {MIN_BASELINE_SAMPLES}), "
            f"got {t_baseline!r}"
        )
    mu, sd = float(np.mean(base)), float(np.std(base, ddof=1))
    return mu + k * sd, mu, sd


def truncate_pat(
    t: ArrayLike, y: ArrayLike, k: float = PAT_K, t_baseline: float | None = None
) -> NDArray:
    """PAT-based truncation: zero every sample below mu + k sigma of the baseline window."""
    lvl, _, _ = pat_level(t, y, k, t_baseline)
    return truncate_level(y, max(lvl, 0.0))


def baseline_correct(
    t: ArrayLike, y: ArrayLike, t_baseline: float | None = None
) -> NDArray[np.float64]:
    """Subtract the mean of the baseline window (``pat_level``'s; a PAT offset; not part of the
    seed's workflow, offered because the offset biases the area and hence E)."""
    _, mu, _ = pat_level(t, y, 0.0, t_baseline)
    return _y(y) - mu


def trim(
    t: ArrayLike,
    e: ArrayLike,
    start_loss: float = 1e-4,
    end_loss: float = 1e-3,
    max_end_fraction: float = 0.05,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Trim an RTD to where its cumulative mass lies in [start_loss, 1 - end_loss] (shorter
    arrays, as bio-rtd's trimming) with sanity checks: ValueError if the profile does not decay
    (last value above `max_end_fraction` of the peak: the tail was cut by the measurement) or if
    the area is not positive. Returns (t, e) with e renormalized to area 1."""
    from twin_core.rtd.convolution import cumulative

    tt, ee = np.asarray(t, float), _y(e)
    if tt.shape != ee.shape:
        raise ValueError(f"e must have the shape of t {tt.shape}, got {ee.shape}")
    if not (0 <= start_loss < 0.5 and 0 <= end_loss < 0.5):
        raise ValueError(
            f"start_loss and end_loss must be in [0, 0.5), got {start_loss!r}, {end_loss!r}"
        )
    peak = float(np.max(ee))
    if not peak > 0:
        raise ValueError(f"e must have a positive peak, got {peak!r}")
    if ee[-1] > max_end_fraction * peak:
        raise ValueError(
            f"profile does not decay: last value is {ee[-1] / peak:.1%} of the peak "
            f"(max_end_fraction={max_end_fraction!r}); measure longer"
        )
    f = cumulative(tt, np.clip(ee, 0, None))
    if not f[-1] > 0:
        raise ValueError(f"e must have a positive area, got {f[-1]!r}")
    f /= f[-1]
    i0 = max(int(np.searchsorted(f, start_loss, side="right")) - 1, 0)
    i1 = min(int(np.searchsorted(f, 1.0 - end_loss, side="left")) + 1, tt.size)
    ts, es = tt[i0:i1], ee[i0:i1]
    area = float(np.sum(0.5 * (es[1:] + es[:-1]) * np.diff(ts)))
    return ts, es / area


def two_peak_profiles(
    t: ArrayLike,
    main: tuple[float, float, float] = (30.0, 6.0, 10.0),
    tails: tuple[tuple[float, float, float], ...] = ((45.0, 12.0, 1.0), (50.0, 20.0, 1.0)),
) -> list[NDArray[np.float64]]:
    """Profiles built as a main Gaussian peak plus a tail Gaussian (seed Fig. 6.15A).

    Each triple is (centre s, width s, height); one profile per tail triple.
    """
    tt = np.asarray(t, float)

    def g(c: float, w: float, h: float) -> NDArray:
        if w <= 0:
            raise ValueError(f"width must be > 0, got {w!r}")
        return h * np.exp(-0.5 * ((tt - c) / w) ** 2)

    return [g(*main) + g(*tail) for tail in tails]


@dataclass(frozen=True)
class TruncationSpec:
    kind: str
    value: float
    t_baseline: float | None = None

    def apply(self, t: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
        if self.kind == "time":
            return truncate_time(t, y, self.value)
        if self.kind == "level":
            return truncate_level(y, self.value)
        if self.kind == "rel":
            return truncate_relative(y, self.value)
        return truncate_pat(t, y, self.value, self.t_baseline)


def parse_spec(spec: str) -> TruncationSpec:
    """Parse ``time:S``, ``level:C``, ``rel:F``, ``pat`` (k = ``PAT_K``), ``pat:K`` or
    ``pat:K@T``."""
    if spec.strip().lower() == "pat":
        return TruncationSpec("pat", PAT_K)
    if ":" not in spec:
        raise ValueError(f"truncate spec must be 'kind:value', got {spec!r}")
    kind, val = spec.split(":", 1)
    kind = kind.strip().lower()
    if kind not in ("time", "level", "rel", "pat"):
        raise ValueError(f"truncate kind must be time, level, rel or pat, got {kind!r}")
    tb = None
    if kind == "pat" and "@" in val:
        val, tbs = val.split("@", 1)
        try:
            tb = float(tbs)
        except ValueError:
            raise ValueError(f"pat baseline start must be a number, got {tbs!r}") from None
    try:
        v = float(val)
    except ValueError:
        raise ValueError(f"truncate value must be a number, got {val!r}") from None
    return TruncationSpec(kind, v, tb)
