"""Feeder service: the loss-in-weight feeders of the line.

- ``feeder_mode: replay``: the plant (a real line, or the virtual plant replaying a recording as
  recorded) publishes the feeders' flows on ``twin/<line>/feeder/<id>/flow``; the service
  subscribes to them and reports per feeder, in its health, the refills seen (``refill_start``,
  ``refill_stop``: edges of each flow's ``refilling`` flag, the one source of refill state) and
  flows of feeders the line does not declare (``rejected_unknown``).
- ``feeder_mode: simulate``: the service is the plant's feeders: it runs the LIW model of each
  feeder (``twin_core.plant.messages.feeder_flow_messages``: PID, refills, feed-factor curve)
  and publishes their flows on ``twin/<line>/feeder/<id>/flow``, paced at ``speed`` x real time.
"""

from __future__ import annotations

import time
from typing import Any

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import FeederFlow
from services.bus import Publisher
from services.service import Service


class FeederService(Service):
    """See the module docstring."""

    def __init__(
        self, spec: LineSpec, speed: float = 1.0, duration_s: float = 3600.0, **kwargs: Any
    ) -> None:
        super().__init__("feeder", spec=spec, **kwargs)
        self.speed = float(speed)
        self.duration_s = float(duration_s)
        self.flow_pubs: dict[str, Publisher] = {}
        self._refilling: dict[str, bool] = {}
        self._last_t: dict[str, float] = {}

    def setup(self) -> None:
        line = self.spec.name
        if self.spec.feeder_mode == "replay":
            self.history_subscribe(keys.feeder_flows(line), FeederFlow)
            return
        for f in self.spec.feeders:
            self.flow_pubs[f.id] = self.publisher(
                keys.feeder_flow(line, f.id), FeederFlow, history=True
            )

    def handle(self, key: str, msg: Any) -> None:
        feeder = keys.parse_key(key).id
        if feeder not in self.spec.components:
            self.counters.inc("rejected_unknown")
            return
        self._watch(feeder, msg)

    def _watch(self, feeder: str, msg: FeederFlow) -> None:
        """Count the edges of the feeder's refill flag (samples not newer than the last: history
        seen again after a restart)."""
        if msg.t <= self._last_t.get(feeder, -1.0):
            return
        self._last_t[feeder] = msg.t
        if msg.refilling != self._refilling.get(feeder, False):
            self.counters.inc("refill_start" if msg.refilling else "refill_stop")
        self._refilling[feeder] = msg.refilling

    def run(self, timeout_s: float | None = None) -> int:
        if self.spec.feeder_mode == "replay":
            return super().run(timeout_s)
        return self._simulate()

    def _simulate(self) -> int:
        """Run the LIW feeders and publish their flows paced at ``speed``."""
        from twin_core.plant.messages import feeder_flow_messages

        t0 = time.perf_counter()
        for key, msg in feeder_flow_messages(self.spec, self.duration_s):
            if self.stopping:
                break
            ahead = msg.t / self.speed - (time.perf_counter() - t0)
            if ahead > 0.002:
                time.sleep(ahead)
            feeder = keys.parse_key(key).id
            self._watch(feeder, msg)
            self.flow_pubs[feeder].publish(msg)
        return 0
