"""Feeder service: one process for all feeders of the line.

- ``feeder_mode: replay``: passes the recorded load-cell flows through
  (``twin/<line>/loadcell/<id>/flow`` -> ``twin/<line>/feeder/<id>/flow``), flagging refills:
  a change of the ``refilling`` flag publishes a ``refill_start``/``refill_stop``
  :class:`~schemas.messages.Event` on ``twin/<line>/feeder/<id>/event``.
- ``feeder_mode: simulate``: runs ``twin_core.feeder.LossInWeightFeeder`` for each feeder
  (PID, refills, feed-factor curve) and publishes its flow every tick, paced at ``speed`` x real
  time, with the same refill events.
"""

from __future__ import annotations

import math
import time
from typing import Any

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import Event, FeederFlow
from services.common import HistoryPublisher, LiveService


class FeederService(LiveService):
    """See the module docstring."""

    def __init__(
        self, spec: LineSpec, speed: float = 1.0, duration_s: float = 3600.0, **kwargs: Any
    ) -> None:
        super().__init__("feeder", spec, **kwargs)
        self.speed = float(speed)
        self.duration_s = float(duration_s)
        self.flow_pubs: dict[str, HistoryPublisher] = {}
        self.event_pubs: dict[str, HistoryPublisher] = {}
        self._refilling: dict[str, bool] = {}
        self._last_t: dict[str, float] = {}

    def setup(self) -> None:
        line = self.spec.name
        for f in self.spec.feeders:
            self.flow_pubs[f.id] = self.history_publisher(keys.feeder_flow(line, f.id), FeederFlow)
            self.event_pubs[f.id] = self.history_publisher(keys.event(line, "feeder", f.id), Event)
        if self.spec.feeder_mode == "replay":
            self.history_subscribe(f"twin/{line}/loadcell/*/flow", FeederFlow)

    def _forward(self, feeder: str, msg: FeederFlow) -> None:
        if msg.t <= self._last_t.get(feeder, -1.0):
            return  # history already forwarded (restart)
        self._last_t[feeder] = msg.t
        prev = self._refilling.get(feeder, False)
        if msg.refilling != prev:
            kind = "refill_start" if msg.refilling else "refill_stop"
            ev = self.event_pubs[feeder]
            ev.publish(
                Event(t=msg.t, seq=ev.seq, kind=kind, source=feeder, component=msg.component)
            )
            self.counters.inc(kind)
        self._refilling[feeder] = msg.refilling
        self.flow_pubs[feeder].publish(msg)

    def handle(self, key: str, msg: Any) -> None:
        feeder = keys.parse_key(key).id
        if feeder not in self.flow_pubs:
            self.counters.inc("rejected_unknown")
            return
        self._forward(feeder, msg)

    def run(self, timeout_s: float | None = None) -> int:
        if self.spec.feeder_mode == "replay":
            return super().run(timeout_s)
        return self._simulate()

    def _simulate(self) -> int:
        """Run the LIW feeders and publish their flows paced at ``speed``."""
        from twin_core.feeder import LossInWeightFeeder

        dt = self.spec.dt_s
        traces = {}
        for i, f in enumerate(self.spec.feeders):
            feeder = LossInWeightFeeder(name=f.id, setpoint_kg_h=f.setpoint_kg_h, **f.liw)
            cp = float(feeder.config.control_period_s)
            sub = max(1, int(math.ceil(dt / cp - 1e-9)))
            tr = feeder.simulate(self.duration_s + dt, dt / sub, seed=i)
            traces[f.id] = (f, tr, sub)
        n = int(self.duration_s / dt) + 1
        t0 = time.perf_counter()
        for i in range(n):
            if self.stopping:
                break
            t = i * dt
            ahead = t / self.speed - (time.perf_counter() - t0)
            if ahead > 0.002:
                time.sleep(ahead)
            for fid, (f, tr, sub) in traces.items():
                a, b = i * sub, (i + 1) * sub
                self._forward(
                    fid,
                    FeederFlow(
                        t=t,
                        seq=i,
                        component=f.component,
                        mass_flow_kg_h=max(0.0, float(tr.mass_flow_kg_h[a:b].mean())),
                        setpoint_kg_h=f.setpoint_kg_h,
                        screw_speed_rpm=max(0.0, float(tr.screw_speed_rpm[a])),
                        hopper_mass_kg=max(0.0, float(tr.hopper_mass_kg[a])),
                        feed_factor_g_rev=max(0.0, float(tr.feed_factor_g_rev[a])),
                        refilling=bool(tr.refilling[a:b].any()),
                    ),
                )
        return 0
