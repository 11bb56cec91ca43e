"""``twin up | status | alerts | plant simulate``: the live twin from the shell (a recording is fed
to a running twin by ``twin replay REC --config LINE``)."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import threading
import time
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / "configs" / "line1.yaml"


def _spec(args: argparse.Namespace):
    from schemas.line import LineSpec

    return LineSpec.from_file(args.config or DEFAULT_CONFIG)


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
    sup = Supervisor(spec, services=services, log_level="DEBUG" if args.verbose else "INFO")
    sup.start()
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
    import zenoh

    from schemas import keys
    from schemas.messages import ServiceHealth
    from services.bus import live_services, open_session

    spec = _spec(args)
    health: dict[str, ServiceHealth] = {}

    def on_health(sample: zenoh.Sample) -> None:
        try:
            h = ServiceHealth.model_validate_json(sample.payload.to_bytes())
        except ValueError:
            return
        health[h.service] = h

    with open_session(spec.client_bus()) as s:
        sub = s.declare_subscriber(
            keys.services_health(spec.name), zenoh.handlers.Callback(on_health, lambda: None)
        )
        alive = live_services(s, spec.name, timeout_s=args.timeout)
        time.sleep(args.timeout)
        sub.undeclare()
    rows = sorted(set(alive) | set(health))
    if args.json:
        print(
            json.dumps(
                {
                    n: {
                        "alive": n in alive,
                        **(health[n].model_dump(mode="json") if n in health else {}),
                    }
                    for n in rows
                },
                indent=2,
            )
        )
        return 0 if alive else 1
    if not rows:
        print(f"no service of line {spec.name} answers on {', '.join(spec.bus.listen)}")
        return 1
    print(
        f"{'service':<10} {'alive':<6} {'state':<9} {'pid':>7} {'up_s':>8} {'plant_t':>9}  counters"
    )
    for n in rows:
        h = health.get(n)
        if h is None:
            print(f"{n:<10} {'yes' if n in alive else 'no':<6}")
            continue
        c = " ".join(f"{k}={v}" for k, v in sorted(h.counters.items()))
        print(
            f"{n:<10} {'yes' if n in alive else 'no':<6} {h.state:<9} {h.pid:>7} "
            f"{h.uptime_s:>8.1f} {h.t:>9.1f}  {c}"
        )
    return 0


def cmd_alerts(args: argparse.Namespace) -> int:
    from schemas import keys
    from schemas.messages import DivertCommand, OosAlert
    from services.bus import HistoryFeed, open_session
    from services.common import format_alert

    spec = _spec(args)
    seen: set[str] = set()
    lock = threading.Lock()
    count = [0]
    done = threading.Event()

    def printer(model):
        def cb(key: str, payload: bytes) -> None:
            try:
                msg = model.model_validate_json(payload)
            except ValueError as exc:
                log.warning("bad message on %s: %s", key, exc)
                return
            ident = getattr(msg, "alert_id", None) if model is OosAlert else msg.command_id
            with lock:
                if ident in seen:
                    return
                seen.add(ident)
                if args.json:
                    print(json.dumps({"key": key, **msg.model_dump(mode="json")}))
                else:
                    print(format_alert(msg), flush=True)
                if model is OosAlert:
                    count[0] += 1
                    if args.count and count[0] >= args.count:
                        done.set()

        return cb

    with open_session(spec.client_bus()) as s:
        subs = []
        for key, model in ((keys.oos_alert(spec.name), OosAlert),):
            subs.append(HistoryFeed(s, key, printer(model)))
        if args.divert:
            subs.append(HistoryFeed(s, keys.divert_command(spec.name), printer(DivertCommand)))
        if args.timeout:
            done.wait(args.timeout)
        elif args.count:
            done.wait()
        else:
            _wait_for_signal()
        for sub in subs:
            sub.undeclare()
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


def cmd_plant_simulate(args: argparse.Namespace) -> int:
    from services.recording import write_messages
    from twin_core.plant.messages import simulate_messages

    spec = _spec(args)
    dists = [parse_disturbance(d) for d in args.disturbance or []]
    effects = [json.loads(e) for e in args.effect or []]
    t0 = time.perf_counter()
    _, msgs = simulate_messages(spec, args.duration, args.seed, dists, effects)
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
    ps.set_defaults(func=cmd_plant_simulate)
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])
