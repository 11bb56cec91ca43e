"""What the end-to-end tests see of a running twin: its alerts, divert commands and the latest
health of each service (as the operator sees them), and process checks."""

from __future__ import annotations

import time
from pathlib import Path

import zenoh

from schemas import keys
from schemas.messages import DivertCommand, OosAlert, ServiceHealth
from services.bus import open_session
from services.recording import BusReplay, Recording
from services.supervisor import Supervisor


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
        self.session = open_session(sup.client_config("operator"))
        line = sup.spec.name
        self.subs = [
            self.session.declare_subscriber(keys.oos_alert(line), self._on(OosAlert)),
            self.session.declare_subscriber(keys.divert_command(line), self._on(DivertCommand)),
            self.session.declare_subscriber(keys.services_health(line), self._on(ServiceHealth)),
        ]

    def _on(self, model):
        def cb(sample: zenoh.Sample) -> None:
            msg = model.model_validate_json(sample.payload.to_bytes())
            if model is ServiceHealth:
                self.health[msg.service] = msg
            else:
                self.got[model].append(msg)

        return zenoh.handlers.Callback(cb, lambda: None)

    def plant_time(self, service: str) -> float:
        h = self.health.get(service)
        return h.t if h is not None else -1.0

    def close(self) -> None:
        for s in self.subs:
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
    return BusReplay(
        rec,
        sup.client_config("plant"),
        spec=sup.spec,
        settle_s=0.5,
        service_name="plant",
        install_signal_handlers=False,
    )
