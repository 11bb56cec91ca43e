"""Early flag of feeder disturbances from funnel-plot knowledge.

For a linear blender with residence time distribution E(t), a rectangular disturbance of the
inlet concentration of relative size h and duration d gives an outlet deviation (convolution,
Eq. (1) of :mod:`twin_core.online.convolution`) whose maximum is

    max_t dc_out(t) = h c_target * g(d),   g(d) = max_t [F(t) - F(t - d)],          (1)

the largest fraction of the RTD mass inside any window of length d (Engisch & Muzzio 2016,
J. Pharm. Innov. 11:64; the "funnel plot" of the seed, chapter 6: the feasible region is the set
of (d, h) whose maximum outlet deviation stays inside the limit). g on the tick grid is
``twin_core.quality.funnel.funnel_gain`` (the twin's one funnel gain), so a disturbance of
(m ticks, h) is predicted to leave the specification **iff** ``|h| c_target g[m]`` exceeds the
allowed deviation.

:class:`FunnelFlagger` watches the inlet concentration (from the feeder flows), finds deviation
episodes with a :class:`~twin_core.online.alerts.HysteresisTracker` and, as soon as the episode
so far (duration m samples, peak deviation h) is outside the feasible region, flags it: long
before the disturbed material reaches the outlet, because g grows with d and the blender
delays the outlet. The window at the outlet comes from RTD traceability (lot boundaries:
``window(t_in_start, t_in_end) -> (t_out_start, t_out_end)``, e.g.
``twin_core.quality.lots.diversion_window``) or, with ``excursion``, from the episode's own
predicted outlet: ``excursion(t_in_start, deviations) -> (t_out_start, t_out_end) | None``
(``twin_core.quality.lots.excursion_window``: where the convolution of the episode's inlet
deviations with E(t) leaves the guarded specification). A flag's provisional window starts
where the episode so far, its last deviation held, would leave it (or at the lot boundary),
and holds until the final window replaces it (the episode's end is not known yet); the final
window is the whole episode's excursion (the lot window when its prediction stays inside). The rectangle test is
conservative for shapes other than a rectangle (the peak is held over the whole episode).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from twin_core.online.alerts import Episode, HysteresisTracker

__all__ = ["Excursion", "FlagEvent", "FunnelFlagger"]

#: predicted outlet window of an inlet episode: (t_in_start, deviations) -> window or None
Excursion = Callable[[float, np.ndarray], "tuple[float, float] | None"]
#: inlet samples an episode keeps for its excursion (beyond: the lot window), ~1 day at 1 Hz
MAX_EPISODE_SAMPLES = 86400
#: length of a flag's provisional outlet window, s: it holds until the final one replaces it
#: (a window ending at the lot boundary of the episode so far left the product of a longer
#: episode between that end and the final window undiverted)
PROVISIONAL_S = 3600.0


@dataclass
class FlagEvent:
    """A flagged inlet disturbance.

    ``kind``: ``flag`` when the episode first leaves the feasible region (early warning),
    ``close`` when a flagged episode ends (final windows). For ``flag``, ``t_out_end`` is
    provisional: :data:`PROVISIONAL_S` after the window's start, so that the gate diverts
    until the final window replaces it however long the episode lasts.
    """

    kind: Literal["flag", "close"]
    t: float
    id: str
    t_in_start: float
    t_in_end: float
    peak_value: float
    n_samples: int
    predicted_peak_deviation: float
    t_out_start: float
    t_out_end: float


@dataclass
class FunnelFlagger:
    """Streaming early detector of feeder disturbances that will put the outlet out of spec.

    Args:
        target: target concentration (the same at inlet and outlet at steady state), % w/w.
        lower, upper: outlet specification limits, % w/w.
        gain: ``twin_core.quality.funnel.funnel_gain(e, dt)`` of the blender's E(t).
        dt: sampling interval of the inlet stream, s.
        window: RTD traceability ``(t_in_start, t_in_end) -> (t_out_start, t_out_end)``.
        detect: inlet deviation from target that starts an episode, % w/w (> 0).
        n_on, n_off: debounce counts of the inlet episode detector.
        prefix: id prefix.
        excursion: the episode's predicted outlet window (module docstring), or None for the
            lot window alone.
    """

    target: float
    lower: float
    upper: float
    gain: np.ndarray
    dt: float
    window: Callable[[float, float], tuple[float, float]]
    detect: float
    n_on: int = 1
    n_off: int = 1
    prefix: str = "feed"
    excursion: Excursion | None = None
    _tracker: HysteresisTracker = field(init=False, repr=False)
    _flagged: set[str] = field(default_factory=set, repr=False)
    #: recent inlet samples (t, value): those of the active episode, or the last n_on
    _buf: list[tuple[float, float]] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        if not (self.lower < self.target < self.upper):
            raise ValueError(
                f"target must lie inside (lower, upper), got {self.target} not in "
                f"({self.lower}, {self.upper})"
            )
        if not self.detect > 0:
            raise ValueError(f"detect must be > 0, got {self.detect!r}")
        self.gain = np.asarray(self.gain, dtype=float)
        self._tracker = HysteresisTracker(
            self.target - self.detect,
            self.target + self.detect,
            0.0,
            self.n_on,
            self.n_off,
            self.prefix,
        )

    def predicted_peak(self, peak_value: float, n: int) -> float:
        """Predicted peak outlet deviation (signed, % w/w) of a rectangle (n samples, peak)."""
        g = self.gain[min(max(n, 0), self.gain.size - 1)]
        return (peak_value - self.target) * g

    def infeasible(self, peak_value: float, n: int) -> bool:
        """True when the rectangle (n samples, peak) lies outside the funnel's feasible region."""
        dev = self.predicted_peak(peak_value, n)
        return self.target + dev > self.upper or self.target + dev < self.lower

    def _outlet_window(self, kind: Literal["flag", "close"], ep: Episode) -> tuple[float, float]:
        """The outlet window of an episode (module docstring)."""
        t_out_start, t_out_end = self.window(ep.t_start, ep.t_end)
        if kind == "flag":
            t_out_end = t_out_start + PROVISIONAL_S
        if self.excursion is None:
            return t_out_start, t_out_end
        half = 0.5 * self.dt
        x = [v for t, v in self._buf if ep.t_start - half <= t <= ep.t_end + half]
        if not x or len(x) >= MAX_EPISODE_SAMPLES:
            return t_out_start, t_out_end
        dev = np.asarray(x, dtype=float) - self.target
        if kind == "flag":  # the episode so far, its last deviation held
            dev = np.concatenate([dev, np.full(self.gain.size, dev[-1])])
        w = self.excursion(ep.t_start, dev)
        if w is None:
            return t_out_start, t_out_end
        return (w[0], t_out_end) if kind == "flag" else w

    def _event(self, kind: Literal["flag", "close"], t: float, ep: Episode) -> FlagEvent:
        n = int(round((ep.t_end - ep.t_start) / self.dt)) + 1
        t_out_start, t_out_end = self._outlet_window(kind, ep)
        return FlagEvent(
            kind=kind,
            t=t,
            id=ep.id,
            t_in_start=ep.t_start,
            t_in_end=ep.t_end,
            peak_value=ep.peak_value,
            n_samples=n,
            predicted_peak_deviation=self.predicted_peak(ep.peak_value, n),
            t_out_start=float(t_out_start),
            t_out_end=float(t_out_end),
        )

    def push(self, t: float, c_in: float) -> list[FlagEvent]:
        """Process one inlet concentration sample; return flag/close events."""
        out: list[FlagEvent] = []
        self._buf.append((t, c_in))
        for ev in self._tracker.push(t, c_in):
            if ev.kind == "close" and ev.episode.id in self._flagged:
                self._flagged.discard(ev.episode.id)
                out.append(self._event("close", t, ev.episode))
        ep = self._tracker.active
        self._trim(ep)
        if ep is not None and ep.id not in self._flagged:
            n = int(round((t - ep.t_start) / self.dt)) + 1
            if self.infeasible(ep.peak_value, n):
                self._flagged.add(ep.id)
                out.append(self._event("flag", t, ep))
        return out

    def _trim(self, ep: Episode | None) -> None:
        """Keep the active episode's samples (bounded), else the last few."""
        if ep is not None:
            i = 0
            while i < len(self._buf) and self._buf[i][0] < ep.t_start - 0.5 * self.dt:
                i += 1
            del self._buf[: max(i, len(self._buf) - MAX_EPISODE_SAMPLES)]
        elif len(self._buf) > self.n_on + self.n_off + 1:
            del self._buf[: len(self._buf) - (self.n_on + self.n_off + 1)]

    def flush(self) -> list[FlagEvent]:
        """End of stream: close a flagged episode still open."""
        out = []
        for ev in self._tracker.flush():
            if ev.episode.id in self._flagged:
                self._flagged.discard(ev.episode.id)
                out.append(self._event("close", ev.t, ev.episode))
        return out

    def to_state(self) -> dict[str, Any]:
        return {
            "tracker": self._tracker.to_state(),
            "flagged": sorted(self._flagged),
            "buf": [list(x) for x in self._buf],
        }

    def load_state(self, state: dict[str, Any]) -> None:
        """Restore the stream state saved by :meth:`to_state` (parameters stay as constructed)."""
        self._tracker = HysteresisTracker.from_state(state["tracker"])
        self._flagged = set(state["flagged"])
        self._buf = [(float(a), float(b)) for a, b in state.get("buf", [])]
