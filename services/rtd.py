"""RTD service: tracer-pulse experiments in the NIR signal -> fitted RTD estimates.

Thin shell over ``twin_core``: :class:`twin_core.online.TracerPulseDetector` finds the pulse
(announced by a ``tracer_pulse`` event, or by itself with ``rtd.detect: auto``), then
``twin_core.rtd.outliers.hampel`` removes outliers, ``twin_core.rtd.denoise.denoise`` denoises,
``twin_core.rtd.truncation.truncate_level`` zeroes the samples below ``k`` baseline standard
deviations (the seed's mu + 3 sigma rule) and ``twin_core.rtd.fitting.fit`` fits the model
(free scale: a concentration profile). The estimate is published on ``twin/<line>/rtd/estimate``
(:class:`~schemas.messages.RtdEstimate`, parameters of the ``twin_core.rtd.models`` function
named in ``model``); the blender adopts it when ``blender.adopt_rtd_estimates`` is set. A pulse
found by itself (not announced) while a known feeder disturbance or hopper refill can reach the
outlet (its events, plus the kernel length) is not fitted: it is not a tracer experiment.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import Event, MeasuredConcentration, RtdEstimate
from services.common import LiveService
from twin_core.online import TracerPulseDetector, TracerSegment

log = logging.getLogger(__name__)


@dataclass
class RtdResult:
    """A fitted pulse: the wire fields plus the cleaned profile."""

    model: str
    params: dict[str, float]
    stderr: dict[str, float]
    mean_residence_time_s: float
    pulse_t_s: float
    n_points: int
    rmse: float
    t_rel: np.ndarray
    cleaned: np.ndarray


def analyze_segment(seg: TracerSegment, spec: LineSpec) -> RtdResult:
    """Outliers, denoising, truncation and fit of one tracer segment (see the module docstring)."""
    from twin_core.rtd.denoise import denoise
    from twin_core.rtd.fitting import fit
    from twin_core.rtd.models import get_model
    from twin_core.rtd.outliers import hampel
    from twin_core.rtd.truncation import truncate_level

    s = spec.rtd
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


class RtdService(LiveService):
    """See the module docstring."""

    def __init__(self, spec: LineSpec, **kwargs: Any) -> None:
        super().__init__("rtd", spec, **kwargs)
        self.detector = TracerPulseDetector(
            spec.sensor.sample_period_s,
            max_duration_s=spec.rtd.max_duration_s,
            auto=spec.rtd.detect == "auto",
        )
        self._last_t = -1.0
        self._pending: list[float] = []  # announced pulse times not yet reached
        self._seen_events: set[tuple[str, str, float]] = set()
        self._excluded: list[list[float]] = []  # inlet windows of known non-tracer excursions
        self._open: dict[tuple[str, str], float] = {}

    def setup(self) -> None:
        line = self.spec.name
        self.pub = self.history_publisher(keys.rtd_estimate(line), RtdEstimate)
        self.history_subscribe(
            keys.measured_concentration(line, self.spec.sensor.id), MeasuredConcentration
        )
        self.history_subscribe(f"twin/{line}/*/*/event", Event)

    def handle(self, key: str, msg: Any) -> None:
        if isinstance(msg, Event):
            ident = (key, msg.kind, msg.t)
            if ident in self._seen_events:
                return  # the same event again (history after a restart)
            self._seen_events.add(ident)
            if msg.kind == "tracer_pulse" and msg.component in (None, self.spec.sensor.component):
                self._pending.append(msg.t)
                self._pending.sort()
                self.counters.inc("tracer_events")
            elif msg.kind in ("disturbance", "refill_start"):
                self._open[(key, msg.kind)] = msg.t
                end = msg.t + (msg.duration_s or 0.0)
                self._excluded.append([msg.t, end if msg.duration_s else float("inf")])
            elif msg.kind in ("disturbance_end", "refill_stop"):
                start_kind = "disturbance" if msg.kind == "disturbance_end" else "refill_start"
                t0 = self._open.pop((key, start_kind), None)
                for w in self._excluded:
                    if w[0] == t0 and w[1] == float("inf"):
                        w[1] = msg.t
            return
        if msg.t <= self._last_t or msg.quality == "bad":
            return
        self._last_t = msg.t
        while self._pending and self._pending[0] <= msg.t:
            self.detector.announce(self._pending.pop(0))
        seg = self.detector.push(msg.t, msg.concentration_pct_w_w)
        if seg is not None:
            if not seg.announced and self._disturbed(float(seg.t[0]), float(seg.t[-1])):
                self.counters.inc("pulses_skipped_disturbance")
                return
            self.fit_and_publish(seg)

    def _disturbed(self, a: float, b: float) -> bool:
        """Whether a known feeder disturbance or refill (its inlet window plus the blender's
        kernel length) overlaps [a, b]: such an excursion is not a tracer pulse."""
        lag = self.spec.blender.kernel_s
        return any(w0 <= b and a <= w1 + lag for w0, w1 in self._excluded)

    def fit_and_publish(self, seg: TracerSegment) -> None:
        try:
            r = analyze_segment(seg, self.spec)
        except (ValueError, FloatingPointError) as exc:
            self.counters.inc("fit_failed")
            self.counters.last_error = f"rtd fit of pulse at {seg.t0:.1f} s failed: {exc}"
            log.warning("%s", self.counters.last_error)
            return
        self.pub.publish(
            RtdEstimate(
                t=float(seg.t[-1]),
                seq=self.pub.seq,
                model=r.model,
                params=r.params,
                stderr=r.stderr,
                mean_residence_time_s=r.mean_residence_time_s,
                pulse_t_s=r.pulse_t_s,
                n_points=r.n_points,
                rmse=r.rmse,
            )
        )
        self.counters.inc("estimates")
