"""Process entry point of one live service: ``python -m services.runner NAME --config LINE``.

``twin up`` starts every service this way (a fresh interpreter per service: no fork after zenoh
is open). ``--config`` takes the line YAML/JSON; the run's state directory comes from
``$TWIN_STATE_DIR``.
"""

from __future__ import annotations

import argparse
import ctypes
import logging
import os
import signal
import sys
import threading
import time

from schemas.line import LineSpec

log = logging.getLogger("services.runner")

#: environment variable naming the supervisor's pid (``services.supervisor``)
SUPERVISOR_PID_ENV = "TWIN_SUPERVISOR_PID"
#: Linux prctl option: the signal this process gets when its parent thread dies
PR_SET_PDEATHSIG = 1
#: seconds between checks of the parent process; and the grace of a clean stop after it died
PARENT_CHECK_S = 0.5
STOP_GRACE_S = 10.0


def die_with_parent(parent: int) -> None:
    """Stop when the supervisor ``parent`` dies, however it dies (SIGKILL included): SIGTERM
    from the kernel on Linux (``prctl(PR_SET_PDEATHSIG)``), and on any system a thread that
    watches the parent process (its pid changes when it dies) and sends SIGTERM, then exits
    hard after ``STOP_GRACE_S`` if the clean stop hangs."""
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
            log.warning("prctl(PR_SET_PDEATHSIG) failed: errno %d", ctypes.get_errno())
    if os.getppid() != parent:  # the parent died before the signal was armed
        log.error("supervisor (pid %d) is gone: exiting", parent)
        sys.exit(3)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK_S)
        log.error("supervisor (pid %d) is gone: stopping", parent)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(STOP_GRACE_S)
        os._exit(3)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def make_service(name: str, spec: LineSpec, **kwargs):
    """The service object of ``name`` (one of ``schemas.line.SERVICE_NAMES`` except plant)."""
    if name == "blender":
        from services.blender import BlenderService

        return BlenderService(spec, **kwargs)
    if name == "oos":
        from services.oos import OosService

        return OosService(spec, **kwargs)
    if name == "feeder":
        from services.feeder import FeederService

        return FeederService(spec, **kwargs)
    if name == "rtd":
        from services.rtd import RtdService

        return RtdService(spec, **kwargs)
    if name == "recorder":
        from services.recorder import RecorderService

        return RecorderService(spec, **kwargs)
    if name == "closeloop":
        from services.closeloop import CloseLoopService

        return CloseLoopService(spec, **kwargs)
    if name == "dem":
        from services.dem import DemService

        return DemService(spec, **kwargs)
    if name == "trace":
        from services.trace_service import TraceService

        return TraceService(spec, **kwargs)
    if name == "bridge":
        from services.opcua_bridge import bridge_service

        return bridge_service(spec, **kwargs)
    raise ValueError(
        "service must be one of blender, oos, feeder, rtd, recorder, dem, closeloop, bridge, trace, "
        f"got {name!r}"
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m services.runner")
    p.add_argument("name")
    p.add_argument("--config", required=True)
    p.add_argument("--log-level", default="INFO")
    a = p.parse_args(argv)
    logging.basicConfig(
        level=a.log_level, format=f"%(asctime)s {a.name}[%(process)d] %(levelname)s %(message)s"
    )
    parent = os.environ.get(SUPERVISOR_PID_ENV)
    if parent:
        die_with_parent(int(parent))
    spec = LineSpec.from_file(a.config)
    svc = make_service(a.name, spec)
    return svc.serve()


if __name__ == "__main__":
    sys.exit(main())
