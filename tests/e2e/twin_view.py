"""What the end-to-end tests see of a running twin: its alerts, divert commands and the latest
health of each service (as the operator sees them), and process checks."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import DivertCommand, OosAlert, ServiceHealth
from services.bus import HistoryFeed, open_session
from services.recording import BusReplay, Recording
from services.supervisor import Supervisor
from twin_core.online.blender import declared_kernel
from twin_core.online.oos import predicted_excursion
from twin_core.quality.lots import diversion_window


def running(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in ("Z", "X")


class Seen:
    """Alerts, divert commands and the latest health of each service, as the operator sees."""

    def __init__(self, sup: Supervisor) -> None:
        self.got: dict[type, list] = {OosAlert: [], DivertCommand: []}
        self.health: dict[str, ServiceHealth] = {}
        self.positions: set[tuple[str, float, int]] = set()
        self.resent = 0
        self._lock = threading.Lock()
        self.session = open_session(sup.client_config("operator"))
        line = sup.spec.name
        # alerts and divert commands through advanced subscribers: one published while the
        # router restarts is recovered from the diverter's cache, as a twin tool gets it
        self.feeds = [
            HistoryFeed(self.session, keys.oos_alert(line), self._feed(OosAlert)),
            HistoryFeed(self.session, keys.divert_command(line), self._feed(DivertCommand)),
        ]
        self.subs = [
            self.session.declare_subscriber(
                keys.services_health(line),
                zenoh.handlers.Callback(self._on_health, lambda: None),
            ),
        ]

    def _feed(self, model):
        def sink(key: str, payload: bytes) -> None:
            msg = model.model_validate_json(payload)
            with self._lock:
                new = (key, msg.t, msg.seq) not in self.positions
                self.positions.add((key, msg.t, msg.seq))
            if not new:
                # the same message again: a restarted diverter re-sends what it logged just
                # before it died (services.common.OutputLog); dropped as the contract's
                # subscribers drop a duplicate position (services.bus.StreamOrder), counted
                self.resent += 1
                return
            self.got[model].append(msg)

        return sink

    def _on_health(self, sample: zenoh.Sample) -> None:
        msg = ServiceHealth.model_validate_json(sample.payload.to_bytes())
        self.health[msg.service] = msg

    def plant_time(self, service: str) -> float:
        h = self.health.get(service)
        return h.t if h is not None else -1.0

    def close(self) -> None:
        for s in [*self.feeds, *self.subs]:
            s.undeclare()
        self.session.close()


def wait_until(pred, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end and not pred():
        time.sleep(0.05)
    return pred()


def plant_replay(rec: Recording, sup: Supervisor) -> BusReplay:
    """The virtual plant replaying ``rec`` into the supervised twin, as the ``plant`` identity
    (a context manager: ``with plant_replay(rec, sup) as rp: rp.replay(speed=...)``)."""
    return BusReplay.as_plant(rec, sup.client_config("plant"), sup.spec)


def expected_windows(spec: LineSpec, disturbances: list[dict]) -> list[tuple[float, float]]:
    """The outlet windows the declared blender gives each feeder disturbance (``t_s``,
    ``duration_s``, ``delta_kg_h`` of the sensor's component): the alert windows a correct
    diverter raises. ``oos.divert_window: lot``: the lot boundaries of the inlet stretch;
    ``excursion``: where the rectangle's predicted outlet leaves the guarded specification
    (its inlet deviation delta (100 - c0) / m_nom, ``twin_core.online.oos``'s linearised inlet
    composition), padded."""
    e = declared_kernel(spec)
    tk = np.arange(e.size) * spec.dt_s
    if spec.oos.divert_window == "lot":
        return [
            diversion_window(d["t_s"], d["t_s"] + d["duration_s"] - spec.dt_s, tk, e)
            for d in disturbances
        ]
    s = next(x for x in spec.spec if x.component == spec.sensor.component)
    m_nom = sum(f.setpoint_kg_h for f in spec.feeders)
    o = spec.oos
    excursion = predicted_excursion(
        e,
        spec.dt_s,
        s.target_pct_w_w,
        s.lower_pct_w_w,
        s.upper_pct_w_w,
        o.divert_guard_pct_w_w,
        o.divert_pad_s,
    )
    out = []
    for d in disturbances:
        n = int(round(d["duration_s"] / spec.dt_s))
        dev = np.full(n, d["delta_kg_h"] * (100.0 - s.target_pct_w_w) / m_nom)
        out.append(excursion(d["t_s"], dev))
    return out
