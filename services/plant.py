"""Virtual plant: a simulated line run or a recording, replayed onto the bus.

- :func:`run_messages` turns a ``twin_core.plant.LineRun`` (from ``simulate_line``) into the
  time-ordered bus messages a real line would produce: one
  :class:`~schemas.messages.FeederFlow` per feeder per tick, one
  :class:`~schemas.messages.MeasuredConcentration` per NIR sample, the
  :class:`~schemas.messages.Event` s (refills, tracer pulses, disturbances).
- :func:`simulate_messages` runs ``simulate_line`` for a :class:`~schemas.line.LineSpec`
  (disturbances and hidden effects injectable).
- :class:`Replayer` publishes ``(key, t, payload)`` items at ``speed`` x real time (plant time
  paced against the wall clock; ``speed=inf`` as fast as the bus takes them) with
  ``CongestionControl.BLOCK`` and a history cache, and finally an ``end-of-stream`` event.
  Feeder flows can be moved to the ``loadcell`` unit so that the feeder service passes them
  through (``feeder_mode: replay``).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import Event, FeederFlow, MeasuredConcentration
from services.common import HistoryPublisher, LiveService

log = logging.getLogger(__name__)

Item = tuple[str, float, bytes]

_EVENT_KINDS = {
    "refill_start": "refill_start",
    "refill_stop": "refill_stop",
    "tracer_pulse": "tracer_pulse",
    "disturbance": "disturbance",
    "disturbance_end": "disturbance_end",
    "disturbance_start": "disturbance",
    "disturbance_stop": "disturbance_end",
}


def _nz(x: float) -> float:
    return float(x) if math.isfinite(x) and x >= 0 else 0.0


def run_messages(run: Any, spec: LineSpec) -> list[tuple[str, Any]]:
    """Bus messages of a ``LineRun`` in plant-time order, as (key, message) pairs.

    Flows go to ``twin/<line>/feeder/<id>/flow``, NIR samples to
    ``twin/<line>/pat/<sensor>/concentration``, events to ``twin/<line>/feeder/<id>/event``
    (feeder events) or ``twin/<line>/plant/<source>/event``.
    """
    line = spec.name
    t = np.asarray(run.t_s, float)
    out: list[tuple[float, int, str, Any]] = []
    for j, (name, rec) in enumerate(run.feeders.items()):
        k = keys.feeder_flow(line, name)
        sp = spec.feeders[j].setpoint_kg_h if j < len(spec.feeders) else None
        for i in range(t.size):
            out.append(
                (
                    t[i],
                    j,
                    k,
                    FeederFlow(
                        t=float(t[i]),
                        seq=i,
                        component=rec.component,
                        mass_flow_kg_h=_nz(rec.flow_kg_h[i]),
                        setpoint_kg_h=sp,
                        screw_speed_rpm=_nz(rec.screw_speed_rpm[i]),
                        hopper_mass_kg=_nz(rec.hopper_mass_kg[i]),
                        feed_factor_g_rev=_nz(rec.feed_factor_g_rev[i]),
                        refilling=bool(rec.refilling[i]),
                    ),
                )
            )
    nk = keys.measured_concentration(line, spec.sensor.id)
    m = np.asarray(run.measured_pct_w_w, float)
    seq = 0
    for i in np.nonzero(np.isfinite(m))[0]:
        out.append(
            (
                t[i],
                100,
                nk,
                MeasuredConcentration(
                    t=float(t[i]),
                    seq=seq,
                    sensor=spec.sensor.id,
                    component=run.sensor_component,
                    concentration_pct_w_w=float(m[i]),
                ),
            )
        )
        seq += 1
    feeders = {f.id for f in spec.feeders}
    for n, ev in enumerate(run.events):
        unit = "feeder" if ev.source in feeders else "plant"
        d = dict(ev.detail)
        out.append(
            (
                float(ev.t_s),
                200,
                keys.event(line, unit, ev.source),
                Event(
                    t=float(ev.t_s),
                    seq=n,
                    kind=_EVENT_KINDS.get(ev.kind, "note"),
                    source=ev.source,
                    mass_kg=d.get("mass_kg"),
                    duration_s=d.get("duration_s"),
                    magnitude=d.get("delta_kg_h"),
                    detail=ev.kind,
                ),
            )
        )
    out.sort(key=lambda x: (x[0], x[1]))
    return [(k, msg) for _, _, k, msg in out]


def simulate_messages(
    spec: LineSpec,
    duration_s: float,
    seed: int | None = 0,
    disturbances: Sequence[dict[str, Any]] = (),
    effects: Sequence[dict[str, Any]] = (),
) -> tuple[Any, list[tuple[str, Any]]]:
    """Simulate the line of ``spec`` (``twin_core.plant.simulate_line``); return (run, messages)."""
    from twin_core.plant import simulate_line

    run = simulate_line(
        spec.plant_config(),
        duration_s,
        dt_s=spec.dt_s,
        seed=seed,
        effects=list(effects),
        disturbances=list(disturbances),
    )
    return run, run_messages(run, spec)


def encode(messages: Iterable[tuple[str, Any]]) -> Iterator[Item]:
    """(key, message) -> (key, t, JSON payload)."""
    for k, msg in messages:
        yield k, float(msg.t), msg.to_json_bytes()


def remap_unit(key: str, src: str, dst: str) -> str:
    """Replace the unit segment ``src`` of a key by ``dst`` (others unchanged)."""
    parts = key.split("/")
    if len(parts) >= 4 and parts[2] == src:
        parts[2] = dst
        return "/".join(parts)
    return key


class Replayer(LiveService):
    """Publishes items at ``speed`` x real time, then an end-of-stream event.

    Args:
        spec: the line.
        items: (key, plant time, payload) in plant-time order.
        speed: replay speed (``math.inf``: no pacing).
        feeder_unit: unit segment for feeder flows (``loadcell`` when a feeder service passes
            them through).
    """

    def __init__(
        self,
        spec: LineSpec,
        items: Iterable[Item],
        speed: float = math.inf,
        feeder_unit: str = "feeder",
        **kwargs: Any,
    ) -> None:
        super().__init__("plant", spec, **kwargs)
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed!r}")
        self.items = items
        self.speed = float(speed)
        self.feeder_unit = feeder_unit
        self.pubs: dict[str, HistoryPublisher] = {}
        self.sent = 0
        self.wall_s = 0.0
        self.first_t: float | None = None
        self.last_t: float | None = None
        #: wall seconds between declaring the publishers and the first sample
        self.declare_settle_s = 0.5

    def _pub(self, key: str) -> HistoryPublisher:
        pub = self.pubs.get(key)
        if pub is None:
            pub = self.history_publisher(key, None)
            self.pubs[key] = pub
        return pub

    def replay(self) -> int:
        """Publish everything (blocking), then the end-of-stream event; return messages sent.

        ``items`` may be a ``services.recording.Recording`` (replayed by
        ``services.recording.replay``, payloads byte for byte) or (key, t, payload) items.
        """
        from services.oos import END_OF_STREAM, replay_event_key
        from services.recording import Recording, replay

        def wire_key(key: str) -> str:
            if self.feeder_unit != "feeder" and key.endswith("/flow"):
                return remap_unit(key, "feeder", self.feeder_unit)
            return key

        def publish(key: str, payload: bytes) -> None:
            self._pub(wire_key(key)).put_raw(payload)
            self.sent += 1

        # Declare every publisher before the first sample: a publisher declared on first use
        # (e.g. the first tracer event, minutes into a run) is found by the subscribers only
        # through late-publisher detection and a history query, and its samples then reach them
        # after samples of the same plant time on the other keys.
        if isinstance(self.items, Recording):
            first_keys = list(dict.fromkeys(m.key for m in self.items.messages))
        elif isinstance(self.items, (list, tuple)):
            first_keys = list(dict.fromkeys(k for k, _, _ in self.items))
        else:
            first_keys = []
        for key in first_keys + [replay_event_key(self.spec.name)]:
            self._pub(wire_key(key))
        if first_keys and self.pubs:
            time.sleep(self.declare_settle_s)  # let the subscribers' routes to them settle

        t_wall0 = time.perf_counter()
        if isinstance(self.items, Recording):
            msgs = self.items.messages
            if msgs:
                self.first_t, self.last_t = msgs[0].t, msgs[-1].t
            replay(
                self.items,
                publish,
                speed=self.speed if math.isfinite(self.speed) else 1.0,
                as_fast_as_possible=not math.isfinite(self.speed),
                should_stop=lambda: self.stopping,
            )
        else:
            t_plant0: float | None = None
            for key, t, payload in self.items:
                if self.stopping:
                    break
                if t_plant0 is None:
                    t_plant0 = t
                    self.first_t = t
                if math.isfinite(self.speed):
                    ahead = (t - t_plant0) / self.speed - (time.perf_counter() - t_wall0)
                    if ahead > 0.002:
                        time.sleep(ahead)
                publish(key, payload)
                self.last_t = t
        end = Event(
            t=self.last_t or 0.0,
            seq=0,
            kind="note",
            source="replay",
            detail=END_OF_STREAM,
        )
        self._pub(replay_event_key(self.spec.name)).put_raw(end.to_json_bytes())
        self.wall_s = time.perf_counter() - t_wall0
        return self.sent


def write_recording(path: str | Path, messages: Iterable[tuple[str, Any]]) -> int:
    """Write (key, message) pairs to an MCAP recording (``services.recording.McapRecorder``)."""
    from services.recording import McapRecorder

    n = 0
    with McapRecorder(path) as rec:
        for k, msg in messages:
            rec.write_message(k, msg, publish_time_ns=int(msg.t * 1e9))
            n += 1
    return n


def parse_disturbance(text: str) -> dict[str, Any]:
    """``FEEDER:T_S:DELTA_KG_H[:DURATION_S]`` -> a ``FlowDisturbance`` dict (CLI form)."""
    parts = text.split(":")
    if len(parts) not in (3, 4):
        raise ValueError(f"disturbance must be FEEDER:T_S:DELTA_KG_H[:DURATION_S], got {text!r}")
    d: dict[str, Any] = {"feeder": parts[0], "t_s": float(parts[1]), "delta_kg_h": float(parts[2])}
    if len(parts) == 4:
        d["duration_s"] = float(parts[3])
    return d
