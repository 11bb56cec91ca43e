"""The twin's record of a line on its tick grid: bus messages in, the arrays of the declared line
model out (``twin_core.plant.LineInputs``, the NIR readings, the events).

:class:`LineRecord` is the one message-to-array adapter, keyed by feeder id (the ``<id>`` of
``twin/<line>/feeder/<id>/flow``; two feeders of one component stay two inputs). The close-loop
uses it online (``twin_core.closeloop.online.OnlineCloseLoop``, window by window) and offline
(``twin close-loop`` on a recording: :meth:`LineRecord.from_messages`, then
:meth:`LineRecord.run_data`). It is fed decoded messages (``schemas.messages``), so it needs no
bus and no file format.

- Feeder samples are aligned into complete ticks (``twin_core.online.inlet.InletAligner``, the
  one alignment of the inlet); a tick missing in a window holds the previous one (the first
  available at the start).
- NIR readings of the sensor's component (not of ``bad`` quality) are kept at their tick; a
  missing reading is NaN (left out of the fit).
- Tracer pulses come from the ``tracer_pulse`` events (``twin_core.online.inlet.tracer_pulse``).
- The raw stamps (and sequence numbers) of every stream's messages are kept in arrival order
  for the data-quality check (``twin_core.closeloop.quality``: time jumps, duplicate stamps,
  dropouts), which the tick grid would hide.
- Every message's place in the arrival order of the record is kept with its stamp; a message
  received twice (same stamp, sequence number and values as the stream's one before) is
  dropped and its stamp kept (``StreamStamps.resent``, noted by the data-quality check).
- Offline (:meth:`LineRecord.from_messages`) a source whose clock is off the others' is put
  back on the common clock before its samples are placed on the ticks: the offsets are
  estimated from the arrival order (``twin_core.closeloop.quality.estimate_clock_offsets``)
  and reported (``RunData.clock_offsets``); the raw stamps are kept for the data-quality check.
- Two readings of a stream on one tick (jitter, irregular sampling): the NIR keeps the one
  stamped nearer the tick (interpolating between noisy readings would average their noise and
  correlate it, which the noise tests read as structure).
- Refill state comes from the feeders' ``refilling`` flags only: ``refill_start`` /
  ``refill_stop`` events on the bus are not read; the events of a window carry refill events at
  the flags' edges instead.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from schemas.line import TracerPulse
from twin_core.closeloop.data import ClockOffset, RunData, StreamStamps
from twin_core.closeloop.quality import NIR as NIR_STREAM
from twin_core.closeloop.quality import estimate_clock_offsets
from twin_core.online.inlet import FeederSample, InletAligner, event_record, tracer_pulse
from twin_core.plant.model import LineInputs

__all__ = ["LineRecord", "REFILL_EVENTS"]

#: event kinds of refill state on the bus, superseded by the feeders' refill flags
REFILL_EVENTS = ("refill_start", "refill_stop")

#: how far before a window a tracer pulse is still kept (its response is still in the blender), s
TRACER_REACH_S = 600.0


class LineRecord:
    """Feeder samples, NIR readings, tracer pulses and events of a line, on its tick grid (see
    the module docstring).

    Args:
        components: feeder id -> component.
        dt_s: tick, s.
        sensor_component: the component the NIR probe measures.
        max_lag: ticks a feeder may lag before its last value is held (``InletAligner``).
    """

    def __init__(
        self,
        components: Mapping[str, str],
        dt_s: float,
        sensor_component: str,
        max_lag: int = 600,
    ) -> None:
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
        self.components = dict(components)
        self.dt_s = float(dt_s)
        self.sensor_component = sensor_component
        self._aligner = InletAligner(list(self.components), self.dt_s, max_lag=max_lag)
        self._ticks: dict[int, dict[str, FeederSample]] = {}
        self._meas: dict[int, float] = {}
        self._tracers: dict[tuple[float, str], TracerPulse] = {}
        self._events: list[dict[str, Any]] = []
        #: raw (t, seq, arrival) of each stream's messages in arrival order (``nir``,
        #: ``<feeder>:flow``)
        self._stamps: dict[str, list[tuple[float, int, int]]] = {}
        #: stamps of the messages received twice (the copies dropped), per stream
        self._resent: dict[str, list[float]] = {}
        #: the last message of each stream (stamp, seq, values), to tell a re-sent copy
        self._last: dict[str, tuple[Any, ...]] = {}
        #: messages received so far (the arrival position of the next one)
        self._arrived = 0
        #: distance of each NIR reading's stamp from its tick (the nearer one is kept)
        self._meas_dist: dict[int, float] = {}
        #: per stream, the clock offset (s) subtracted from its stamps before placing them
        self.clock_offsets: dict[str, ClockOffset] = {}
        #: first tick of the record (the first feeder sample)
        self.first_tick: int | None = None

    def tick(self, t: float) -> int:
        """Tick index of plant time t."""
        return int(round(t / self.dt_s))

    def _arrive(self, stream: str, t: float, seq: int, values: tuple[Any, ...]) -> float | None:
        """Keep a message's raw stamp and arrival position; None if it is a re-sent copy of the
        stream's message before (dropped, its stamp kept), else its time on the common
        clock (the stamp less the stream's clock offset)."""
        key = (float(t), int(seq), *values)
        if self._last.get(stream) == key:
            self._resent.setdefault(stream, []).append(float(t))
            return None
        self._last[stream] = key
        self._stamps.setdefault(stream, []).append((float(t), int(seq), self._arrived))
        self._arrived += 1
        co = self.clock_offsets.get(stream)
        return float(t) - (co.offset_s if co is not None else 0.0)

    # -- input -------------------------------------------------------------------------------
    def add_flow(
        self,
        feeder: str,
        t: float,
        flow_kg_h: float,
        refilling: bool = False,
        screw_speed_rpm: float = math.nan,
        seq: int = -1,
    ) -> None:
        """A reported feeder flow (kg/h) at plant time t, with its refill flag and screw speed
        (``seq``: the message's sequence number, -1 unknown)."""
        if feeder not in self.components:
            raise ValueError(f"feeder must be one of {sorted(self.components)}, got {feeder!r}")
        if not np.isfinite(flow_kg_h) or flow_kg_h < 0:
            raise ValueError(f"flow_kg_h must be finite and >= 0, got {flow_kg_h!r}")
        sample = FeederSample(float(flow_kg_h), bool(refilling), float(screw_speed_rpm))
        tc = self._arrive(f"{feeder}:flow", t, seq, tuple(sample))
        if tc is None:
            return
        t = tc
        if self.first_tick is None:
            self.first_tick = self.tick(t)
        for tt, row in self._aligner.push(feeder, t, sample):
            self._ticks[self.tick(tt)] = row

    def add_measured(self, t: float, c_pct_w_w: float, seq: int = -1) -> None:
        """A reading of the NIR probe (% w/w) at plant time t (``seq``: its sequence number)."""
        if not np.isfinite(c_pct_w_w):
            raise ValueError(f"c_pct_w_w must be finite, got {c_pct_w_w!r}")
        tc = self._arrive(NIR_STREAM, t, seq, (float(c_pct_w_w),))
        if tc is None:
            return
        k = self.tick(tc)
        dist = abs(tc - k * self.dt_s)
        if k in self._meas and self._meas_dist.get(k, math.inf) < dist:
            return  # a reading stamped nearer this tick came first
        self._meas[k] = float(c_pct_w_w)
        self._meas_dist[k] = dist

    def add_event(self, event: Mapping[str, Any]) -> None:
        """A plant event as a dict (``kind``, ``t_s``, ``source``, ...; see
        ``twin_core.online.inlet.event_record``). Refill events are not kept (module docstring)."""
        ev = dict(event)
        if "t_s" not in ev or "kind" not in ev:
            raise ValueError(f"event must have 't_s' and 'kind', got {sorted(ev)}")
        if ev["kind"] in REFILL_EVENTS:
            return
        self._events.append(ev)
        p = tracer_pulse(ev)
        if p is not None:
            self._tracers.setdefault((p.t_s, p.component), p)

    def add_message(self, key: str, msg: Any) -> str:
        """A decoded bus message (``schemas.messages``) on ``key``; returns what it was:
        ``flow``, ``measured``, ``event``, ``unknown_feeder`` (a flow of a feeder the line does
        not declare) or ``ignored`` (another sensor's component, a ``bad`` reading, another
        message)."""
        from schemas import keys
        from schemas.messages import Event, FeederFlow, MeasuredConcentration

        if isinstance(msg, FeederFlow):
            feeder = keys.parse_key(key).id
            if feeder not in self.components:
                return "unknown_feeder"
            self.add_flow(
                feeder, msg.t, msg.mass_flow_kg_h, msg.refilling, msg.screw_speed_rpm, msg.seq
            )
            return "flow"
        if isinstance(msg, MeasuredConcentration):
            if msg.quality == "bad" or msg.component != self.sensor_component:
                return "ignored"
            self.add_measured(msg.t, msg.concentration_pct_w_w, msg.seq)
            return "measured"
        if isinstance(msg, Event):
            self.add_event(event_record(msg))
            return "event"
        return "ignored"

    @classmethod
    def from_messages(
        cls,
        messages: Iterable[tuple[str, Any]],
        components: Mapping[str, str],
        dt_s: float,
        sensor_component: str,
    ) -> LineRecord:
        """The record of (key, decoded message) pairs in arrival order (e.g. a recording): a
        first pass estimates the sources' clock offsets from the arrival order
        (``twin_core.closeloop.quality.estimate_clock_offsets``), the second places every
        sample on the common clock (module docstring)."""
        messages = list(messages)
        first = cls(components, dt_s, sensor_component, max_lag=1 << 30)
        for key, msg in messages:
            first.add_message(key, msg)
        offsets = estimate_clock_offsets(first.stamps(-math.inf, math.inf), dt_s)
        rec = first
        if offsets:
            rec = cls(components, dt_s, sensor_component, max_lag=1 << 30)
            rec.clock_offsets = {c.series: c for c in offsets}
            for key, msg in messages:
                rec.add_message(key, msg)
        rec.finish()
        return rec

    def finish(self) -> None:
        """The record is complete: release the ticks still waiting for a feeder (a feeder's
        dropout would otherwise hold back every later tick); its missing samples stay missing
        (held over in :meth:`arrays`, flagged as a gap by the data-quality check)."""
        for tt, row in self._aligner.flush():
            self._ticks[self.tick(tt)] = row

    # -- output ------------------------------------------------------------------------------
    def last_complete_tick(self) -> int | None:
        """The last tick every stream (every feeder, the NIR) has reached, or None."""
        if not self._ticks or not self._meas:
            return None
        return min(max(self._ticks), max(self._meas))

    def arrays(
        self, t_start: float, t_end: float
    ) -> tuple[np.ndarray, np.ndarray, LineInputs, list[dict[str, Any]]]:
        """(t, measured, inputs, events) on the ticks of [t_start, t_end] (module docstring)."""
        a, b = self.tick(t_start), self.tick(t_end)
        ks = np.arange(a, b + 1)
        t = ks * self.dt_s
        flows: dict[str, np.ndarray] = {}
        refill: dict[str, np.ndarray] = {}
        rpm: dict[str, np.ndarray] = {}
        for f in self.components:
            q = np.full(ks.size, np.nan)
            r = np.zeros(ks.size, dtype=bool)
            s = np.full(ks.size, np.nan)
            for i, k in enumerate(ks):
                v = self._ticks.get(int(k), {}).get(f)
                if v is not None:
                    q[i], r[i], s[i] = v.flow_kg_h, v.refilling, v.screw_speed_rpm
            good = np.isfinite(q)
            if not good.any():
                raise ValueError(f"no flow of feeder {f!r} in window [{t_start}, {t_end}]")
            idx = np.where(good, np.arange(ks.size), -1)
            idx = np.maximum.accumulate(idx)
            idx[idx < 0] = int(np.argmax(good))
            flows[f] = q[idx]
            refill[f] = r
            if np.isfinite(s).sum() >= 2:
                ok = np.isfinite(s)
                rpm[f] = np.interp(ks, ks[ok], s[ok])
        y = np.array([self._meas.get(int(k), np.nan) for k in ks])
        tracers = [p for p in self._tracers.values() if t[0] - TRACER_REACH_S <= p.t_s <= t[-1]]
        inputs = LineInputs(t, flows, dict(self.components), refill, tracers, rpm)
        events = [e for e in self._events if t[0] <= float(e["t_s"]) <= t[-1]]
        events += refill_events(t, refill)
        events.sort(key=lambda e: float(e["t_s"]))
        return t, y, inputs, events

    def stamps(self, t_start: float, t_end: float) -> dict[str, StreamStamps]:
        """The raw message stamps of each stream within [t_start, t_end], in arrival order
        (sequence numbers None when a stream's messages came without them)."""
        out = {}
        for name, rows in self._stamps.items():
            sel = [r for r in rows if t_start <= r[0] <= t_end]
            if not sel:
                continue
            t = np.array([r[0] for r in sel])
            q = np.array([r[1] for r in sel])
            arrival = np.array([r[2] for r in sel])
            resent = [x for x in self._resent.get(name, []) if t_start <= x <= t_end]
            out[name] = StreamStamps(t, None if np.any(q < 0) else q, arrival, np.array(resent))
        return out

    def span(self) -> tuple[float, float]:
        """Plant times of the first and last tick holding both feeder flows and a reading."""
        if not self._ticks or not self._meas:
            raise ValueError("record must hold feeder flows and NIR readings, got none of one")
        a = max(min(self._ticks), min(self._meas))
        b = min(max(self._ticks), max(self._meas))
        if b <= a:
            raise ValueError(
                f"feeder flows and NIR readings must overlap in time, got ticks {a}..{b}"
            )
        return a * self.dt_s, b * self.dt_s

    def run_data(self, name: str = "record") -> RunData:
        """The whole record as a :class:`~twin_core.closeloop.data.RunData` (on :meth:`span`)."""
        a, b = self.span()
        t, y, inputs, events = self.arrays(a, b)
        return RunData(
            t,
            y,
            inputs,
            events,
            name=name,
            stamps=self.stamps(a, b),
            clock_offsets=list(self.clock_offsets.values()),
        )

    def prune(self, keep_from: int) -> None:
        """Forget the ticks before ``keep_from`` (and the events before them, less the reach of
        a tracer pulse)."""
        for k in [k for k in self._ticks if k < keep_from]:
            del self._ticks[k]
        for k in [k for k in self._meas if k < keep_from]:
            del self._meas[k]
            self._meas_dist.pop(k, None)
        lo = keep_from * self.dt_s - TRACER_REACH_S
        self._events = [e for e in self._events if float(e["t_s"]) >= lo]
        t_keep = (keep_from - 0.5) * self.dt_s
        for name, rows in self._stamps.items():
            self._stamps[name] = [r for r in rows if r[0] >= t_keep]
        for name, rows in self._resent.items():
            self._resent[name] = [r for r in rows if r >= t_keep]


def refill_events(t: np.ndarray, refilling: Mapping[str, np.ndarray]) -> list[dict[str, Any]]:
    """``refill_start`` / ``refill_stop`` events at the edges of each feeder's refill flag on
    the ticks ``t`` (a flag already up at the first tick starts a refill there)."""
    out: list[dict[str, Any]] = []
    for feeder, r in refilling.items():
        r = np.asarray(r, dtype=bool)
        if r.size == 0:
            continue
        prev = np.concatenate([[False], r[:-1]])
        for i in np.nonzero(r & ~prev)[0]:
            out.append({"t_s": float(t[i]), "kind": "refill_start", "source": feeder})
        for i in np.nonzero(~r & prev)[0]:
            out.append({"t_s": float(t[i]), "kind": "refill_stop", "source": feeder})
    return out
