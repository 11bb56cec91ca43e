"""Tracer-pulse experiments in the live NIR signal -> fitted RTD estimates (the rtd service's core).

:class:`~twin_core.online.tracer.TracerPulseDetector` finds the pulse (announced by a
``tracer_pulse`` event, or by itself with ``rtd.detect: auto``); :func:`analyze_segment` then
removes outliers (``twin_core.rtd.outliers.hampel``), denoises (``twin_core.rtd.denoise``),
zeroes the samples below ``k`` baseline standard deviations (``truncate_level``: the seed's
mu + 3 sigma rule, chapter 6) and fits the model (``twin_core.rtd.fitting.fit``, free scale: a
concentration profile). A pulse found by itself (not announced) while a known feeder disturbance
or hopper refill can reach the outlet is not fitted: it is not a tracer experiment. Disturbances
come from their events; refills from the feeders' ``refilling`` flags (the one source of refill
state). The window of an excursion at the inlet reaches the outlet within the blender's kernel
length.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np

from schemas.line import LineSpec, RtdSettings
from twin_core.online.tracer import TracerPulseDetector, TracerSegment

__all__ = ["PulseOutcome", "RtdCore", "RtdResult", "analyze_segment"]


@dataclass
class RtdResult:
    """A fitted pulse: the estimate's fields plus the cleaned profile."""

    model: str
    params: dict[str, float]
    stderr: dict[str, float]
    mean_residence_time_s: float
    pulse_t_s: float
    n_points: int
    rmse: float
    t_rel: np.ndarray
    cleaned: np.ndarray


def analyze_segment(seg: TracerSegment, settings: RtdSettings) -> RtdResult:
    """Outliers, denoising, truncation and fit of one tracer segment (module docstring).

    The mean residence time is the first moment of the fitted E(t),
    int t E dt / int E dt (trapezoid on a grid reaching 4x the segment, at least 600 s).
    """
    from twin_core.rtd.denoise import denoise
    from twin_core.rtd.fitting import fit
    from twin_core.rtd.models import get_model
    from twin_core.rtd.outliers import hampel
    from twin_core.rtd.truncation import truncate_level

    s = settings
    t_rel = seg.t - seg.t0
    y = seg.c - seg.baseline
    y = np.asarray(hampel(y, n_sigma=s.hampel_n_sigma, t=t_rel).y, float)
    if s.denoise != "none" and y.size >= 8:
        y = np.asarray(denoise(y, s.denoise).y, float)
    y = np.asarray(truncate_level(y, s.truncation_k * seg.sigma), float)
    res = fit(t_rel, y, s.model, scale="free")
    mspec = get_model(s.model)
    params = {k: float(res.params[k]) for k in mspec.params}
    stderr = {k: float(res.stderr[k]) for k in mspec.params if np.isfinite(res.stderr[k])}
    tg = np.linspace(0.0, max(float(t_rel[-1]) * 4, 600.0), 20001)
    e = np.asarray(mspec.func(tg, *[params[k] for k in mspec.params]), float)
    area = np.trapezoid(e, tg)
    mrt = float(np.trapezoid(tg * e, tg) / area) if area > 0 else float("nan")
    return RtdResult(
        model=mspec.func.__name__,
        params=params,
        stderr=stderr,
        mean_residence_time_s=mrt,
        pulse_t_s=float(seg.t0),
        n_points=int(t_rel.size),
        rmse=float(np.sqrt(res.rss / max(res.n, 1))),
        t_rel=t_rel,
        cleaned=y,
    )


@dataclass
class PulseOutcome:
    """What became of a detected pulse: ``fitted`` (``result``), ``skipped_disturbance`` (found
    by itself while a known excursion could reach the outlet) or ``fit_failed`` (``error``)."""

    kind: Literal["fitted", "skipped_disturbance", "fit_failed"]
    segment: TracerSegment
    result: RtdResult | None = None
    error: str = ""


class RtdCore:
    """Events, feeder refill flags and NIR samples in; tracer pulses fitted (module docstring).

    Args:
        spec: the line (sensor, rtd settings, blender kernel length).
    """

    def __init__(self, spec: LineSpec) -> None:
        self.settings = spec.rtd
        self.component = spec.sensor.component
        #: how long an inlet excursion can affect the outlet, s
        self.reach_s = spec.blender.kernel_s
        self.detector = TracerPulseDetector(
            spec.sensor.sample_period_s,
            max_duration_s=spec.rtd.max_duration_s,
            auto=spec.rtd.detect == "auto",
        )
        self._last_t = -1.0
        self._pending: list[float] = []  # announced pulse times not yet reached
        self._announced: set[float] = set()
        self._excluded: list[list[float]] = []  # inlet windows of known non-tracer excursions
        self._open: dict[tuple[str, str], list[float]] = {}
        self._refilling: dict[str, bool] = {}
        self.duplicates = 0

    # -- what can reach the outlet -----------------------------------------------------------
    def _open_window(self, key: tuple[str, str], t: float, end: float = math.inf) -> None:
        w = [t, end]
        self._excluded.append(w)
        if math.isinf(end):
            self._open[key] = w

    def _close_window(self, key: tuple[str, str], t: float) -> None:
        w = self._open.pop(key, None)
        if w is not None:
            w[1] = t

    def add_event(self, event: Mapping) -> bool:
        """A plant event (dict form, ``twin_core.online.inlet.event_record``): announced tracer
        pulses of the measured component and feeder disturbances. Returns whether it announced a
        new tracer pulse."""
        kind, t, source = event.get("kind"), float(event["t_s"]), str(event.get("source"))
        if kind == "tracer_pulse" and event.get("component") in (None, self.component):
            if t in self._announced:
                self.duplicates += 1
                return False
            self._announced.add(t)
            self._pending.append(t)
            self._pending.sort()
            return True
        if kind == "disturbance":
            dur = event.get("duration_s")
            self._open_window(("disturbance", source), t, t + dur if dur else math.inf)
        elif kind == "disturbance_end":
            self._close_window(("disturbance", source), t)
        return False

    def flow(self, feeder: str, t: float, refilling: bool) -> None:
        """A feeder's refill flag: a refill opens an excluded window until the flag drops."""
        was = self._refilling.get(feeder, False)
        if refilling and not was:
            self._open_window(("refill", feeder), t)
        elif was and not refilling:
            self._close_window(("refill", feeder), t)
        self._refilling[feeder] = refilling

    def disturbed(self, a: float, b: float) -> bool:
        """Whether a known feeder disturbance or refill (its inlet window plus the blender's
        kernel length) overlaps [a, b]."""
        return any(w0 <= b and a <= w1 + self.reach_s for w0, w1 in self._excluded)

    # -- the signal --------------------------------------------------------------------------
    def measured(self, t: float, c: float) -> PulseOutcome | None:
        """One NIR sample of the measured component (good or suspect quality); returns the
        outcome of a pulse that has just ended."""
        if t <= self._last_t:
            return None
        self._last_t = t
        while self._pending and self._pending[0] <= t:
            self.detector.announce(self._pending.pop(0))
        seg = self.detector.push(t, c)
        if seg is None:
            return None
        if not seg.announced and self.disturbed(float(seg.t[0]), float(seg.t[-1])):
            return PulseOutcome("skipped_disturbance", seg)
        try:
            return PulseOutcome("fitted", seg, analyze_segment(seg, self.settings))
        except (ValueError, FloatingPointError) as exc:
            return PulseOutcome(
                "fit_failed", seg, error=f"rtd fit of pulse at {seg.t0:.1f} s failed: {exc}"
            )
