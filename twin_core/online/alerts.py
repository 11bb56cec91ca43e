"""Out-of-specification (OOS) episode tracking on a stream, with hysteresis and stable ids.

A sample is *out* when it lies outside the specification ``[lower, upper]``; it is *back in*
when it lies inside the narrower band ``[lower + hysteresis, upper - hysteresis]``. An episode
opens after ``n_on`` consecutive out samples and closes after ``n_off`` consecutive back-in
samples (a Schmitt trigger with a debounce count, the usual alarm-management practice: ISA-18.2 /
EEMUA 191 "deadband" and "on/off delay"). Its start is the time of the first out sample of the
opening run and its end the time of the last out sample before the closing run, so the debounce
delays the *decision*, not the window.

Episode ids are derived from the data only (``<prefix>-<start time in ms>``), so a tracker
restarted from its saved state, or replaying the same data, reproduces the same ids; episodes of
one tracker never overlap, so the start time makes the id unique.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Literal

__all__ = ["Episode", "EpisodeEvent", "HysteresisTracker", "episode_id"]


def episode_id(prefix: str, t_start_s: float) -> str:
    """Stable id of an episode: ``<prefix>-<start in integer milliseconds, zero-padded>``."""
    if not math.isfinite(t_start_s) or t_start_s < 0:
        raise ValueError(f"t_start_s must be finite and >= 0, got {t_start_s!r}")
    return f"{prefix}-{int(round(t_start_s * 1000.0)):012d}"


@dataclass
class Episode:
    """One out-of-specification episode.

    Attributes:
        id: stable id (see :func:`episode_id`).
        t_start: time of the first out sample, s.
        t_end: time of the last out sample seen so far (final once closed), s.
        peak_value: value of the sample farthest outside the specification.
        peak_excess: how far outside the limits that sample was (>= 0).
        n_out: number of out samples in the episode.
        closed: True once the episode has closed.
    """

    id: str
    t_start: float
    t_end: float
    peak_value: float
    peak_excess: float
    n_out: int = 0
    closed: bool = False


@dataclass
class EpisodeEvent:
    """A transition reported by a tracker: ``open`` or ``close`` of ``episode`` at time ``t``.

    ``episode`` is a snapshot taken at the transition (later samples do not change it).
    """

    kind: Literal["open", "close"]
    t: float
    episode: Episode


@dataclass
class HysteresisTracker:
    """Streaming OOS episode detector with deadband and on/off debounce.

    Args:
        lower, upper: specification limits (same unit as the values).
        hysteresis: deadband inside the limits a value must reach to count as back in (>= 0).
        n_on: consecutive out samples that open an episode (>= 1).
        n_off: consecutive back-in samples that close it (>= 1).
        prefix: id prefix (a key-expression-safe token such as ``line1.api.measured``).

    Use :meth:`push` for each sample in time order; it returns the transitions it caused.
    :meth:`to_state`/:meth:`from_state` save and restore the exact state.
    """

    lower: float
    upper: float
    hysteresis: float = 0.0
    n_on: int = 1
    n_off: int = 1
    prefix: str = "oos"
    # --- state
    _run_out: int = field(default=0, repr=False)
    _cand_start: float = field(default=0.0, repr=False)
    _cand_peak: tuple[float, float] = field(default=(0.0, -1.0), repr=False)
    _run_in: int = field(default=0, repr=False)
    _active: Episode | None = field(default=None, repr=False)
    _t_last: float = field(default=-math.inf, repr=False)

    def __post_init__(self) -> None:
        for name in ("lower", "upper", "hysteresis"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise ValueError(f"{name} must be finite, got {v!r}")
        if self.upper <= self.lower:
            raise ValueError(f"upper must be > lower, got upper={self.upper}, lower={self.lower}")
        if self.hysteresis < 0 or 2 * self.hysteresis >= self.upper - self.lower:
            raise ValueError(
                f"hysteresis must be >= 0 and < (upper-lower)/2, got {self.hysteresis!r}"
            )
        if self.n_on < 1:
            raise ValueError(f"n_on must be >= 1, got {self.n_on!r}")
        if self.n_off < 1:
            raise ValueError(f"n_off must be >= 1, got {self.n_off!r}")

    # ------------------------------------------------------------------
    def excess(self, value: float) -> float:
        """Distance outside [lower, upper] (0 inside)."""
        if value > self.upper:
            return value - self.upper
        if value < self.lower:
            return self.lower - value
        return 0.0

    @property
    def active(self) -> Episode | None:
        """The open episode, if any."""
        return self._active

    def push(self, t: float, value: float) -> list[EpisodeEvent]:
        """Process one sample (time ``t`` strictly increasing); return the transitions it caused."""
        if not (math.isfinite(t) and math.isfinite(value)):
            raise ValueError(f"t and value must be finite, got t={t!r}, value={value!r}")
        if t <= self._t_last:
            raise ValueError(f"t must increase, got t={t!r} after {self._t_last!r}")
        self._t_last = t
        ex = self.excess(value)
        out = ex > 0.0
        events: list[EpisodeEvent] = []
        ep = self._active
        if ep is None:
            if out:
                if self._run_out == 0:
                    self._cand_start = t
                    self._cand_peak = (value, ex)
                elif ex > self._cand_peak[1]:
                    self._cand_peak = (value, ex)
                self._run_out += 1
                if self._run_out >= self.n_on:
                    pv, pe = self._cand_peak
                    ep = Episode(
                        id=episode_id(self.prefix, self._cand_start),
                        t_start=self._cand_start,
                        t_end=t,
                        peak_value=pv,
                        peak_excess=pe,
                        n_out=self._run_out,
                    )
                    self._active = ep
                    self._run_out = 0
                    self._run_in = 0
                    events.append(EpisodeEvent("open", t, replace(ep)))
            else:
                self._run_out = 0
            return events
        # an episode is open
        if out:
            ep.t_end = t
            ep.n_out += 1
            if ex > ep.peak_excess:
                ep.peak_value, ep.peak_excess = value, ex
            self._run_in = 0
        elif self.lower + self.hysteresis <= value <= self.upper - self.hysteresis:
            self._run_in += 1
            if self._run_in >= self.n_off:
                ep.closed = True
                self._active = None
                self._run_in = 0
                events.append(EpisodeEvent("close", t, replace(ep)))
        else:
            self._run_in = 0  # inside the limits but within the deadband: not yet back
        return events

    def flush(self) -> list[EpisodeEvent]:
        """Close an open episode at the end of a stream (its end is the last out sample)."""
        ep = self._active
        if ep is None:
            return []
        ep.closed = True
        self._active = None
        self._run_in = 0
        return [EpisodeEvent("close", self._t_last, replace(ep))]

    # ------------------------------------------------------------------
    def to_state(self) -> dict[str, Any]:
        """JSON-able state, restorable with :meth:`from_state`."""
        return {
            "params": [self.lower, self.upper, self.hysteresis, self.n_on, self.n_off, self.prefix],
            "run_out": self._run_out,
            "cand_start": self._cand_start,
            "cand_peak": list(self._cand_peak),
            "run_in": self._run_in,
            "active": asdict(self._active) if self._active is not None else None,
            "t_last": self._t_last if math.isfinite(self._t_last) else None,
        }

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> HysteresisTracker:
        lo, up, hy, n_on, n_off, prefix = state["params"]
        obj = cls(lo, up, hy, int(n_on), int(n_off), prefix)
        obj._run_out = int(state["run_out"])
        obj._cand_start = float(state["cand_start"])
        obj._cand_peak = (float(state["cand_peak"][0]), float(state["cand_peak"][1]))
        obj._run_in = int(state["run_in"])
        obj._active = Episode(**state["active"]) if state["active"] is not None else None
        obj._t_last = -math.inf if state["t_last"] is None else float(state["t_last"])
        return obj
