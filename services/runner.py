"""Process entry point of one live service: ``python -m services.runner NAME --config LINE``.

``twin up`` starts every service this way (a fresh interpreter per service: no fork after zenoh
is open). ``--config`` takes the line YAML/JSON; the run's state directory comes from
``$TWIN_STATE_DIR``.
"""

from __future__ import annotations

import argparse
import logging
import sys

from schemas.line import LineSpec

log = logging.getLogger("services.runner")


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
    raise ValueError(
        f"service must be one of blender, oos, feeder, rtd, recorder, dem, closeloop, got {name!r}"
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
    spec = LineSpec.from_file(a.config)
    svc = make_service(a.name, spec)
    return svc.serve()


if __name__ == "__main__":
    sys.exit(main())
