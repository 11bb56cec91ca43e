"""Streaming detection of tracer-pulse experiments in a PAT (NIR) concentration signal.

While no pulse is in progress the detector keeps a rolling window of the baseline and estimates
its level and noise robustly (median, and 1.4826 x median absolute deviation: the consistent
estimator of a normal standard deviation, Rousseeuw & Croux 1993). A pulse starts when
``n_on`` consecutive samples exceed ``baseline + k_on * sigma``; the segment handed to the RTD
fit begins ``pre_s`` before that (the rise) or at the announced injection time when an event
told it (:meth:`TracerPulseDetector.announce`; the baseline is then the one before the
injection, so an announcement that arrives a few samples after the injection's samples gives the
segment of an in-time one). It ends when, after the peak, ``n_off``
consecutive samples stay below ``baseline + k_off * sigma`` (the seed's mu +/- 3 sigma
truncation level, chapter 6), plus ``tail_s`` of tail, or after ``max_duration_s``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

__all__ = ["TracerSegment", "TracerPulseDetector"]


@dataclass
class TracerSegment:
    """A detected tracer pulse: the samples from the injection (or rise) to the end of the tail.

    ``t0`` is the injection time when announced by an event, else the start of the segment;
    ``baseline`` and ``sigma`` are the pre-pulse level and noise.
    """

    t0: float
    t: np.ndarray
    c: np.ndarray
    baseline: float
    sigma: float
    announced: bool
    peak_t: float
    peak_c: float


@dataclass
class TracerPulseDetector:
    """Online tracer-pulse detector (see the module docstring).

    Args:
        dt: sampling interval, s.
        baseline_s: length of the rolling baseline window, s.
        k_on, k_off: detection and end thresholds in baseline standard deviations.
        n_on, n_off: debounce counts.
        pre_s: samples kept before the detection when no injection was announced, s.
        tail_s: samples kept after the end criterion is met, s.
        max_duration_s: a segment is closed after this long in any case, s.
        min_sigma: floor of the noise estimate (a flat simulated baseline has MAD 0).
        auto: detect pulses by the threshold rule; False: only announced pulses are segmented.
    """

    dt: float
    baseline_s: float = 60.0
    k_on: float = 6.0
    k_off: float = 3.0
    n_on: int = 3
    n_off: int = 10
    pre_s: float = 10.0
    tail_s: float = 10.0
    max_duration_s: float = 600.0
    min_sigma: float = 1e-3
    auto: bool = True
    _base: deque = field(init=False, repr=False)
    _pre: deque = field(init=False, repr=False)
    _seg_t: list = field(default_factory=list, repr=False)
    _seg_c: list = field(default_factory=list, repr=False)
    _state: str = field(default="idle", repr=False)
    _run: int = field(default=0, repr=False)
    _tail_left: int = field(default=0, repr=False)
    _t0: float = field(default=math.nan, repr=False)
    _announced: bool = field(default=False, repr=False)
    _level: tuple[float, float] = field(default=(0.0, 1e-3), repr=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"dt must be > 0, got {self.dt!r}")
        for name in ("baseline_s", "pre_s", "tail_s", "max_duration_s"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        self._n_base = max(3, int(round(self.baseline_s / self.dt)))
        # (t, c) of the baseline, with room for the samples an announcement may come after
        self._base = deque(maxlen=self._n_base + int(round(self.pre_s / self.dt)) + self.n_on)
        self._pre = deque(maxlen=max(1, int(round(self.pre_s / self.dt)) + self.n_on))

    @property
    def in_pulse(self) -> bool:
        return self._state != "idle"

    def baseline(self, before: float = math.inf) -> tuple[float, float]:
        """Baseline level and noise estimate (median, 1.4826 MAD floored at min_sigma) of the
        last ``baseline_s`` of idle samples before plant time ``before``."""
        b = np.array([c for t, c in self._base if t < before][-self._n_base :], dtype=float)
        if b.size < 3:
            return self._level
        med = float(np.median(b))
        sig = max(1.4826 * float(np.median(np.abs(b - med))), self.min_sigma)
        return med, sig

    def announce(self, t_pulse: float) -> None:
        """An event says a pulse was injected at ``t_pulse``: start a segment there."""
        if self._state != "idle":
            return
        self._level = self.baseline(before=t_pulse)
        self._state = "pulse"
        self._announced = True
        self._t0 = float(t_pulse)
        self._seg_t = [t for t, _ in self._pre if t >= t_pulse]
        self._seg_c = [c for t, c in self._pre if t >= t_pulse]
        self._run = 0

    def push(self, t: float, c: float) -> TracerSegment | None:
        """Process one sample; return a segment when a pulse has just ended."""
        if not (math.isfinite(t) and math.isfinite(c)):
            raise ValueError(f"t and c must be finite, got t={t!r}, c={c!r}")
        if self._state == "idle":
            self._pre.append((t, c))
            base, sig = self.baseline()
            ready = min(len(self._base), self._n_base) >= max(3, self._n_base // 2)
            if self.auto and ready and c > base + self.k_on * sig:
                self._run += 1
                if self._run >= self.n_on:
                    self._level = (base, sig)
                    self._state = "pulse"
                    self._announced = False
                    t_first = t - (self.n_on - 1) * self.dt
                    t_from = t_first - self.pre_s
                    self._seg_t = [tt for tt, _ in self._pre if tt >= t_from - 1e-9]
                    self._seg_c = [cc for tt, cc in self._pre if tt >= t_from - 1e-9]
                    self._t0 = self._seg_t[0]
                    self._run = 0
            else:
                self._run = 0
                self._base.append((t, c))
            return None
        self._seg_t.append(t)
        self._seg_c.append(c)
        base, sig = self._level
        if self._state == "pulse":
            peak = max(self._seg_c)
            past_peak = peak > base + self.k_on * sig and c < peak
            if past_peak and c < base + self.k_off * sig:
                self._run += 1
            else:
                self._run = 0
            if self._run >= self.n_off:
                self._state = "tail"
                self._tail_left = int(round(self.tail_s / self.dt))
        elif self._state == "tail":
            self._tail_left -= 1
        done = (self._state == "tail" and self._tail_left <= 0) or (
            t - self._t0 >= self.max_duration_s
        )
        if not done:
            return None
        return self._finish()

    def _finish(self) -> TracerSegment:
        base, sig = self._level
        tt = np.asarray(self._seg_t)
        cc = np.asarray(self._seg_c)
        i = int(np.argmax(cc))
        seg = TracerSegment(
            t0=self._t0,
            t=tt,
            c=cc,
            baseline=base,
            sigma=sig,
            announced=self._announced,
            peak_t=float(tt[i]),
            peak_c=float(cc[i]),
        )
        self._state = "idle"
        self._seg_t, self._seg_c = [], []
        self._pre.clear()
        self._run = 0
        return seg

    def flush(self) -> TracerSegment | None:
        """End of stream: return a pulse in progress (if it has samples)."""
        if self._state == "idle" or not self._seg_t:
            return None
        return self._finish()
