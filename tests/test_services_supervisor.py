"""Supervisor: a service that hangs (SIGSTOP) loses its liveliness token when the router's
lease expires; the supervisor kills it and restarts it."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

from schemas.line import LineSpec
from services.supervisor import Supervisor
from services.twin_demo import free_port

CONFIG = Path(__file__).resolve().parent.parent / "services" / "configs" / "line1.yaml"


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
