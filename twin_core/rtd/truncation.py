"""Truncation of tracer profiles (seed 6.2.2.3), keeping the number of samples.

- ``truncate_time``: values after t_cut are set to zero (6.2.2.3.2);
- ``truncate_level``: values below an absolute concentration level (e.g. 0.125-2 % w/w) are
  set to zero (6.2.2.3.3); ``truncate_relative``: the level is a fraction of the peak height
  (1.25-10 %, Fig. 6.17 / Table 6.2);
- ``pat_level`` / ``truncate_pat``: the level mu + k sigma of a baseline window where no tracer
  is present (t > 120 s in the seed; k = 3), 6.2.4 third approach;
- ``two_peak_profiles``: the superposed-Gaussian construction of 6.2.2.3.1 (main peak plus
  a tail peak), for the "do tails matter?" case.
Zeroed samples stay in the array (same length), so E = C / int C of the truncated profile is
renormalized by its reduced area, as in the seed's Fig. 6.18A.

``parse_spec`` reads the CLI form: ``time:50``, ``level:0.5``, ``rel:0.0375``, ``pat:3`` or
``pat:3@120`` (k sigma from t >= 120 s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "truncate_time",
    "truncate_level",
    "truncate_relative",
    "pat_level",
    "truncate_pat",
    "two_peak_profiles",
    "baseline_correct",
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


def pat_level(
    t: ArrayLike, y: ArrayLike, k: float = 3.0, t_baseline: float = 120.0
) -> tuple[float, float, float]:
    """(level, mu, sigma): mu + k sigma of the samples with t >= t_baseline."""
    tt, yy = np.asarray(t, float), _y(y)
    base = yy[tt >= t_baseline]
    if base.size < 5:
        raise ValueError(
            f"t_baseline leaves {base.size} baseline samples (need >= 5), got {t_baseline!r}"
        )
    if not k >= 0:
        raise ValueError(f"k must be >= 0, got {k!r}")
    mu, sd = float(np.mean(base)), float(np.std(base, ddof=1))
    return mu + k * sd, mu, sd


def truncate_pat(t: ArrayLike, y: ArrayLike, k: float = 3.0, t_baseline: float = 120.0) -> NDArray:
    """PAT-based truncation: zero every sample below mu + k sigma of the baseline window."""
    lvl, _, _ = pat_level(t, y, k, t_baseline)
    return truncate_level(y, max(lvl, 0.0))


def baseline_correct(t: ArrayLike, y: ArrayLike, t_baseline: float = 120.0) -> NDArray[np.float64]:
    """Subtract the mean of the baseline window t >= t_baseline (a PAT offset; not part of the
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
    t_baseline: float = 120.0

    def apply(self, t: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
        if self.kind == "time":
            return truncate_time(t, y, self.value)
        if self.kind == "level":
            return truncate_level(y, self.value)
        if self.kind == "rel":
            return truncate_relative(y, self.value)
        return truncate_pat(t, y, self.value, self.t_baseline)


def parse_spec(spec: str) -> TruncationSpec:
    """Parse ``time:S``, ``level:C``, ``rel:F``, ``pat:K`` or ``pat:K@T``."""
    if ":" not in spec:
        raise ValueError(f"truncate spec must be 'kind:value', got {spec!r}")
    kind, val = spec.split(":", 1)
    kind = kind.strip().lower()
    if kind not in ("time", "level", "rel", "pat"):
        raise ValueError(f"truncate kind must be time, level, rel or pat, got {kind!r}")
    tb = 120.0
    if kind == "pat" and "@" in val:
        val, tbs = val.split("@", 1)
        tb = float(tbs)
    try:
        v = float(val)
    except ValueError:
        raise ValueError(f"truncate value must be a number, got {val!r}") from None
    return TruncationSpec(kind, v, tb)
