"""Supervisor: a service that hangs (SIGSTOP) loses its liveliness token when the router's
lease expires; the supervisor kills it and restarts it."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

from schemas import keys
from schemas.line import LineSpec
from services.bus import free_port
from services.supervisor import Supervisor

CONFIG = Path(__file__).resolve().parents[2] / "services" / "configs" / "line1.yaml"


def test_hung_service_is_killed_and_restarted(tmp_path):
    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(
        bus={
            "mode": "router",
            "listen": [f"tcp/127.0.0.1:{free_port()}"],
            "connect": [],
            # short zenoh lease so that a silent peer is dropped within ~1 s
            "extra": {"transport/link/tx/lease": 1000, "transport/link/tx/keep_alive": 4},
        },
        services=["blender"],
        state_dir=str(tmp_path),
    )
    spec = LineSpec.model_validate(data)
    sup = Supervisor(spec, liveliness_timeout_s=1.0, backoff_s=0.2).start()
    try:
        assert sup.wait_ready(120)
        pid = sup.pids()["blender"]
        os.kill(pid, signal.SIGSTOP)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and sup.children["blender"].restarts == 0:
            time.sleep(0.1)
        assert sup.children["blender"].restarts == 1
        assert sup.children["blender"].exit_codes == [-signal.SIGKILL]
        assert sup.wait_ready(120)
        assert sup.pids()["blender"] not in (None, pid)
    finally:
        codes = sup.stop()
    assert codes == {"blender": 0}


def test_a_dead_model_does_not_block_measured_oos_decisions(tmp_path):
    """The diverter expects the blender's predictions (configured) but the blender never runs:
    after ``oos.stall_release_s`` it decides on the feeder flows and the NIR, during the run."""
    import threading

    import zenoh

    from schemas.messages import OosAlert, ServiceHealth
    from services.bus import open_session
    from services.recording import BusReplay, Recording
    from twin_core.plant.messages import simulate_messages

    data = LineSpec.from_file(CONFIG).model_dump()
    data.update(
        bus={"mode": "router", "listen": [f"tcp/127.0.0.1:{free_port()}"], "connect": []},
        services=["blender", "oos"],
        state_dir=str(tmp_path),
    )
    data["oos"]["stall_release_s"] = 2.0
    spec = LineSpec.model_validate(data)
    _, msgs = simulate_messages(
        spec,
        600.0,
        seed=5,
        disturbances=[{"feeder": "api", "t_s": 100.0, "delta_kg_h": 0.6, "duration_s": 30.0}],
    )
    rec = Recording.from_messages(msgs)
    got: list[tuple[float, OosAlert]] = []
    health: dict[str, ServiceHealth] = {}
    lock = threading.Lock()
    sup = Supervisor(spec, services=["oos"]).start()  # no blender
    try:
        assert sup.wait_ready(120)
        s = open_session(sup.client_config("operator"))

        def on_alert(sample: zenoh.Sample) -> None:
            with lock:
                got.append(
                    (time.monotonic(), OosAlert.model_validate_json(sample.payload.to_bytes()))
                )

        def on_health(sample: zenoh.Sample) -> None:
            h = ServiceHealth.model_validate_json(sample.payload.to_bytes())
            health[h.service] = h

        subs = [
            s.declare_subscriber(
                keys.oos_alert("line1"), zenoh.handlers.Callback(on_alert, lambda: None)
            ),
            s.declare_subscriber(
                keys.service_health("line1", "oos"),
                zenoh.handlers.Callback(on_health, lambda: None),
            ),
        ]
        with BusReplay.as_plant(rec, sup.client_config("plant"), spec) as rp:
            rp.replay(speed=90.0)
            t_end = time.monotonic()
            time.sleep(1.5)
        for sub in subs:
            sub.undeclare()
        s.close()
    finally:
        sup.stop()
    assert [a.alert_id for _, a in got] == ["line1.api.feed-000000100000"]
    assert got[0][0] < t_end  # decided while the replay was still running
    assert health["oos"].counters.get("degraded_releases", 0) >= 1
