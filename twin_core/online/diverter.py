"""OOS decisions of the diverter for one component: alerts and divert commands, deterministic.

Three views of the outlet concentration are combined, all in plant time:

1. **Feeder disturbances, traced** (early). The inlet composition (from the feeder flows) is
   watched by a :class:`~twin_core.online.funnel.FunnelFlagger`: an inlet episode outside the
   funnel's feasible region is flagged while it is still at the inlet. Its outlet window comes
   from RTD traceability (lot boundaries: ``[t_in_start + t_lo, t_in_end + t_hi]``, Engisch &
   Muzzio 2016). A ``divert`` command with the provisional window is issued at the flag, the
   alert and the final ``divert`` window when the inlet episode ends.
2. **Predicted outlet** (blender model) and 3. **measured outlet** (NIR): each through a
   :class:`~twin_core.online.alerts.HysteresisTracker`. An episode that starts inside a traced
   window (to within one tick) is the same event (it confirms it, counted, no new alert). Otherwise it is an alert of
   its own: ``divert`` from its start when it opens, alert and final window when it closes.

4. **Close-loop findings with the product at risk** (late, from the model check): when the data
   cannot tell a probe-side from a product-side explanation of a window, the twin acts on the
   product-side reading (``schemas.closeloop.ModelFinding.product_reading``): if that reading's
   outlet leaves the specification, the stretches it puts out of specification that no divert
   window covers yet are diverted (alert and ``divert`` at once, source ``closeloop``): the
   NIR's in-spec reading may be the probe's error, not the product's quality.

Outputs carry stable ids derived from the data (``<line>.<component>.<source>-<start ms>``, with
``.open``/``.final`` for commands), so replaying the same data gives the same outputs and a
consumer (or a restarted diverter) can drop what it has already seen. Inputs must come in plant
time order across the three streams (the service merges them by a watermark).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from twin_core.online.alerts import EpisodeEvent, HysteresisTracker, episode_id
from twin_core.online.funnel import Excursion, FlagEvent, FunnelFlagger

__all__ = ["DiverterOutput", "OosDecider"]


@dataclass
class DiverterOutput:
    """An alert or a divert command decided at plant time ``t``.

    ``kind``: ``alert`` (complete episode) or ``divert`` (window to send to waste).
    ``id``: the alert id (alerts) or command id (divert); ``alert_id``: the alert it belongs to.
    ``source``: ``feed`` (traced feeder disturbance), ``predicted``, ``measured`` or
    ``closeloop`` (a finding whose product-side reading is out of specification).
    """

    kind: Literal["alert", "divert"]
    t: float
    id: str
    alert_id: str
    source: str
    component: str
    t_start: float
    t_end: float
    peak_deviation: float
    limit: float
    cause: str


@dataclass
class OosDecider:
    """Alerts and divert commands for one component (see the module docstring).

    Args:
        line, component: used in ids and messages.
        target, lower, upper: specification at the outlet, % w/w.
        dt: tick of the inlet stream, s.
        gain: the funnel gain of the blender E(t) on the inlet tick
            (``twin_core.quality.funnel.funnel_gain``), or None to skip the early feeder flag.
        window: traceability ``(t_in_start, t_in_end) -> (t_out_start, t_out_end)``.
        n_on, n_off, hysteresis: outlet episode debounce and deadband.
        inlet_detect, inlet_n_on, inlet_n_off: inlet episode detector.
        excursion: the predicted outlet window of an inlet episode
            (``twin_core.online.funnel.FunnelFlagger``), or None for the lot window.
    """

    line: str
    component: str
    target: float
    lower: float
    upper: float
    dt: float
    gain: np.ndarray | None
    window: Callable[[float, float], tuple[float, float]]
    n_on: int = 3
    n_off: int = 3
    hysteresis: float = 0.05
    inlet_detect: float = 0.3
    inlet_n_on: int = 1
    inlet_n_off: int = 3
    excursion: Excursion | None = None
    confirmed_: dict[str, int] = field(default_factory=lambda: {"predicted": 0, "measured": 0})
    _flagger: FunnelFlagger | None = field(init=False, repr=False)
    _trackers: dict[str, HysteresisTracker] = field(init=False, repr=False)
    _windows: list[list[float]] = field(default_factory=list, repr=False)
    _own: dict[str, bool] = field(default_factory=dict, repr=False)
    #: index in ``_windows`` of each flagged inlet episode's provisional window
    _open: dict[str, int] = field(default_factory=dict, repr=False)
    #: inlet ticks that held tracer (plant time, kg of this component), the latest ones
    _tracer: deque[tuple[float, float]] = field(
        default_factory=lambda: deque(maxlen=10_000), repr=False
    )

    def __post_init__(self) -> None:
        base = f"{self.line}.{self.component}"
        self._flagger = None
        if self.gain is not None:
            self._flagger = FunnelFlagger(
                self.target,
                self.lower,
                self.upper,
                self.gain,
                self.dt,
                self.window,
                detect=self.inlet_detect,
                n_on=self.inlet_n_on,
                n_off=self.inlet_n_off,
                prefix=f"{base}.feed",
                excursion=self.excursion,
            )
        self._trackers = {
            src: HysteresisTracker(
                self.lower, self.upper, self.hysteresis, self.n_on, self.n_off, f"{base}.{src}"
            )
            for src in ("predicted", "measured")
        }

    def set_funnel(
        self,
        gain: np.ndarray | None,
        window: Callable[[float, float], tuple[float, float]],
        excursion: Excursion | None = None,
    ) -> None:
        """A new E(t) (the model the blender adopted): its funnel gain, traceability and
        predicted excursions apply to the inlet episodes from now on (an episode in progress
        keeps its id)."""
        self.gain, self.window, self.excursion = gain, window, excursion
        if self._flagger is not None and gain is not None:
            self._flagger.gain = np.asarray(gain, dtype=float)
            self._flagger.window = window
            self._flagger.excursion = excursion

    @property
    def limit(self) -> float:
        """Allowed absolute deviation (the tighter side), % w/w."""
        return min(self.upper - self.target, self.target - self.lower)

    # ------------------------------------------------------------------ inputs
    def inlet(self, t: float, x_pct: float, tracer_kg: float = 0.0) -> list[DiverterOutput]:
        """One inlet composition sample (% w/w of this component); ``tracer_kg``: the mass of
        announced tracer of this component in it (an alert then names the tracer pulse)."""
        if tracer_kg > 0:
            self._tracer.append((t, tracer_kg))
        if self._flagger is None:
            return []
        return [o for ev in self._flagger.push(t, x_pct) for o in self._from_flag(ev)]

    def predicted(self, t: float, c: float) -> list[DiverterOutput]:
        """One predicted outlet concentration (% w/w)."""
        return self._outlet("predicted", t, c)

    def measured(self, t: float, c: float) -> list[DiverterOutput]:
        """One measured outlet concentration (% w/w)."""
        return self._outlet("measured", t, c)

    def product_risk(
        self,
        t: float,
        finding_id: str,
        t_start: float,
        t_end: float,
        outlet_min: float,
        outlet_max: float,
        spans: Sequence[Sequence[float]] | None = None,
    ) -> list[DiverterOutput]:
        """A close-loop finding with the product at risk (module docstring, item 4): its
        product-side outlet range over [t_start, t_end] and, when the finding names them, the
        stretches ``spans`` ([first, last] s) it puts out of specification. Each part of those
        stretches that no divert window covers yet is diverted (alert and ``divert``, once per
        part): a stretch the twin already diverted (a traced disturbance the reading also
        shows) is not diverted again, and the rest of the window is kept. Without ``spans``
        (an older finding) the whole window is diverted when the range leaves the
        specification."""
        low, high = outlet_min < self.lower, outlet_max > self.upper
        if not (low or high):
            return []
        parts = [(t_start, t_end)] if spans is None else self._uncovered(spans)
        peak = (
            outlet_min
            if low and (self.target - outlet_min >= outlet_max - self.target or not high)
            else outlet_max
        )
        cause = (
            f"close-loop finding {finding_id}: the data cannot tell a probe-side from a "
            f"product-side explanation; the product-side reading puts the {self.component} "
            f"outlet at {outlet_min:.3f}..{outlet_max:.3f} % w/w, outside "
            f"[{self.lower}, {self.upper}]"
        )
        out: list[DiverterOutput] = []
        for a, b in parts:
            aid = episode_id(f"{self.line}.{self.component}.closeloop", a)
            if aid in self._own:
                continue
            self._own[aid] = True
            common = dict(
                t=t,
                alert_id=aid,
                source="closeloop",
                component=self.component,
                t_start=a,
                t_end=b,
                peak_deviation=peak - self.target,
                limit=self.limit,
                cause=cause,
            )
            self._windows.append([a, b])
            out += [
                DiverterOutput(kind="alert", id=aid, **common),
                DiverterOutput(kind="divert", id=f"{aid}.final", **common),
            ]
        return out

    def _uncovered(self, spans: Sequence[Sequence[float]]) -> list[tuple[float, float]]:
        """The parts of ``spans`` ([a, b], s) outside every divert window (one tick of slack,
        as :meth:`_covered`), each at least a tick long."""
        parts = [(float(a), float(b)) for a, b in spans]
        for wa, wb in self._windows:
            lo, hi = wa - self.dt, wb + self.dt
            nxt: list[tuple[float, float]] = []
            for a, b in parts:
                if b < lo or a > hi:
                    nxt.append((a, b))
                    continue
                if a < lo:
                    nxt.append((a, lo))
                if b > hi:
                    nxt.append((hi, b))
            parts = nxt
        return [(a, b) for a, b in parts if b - a >= self.dt]

    def flush(self) -> list[DiverterOutput]:
        """End of the streams: close what is open."""
        out: list[DiverterOutput] = []
        if self._flagger is not None:
            for ev in self._flagger.flush():
                out += self._from_flag(ev)
        for src, tr in self._trackers.items():
            for ev in tr.flush():
                out += self._from_episode(src, ev)
        return out

    # ------------------------------------------------------------------ internals
    def _inlet_cause(self, ev: FlagEvent) -> str:
        """What went in: a tracer pulse (every sample of the episode held announced tracer),
        an inlet disturbance of the feeder flows, or both."""
        ticks = [
            (t, kg) for t, kg in self._tracer if ev.t_in_start - self.dt < t < ev.t_in_end + self.dt
        ]
        peak = f"inlet peak {ev.peak_value:.3f} % w/w over {ev.n_samples} samples"
        if not ticks:
            return (
                f"inlet disturbance of {self.component} (feeder flows) from "
                f"{ev.t_in_start:.1f} s ({peak})"
            )
        pulse = f"{1000 * sum(kg for _, kg in ticks):.4g} g injected at {ticks[0][0]:.1f} s"
        if ev.n_samples <= len(ticks):
            return f"tracer pulse of {self.component} ({pulse}; {peak})"
        return (
            f"inlet disturbance of {self.component} (feeder flows, with a tracer pulse of "
            f"{pulse}) from {ev.t_in_start:.1f} s ({peak})"
        )

    def _from_flag(self, ev: FlagEvent) -> list[DiverterOutput]:
        dev = ev.predicted_peak_deviation
        cause = (
            f"{self._inlet_cause(ev)} is outside the funnel's feasible region: predicted outlet "
            f"deviation {dev:+.3f} % w/w"
        )
        common = dict(
            t=ev.t,
            alert_id=ev.id,
            source="feed",
            component=self.component,
            t_start=ev.t_out_start,
            t_end=ev.t_out_end,
            peak_deviation=dev,
            limit=self.limit,
            cause=cause,
        )
        if ev.kind == "flag":
            self._open[ev.id] = len(self._windows)
            self._windows.append([ev.t_out_start, math.inf])
            return [DiverterOutput(kind="divert", id=f"{ev.id}.open", **common)]
        i = self._open.pop(ev.id, None)
        if i is not None:  # the final window replaces the provisional one
            self._windows[i] = [ev.t_out_start, ev.t_out_end]
        else:
            self._windows.append([ev.t_out_start, ev.t_out_end])
        return [
            DiverterOutput(kind="alert", id=ev.id, **common),
            DiverterOutput(kind="divert", id=f"{ev.id}.final", **common),
        ]

    def _covered(self, t: float) -> bool:
        # one tick of slack: windows and episodes are both resolved to the sampling grid
        return any(a - self.dt <= t <= b + self.dt for a, b in self._windows)

    def _outlet(self, src: str, t: float, c: float) -> list[DiverterOutput]:
        out: list[DiverterOutput] = []
        for ev in self._trackers[src].push(t, c):
            out += self._from_episode(src, ev)
        return out

    def _from_episode(self, src: str, ev: EpisodeEvent) -> list[DiverterOutput]:
        ep = ev.episode
        if ev.kind == "open":
            own = not self._covered(ep.t_start)
            self._own[ep.id] = own
            if not own:
                self.confirmed_[src] += 1
                return []
        elif not self._own.pop(ep.id, False):
            return []
        dev = ep.peak_value - self.target
        where = "NIR" if src == "measured" else "blender model"
        cause = (
            f"{src} outlet concentration of {self.component} ({where}) out of "
            f"[{self.lower}, {self.upper}] % w/w, peak {ep.peak_value:.3f}; no traced feeder "
            f"disturbance"
        )
        common = dict(
            t=ev.t,
            alert_id=ep.id,
            source=src,
            component=self.component,
            t_start=ep.t_start,
            t_end=ep.t_end,
            peak_deviation=dev,
            limit=self.limit,
            cause=cause,
        )
        if ev.kind == "open":
            self._windows.append([ep.t_start, math.inf])
            return [DiverterOutput(kind="divert", id=f"{ep.id}.open", **common)]
        for w in self._windows:
            if w[0] == ep.t_start and math.isinf(w[1]):
                w[1] = ep.t_end
                break
        return [
            DiverterOutput(kind="alert", id=ep.id, **common),
            DiverterOutput(kind="divert", id=f"{ep.id}.final", **common),
        ]
