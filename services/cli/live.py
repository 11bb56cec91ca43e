"""``twin up | status | alerts | plant simulate``: the live twin from the shell (a recording is fed
to a running twin by ``twin replay REC --config LINE``)."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / "configs" / "line1.yaml"


def _spec(args: argparse.Namespace):
    from schemas.line import LineSpec

    return LineSpec.from_file(args.config or DEFAULT_CONFIG)


def _tool_session(spec, identity: str = "operator"):
    """A session on the line's bus as a tool (``services.security.tool_bus``); a bus that
    cannot be reached is a one-line error naming the endpoint."""
    import zenoh

    from services.bus import open_session
    from services.security import tool_bus

    bus = tool_bus(spec, identity)
    try:
        return open_session(bus)
    except zenoh.ZError:
        raise RuntimeError(
            f"no twin of line {spec.name} answers (is `twin up` running?), bus.connect: "
            f"{', '.join(bus.connect)}"
        ) from None


def _wait_for_signal() -> None:
    stop = threading.Event()

    def handler(signum, frame):  # noqa: ARG001
        stop.set()

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        while not stop.wait(0.2):
            pass
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def cmd_up(args: argparse.Namespace) -> int:
    from services.supervisor import Supervisor

    spec = _spec(args)
    services = args.services.split(",") if args.services else None
    sup = Supervisor(
        spec,
        services=services,
        secure=not args.insecure,
        log_level="DEBUG" if args.verbose else "INFO",
    )
    sup.start()
    if args.insecure:
        print(
            f"twin up: warning: open bus (--insecure): whoever reaches "
            f"{', '.join(spec.bus.listen)} may publish plant inputs and divert commands",
            file=sys.stderr,
            flush=True,
        )
    else:
        print(
            f"twin up: bus secured: per-run credentials and access control; the tools' "
            f"credentials are in {sup.run_dir / 'credentials'} (mode 0600)",
            flush=True,
        )
    ok = sup.wait_ready(args.ready_timeout)
    print(
        f"twin up: line {spec.name}, router {', '.join(spec.bus.listen)}, services "
        f"{', '.join(sup.names)} {'ready' if ok else 'NOT all ready'}; run dir {sup.run_dir}",
        flush=True,
    )
    try:
        _wait_for_signal()
    finally:
        codes = sup.stop()
        print(f"twin up: stopped {codes}", flush=True)
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    from services.bus import collect_health
    from services.common import status_rows, status_table

    spec = _spec(args)
    with _tool_session(spec) as s:
        alive, health = collect_health(s, spec.name, args.timeout)
    rows = status_rows(alive, health)
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0 if alive else 1
    if not rows:
        print(f"no service of line {spec.name} answers on {', '.join(spec.bus.listen)}")
        return 1
    print("\n".join(status_table(rows)))
    return 0


def cmd_alerts(args: argparse.Namespace) -> int:
    """Print the line's alerts as they come, each once, across restarts of the twin
    (``services.bus.TwinLink``: it says on stderr when it loses the twin and when it is back,
    and fetches what it missed from the new run's history)."""
    from services.bus import AlertFeed, TwinLink, open_session
    from services.common import format_alert

    spec = _spec(args)

    def emit(key: str, msg: Any) -> None:
        if args.json:
            print(json.dumps({"key": key, **msg.model_dump(mode="json")}), flush=True)
        else:
            print(format_alert(msg), flush=True)

    feed = AlertFeed(None, spec.name, emit, divert=args.divert, count=args.count)

    def connect(config: Any, again: bool) -> tuple[Any, Any]:  # noqa: ARG001 - always history
        session = open_session(config)
        feed.attach(session)

        def close() -> None:
            feed.undeclare()
            session.close()

        return session, close

    link = TwinLink(spec, "operator", connect, name="twin alerts").open()
    try:
        if args.timeout or args.count:
            feed.done.wait(args.timeout or None)
        else:
            _wait_for_signal()
    finally:
        link.close()
    return 0


def parse_disturbance(text: str) -> dict[str, Any]:
    """``FEEDER:T_S:DELTA_KG_H[:DURATION_S]`` -> a ``FlowDisturbance`` dict."""
    parts = text.split(":")
    if len(parts) not in (3, 4):
        raise ValueError(f"disturbance must be FEEDER:T_S:DELTA_KG_H[:DURATION_S], got {text!r}")
    d: dict[str, Any] = {"feeder": parts[0], "t_s": float(parts[1]), "delta_kg_h": float(parts[2])}
    if len(parts) == 4:
        d["duration_s"] = float(parts[3])
    return d


def parse_blade_speed(text: str) -> tuple[float, float]:
    """``T_S:RPM`` -> (plant time, blade speed)."""
    parts = text.split(":")
    try:
        t, rpm = (float(x) for x in parts)
    except ValueError:
        raise ValueError(f"blade speed must be T_S:RPM with numbers, got {text!r}") from None
    if not (t >= 0 and rpm > 0):
        raise ValueError(f"blade speed must have T_S >= 0 and RPM > 0, got {text!r}")
    return t, rpm


#: the keys of an effect given on the command line (``twin_core.plant.effects.make_effect``)
EFFECT_KEYS = ("name", "params", "target")


def parse_effect(text: str) -> dict:
    """An ``--effect`` JSON object, checked before any work: JSON, only the keys
    :data:`EFFECT_KEYS`, a known effect name and parameters it takes (ValueError naming the
    value otherwise)."""
    from twin_core.plant.effects import make_effect

    try:
        spec = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--effect must be a JSON object, got {text!r} ({exc.msg})") from None
    if not isinstance(spec, dict):
        raise ValueError(f"--effect must be a JSON object, got {text!r}")
    unknown = sorted(set(spec) - set(EFFECT_KEYS))
    if unknown:
        raise ValueError(
            f"--effect keys must be among {list(EFFECT_KEYS)} (parameters go in 'params'), "
            f"got {unknown} in {text!r}"
        )
    try:
        make_effect(spec)
    except TypeError as exc:
        raise ValueError(f"--effect parameters rejected, {text!r}: {exc}") from None
    return spec


def cmd_plant_simulate(args: argparse.Namespace) -> int:
    from services.cli.bus import check_output_file
    from services.recording import write_messages
    from twin_core.plant.messages import simulate_messages

    spec = _spec(args)
    dists = [parse_disturbance(d) for d in args.disturbance or []]
    effects = [parse_effect(e) for e in args.effect or []]
    check_output_file(Path(args.out))
    t0 = time.perf_counter()
    speeds = [parse_blade_speed(b) for b in args.blade_speed or []]
    from twin_core.tracking.assay import parse_lot_assay

    assays = [parse_lot_assay(a) for a in args.lot_assay or []]
    _, msgs = simulate_messages(spec, args.duration, args.seed, dists, effects, speeds, assays)
    n = write_messages(args.out, msgs)
    print(
        f"wrote {n} messages ({args.duration:.0f} s of plant time, seed {args.seed}, "
        f"{len(dists)} disturbance(s), {len(effects)} effect(s)) to {args.out} in "
        f"{time.perf_counter() - t0:.1f} s"
    )
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    def config_arg(p: argparse.ArgumentParser) -> None:
        p.add_argument("--config", help=f"line YAML/JSON (default {DEFAULT_CONFIG.name})")

    p = subparsers.add_parser("up", help="start the live twin's services (supervised)")
    config_arg(p)
    p.add_argument("--services", help="comma-separated subset (default: the config's list)")
    p.add_argument("--ready-timeout", type=float, default=60.0)
    p.add_argument(
        "--insecure",
        action="store_true",
        help="an open bus: no credentials, no access control (default: per-run credentials "
        "and an access control where only the diverter may divert)",
    )
    p.set_defaults(func=cmd_up)

    p = subparsers.add_parser("status", help="liveliness and health of the running services")
    config_arg(p)
    p.add_argument("--timeout", type=float, default=1.5)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_status)

    p = subparsers.add_parser("alerts", help="print OOS alerts as they come")
    config_arg(p)
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.add_argument("--divert", action="store_true", help="also print divert commands")
    p.add_argument("--count", type=int, default=0, help="exit after this many alerts")
    p.add_argument("--timeout", type=float, default=0.0, help="exit after this many seconds")
    p.set_defaults(func=cmd_alerts)

    p = subparsers.add_parser("plant", help="virtual plant: simulate a recording of the line")
    sub = p.add_subparsers(dest="plant_command", metavar="ACTION")
    ps = sub.add_parser("simulate", help="simulate the line and write an MCAP recording")
    config_arg(ps)
    ps.add_argument("--out", required=True, help="output .mcap")
    ps.add_argument("--duration", type=float, default=3600.0, help="plant time, s")
    ps.add_argument("--seed", type=int, default=0)
    ps.add_argument(
        "--disturbance",
        action="append",
        help="FEEDER:T_S:DELTA_KG_H[:DURATION_S] (repeatable), e.g. api:600:0.6:30",
    )
    ps.add_argument(
        "--effect",
        action="append",
        help='hidden effect as JSON (twin_core.plant.effects), e.g. \'{"name": "bypass", ...}\'',
    )
    ps.add_argument(
        "--blade-speed",
        action="append",
        help="T_S:RPM blade speed the plant reports from T_S on (repeatable), e.g. 900:75",
    )
    ps.add_argument(
        "--lot-assay",
        action="append",
        help="FEEDER:LOT:ASSAY a raw-material lot whose content is ASSAY of label in the truth "
        "(repeatable), e.g. api:L0003:0.9 (lots: <feeder>-L<k> for the k-th refill)",
    )
    ps.set_defaults(func=cmd_plant_simulate)
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])
