"""``twin record | replay | inspect | recover | schemas | router``: the bus and its recordings
(``twin replay`` is the one replay: of a recording onto any bus, or into a running twin with
``--config``). An empty, non-MCAP or incomplete recording is an error unless
``--allow-partial``; ``twin recover`` writes a complete file from an incomplete one."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from schemas import keys

log = logging.getLogger("twin.bus")


def add_bus_options(parser: argparse.ArgumentParser) -> None:
    """Options selecting the zenoh session (shared by every command that opens the bus)."""
    g = parser.add_argument_group("bus")
    g.add_argument("--bus-config", type=Path, help="BusConfig file (YAML or JSON)")
    g.add_argument("--mode", choices=["peer", "client", "router"], help="zenoh mode")
    g.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help="listen endpoint, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    g.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="connect endpoint (repeatable; default tcp/127.0.0.1:7447)",
    )
    g.add_argument("--line", help="line name in key expressions (default line1)")


def partial_arg(parser: argparse.ArgumentParser) -> None:
    """``--allow-partial``: go on with what an incomplete recording holds (the loss is said)."""
    parser.add_argument(
        "--allow-partial",
        action="store_true",
        help="accept an incomplete recording (cut short, corrupt chunks): use what is left",
    )


def check_output_file(path: Path) -> None:
    """Refuse, before any work, an output file whose folder does not exist or is not writable
    (no folder is created for it)."""
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise ValueError(f"the output's folder does not exist, {str(folder)!r} (of {str(path)!r})")
    if not os.access(folder, os.W_OK):
        raise ValueError(f"the output's folder is not writable, {str(folder)!r}")


def bus_config_from_args(args: argparse.Namespace, **defaults):
    """BusConfig from ``--bus-config`` then the individual options (options win)."""
    from schemas.bus_config import BusConfig

    data = {}
    if getattr(args, "bus_config", None):
        data = BusConfig.from_file(args.bus_config).model_dump(exclude_unset=True)
    data = {**defaults, **data}
    for name in ("mode", "listen", "connect", "line"):
        value = getattr(args, name, None)
        if value is not None:
            data[name] = value
    if getattr(args, "listen", None) and getattr(args, "connect", None) is None:
        data["connect"] = []
    return BusConfig.model_validate(data)


def cmd_record(args: argparse.Namespace) -> int:
    from services.recording import read_recording, record_bus, summarize

    check_output_file(args.out)
    cfg = bus_config_from_args(args)
    print(f"recording {args.keys} -> {args.out} (Ctrl-C to stop)", file=sys.stderr, flush=True)
    stats = record_bus(
        args.out,
        cfg,
        key_expr=args.keys,
        count=args.count,
        duration_s=args.duration,
        idle_timeout_s=args.idle_timeout,
        flush_every=args.flush_every,
        exclude_health=args.no_health,
        on_ready=lambda: print("ready", flush=True),
    )
    print(
        f"recorded {stats.total} messages on {len(stats.counts)} channels in {stats.wall_s:.1f} s "
        f"(stopped by {stats.reason}); rejected: {stats.rejected or 'none'}",
        flush=True,
    )
    if args.verbose_summary:
        print(summarize(read_recording(args.out)))
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from services.recording import read_recording, replay_to_bus

    rec = read_recording(args.file)
    rec.require_complete(args.allow_partial)
    if args.config:
        from schemas.line import LineSpec
        from services.security import tool_bus

        spec = LineSpec.from_file(args.config)
        line = {
            "spec": spec,
            "config": tool_bus(spec, "plant"),
            "settle_s": 0.5,
            "service_name": "plant",
            "allow_mismatch": args.allow_mismatch,
        }
    else:
        line = {"config": bus_config_from_args(args), "settle_s": args.settle}
    stats = replay_to_bus(
        rec,
        speed=args.speed,
        as_fast_as_possible=args.as_fast_as_possible,
        loop=args.loop,
        max_passes=args.passes,
        wait_for_subscribers_s=args.wait_subscribers,
        **line,
    )
    print(
        f"replayed {stats.published} messages ({stats.passes} pass(es), plant span "
        f"{stats.plant_span_s:.1f} s) in {stats.wall_s:.2f} s = {stats.rate_msg_s:.0f} msg/s"
        + (" (stopped)" if stats.stopped else ""),
        flush=True,
    )
    return 0


def cmd_inspect(args: argparse.Namespace) -> int:
    from services.recording import read_recording, summarize

    rec = read_recording(args.file)
    print(summarize(rec))
    rec.require_complete(args.allow_partial)
    return 0


def cmd_recover(args: argparse.Namespace) -> int:
    from services.recording import read_recording, write_recording

    out = Path(args.out)
    if out.resolve() == Path(args.file).resolve():
        raise ValueError(f"OUT must be another file than IN, got {str(out)!r} for both")
    check_output_file(out)
    rec = read_recording(args.file)
    if not rec.messages:
        raise ValueError(f"nothing to recover, {args.file}: {rec.loss_report()}")
    n = write_recording(rec, out)
    print(f"recovered {n} messages to {out} ({rec.loss_report()})", flush=True)
    return 0


def cmd_schemas(args: argparse.Namespace) -> int:
    from schemas.export import export_json_schemas

    paths = export_json_schemas(args.dir)
    for p in paths:
        print(p)
    print(f"{len(paths)} JSON Schemas written to {args.dir}", file=sys.stderr)
    return 0


def cmd_router(args: argparse.Namespace) -> int:
    from services.service import Service

    cfg = bus_config_from_args(args, mode="router", listen=["tcp/127.0.0.1:7447"], connect=[])
    with Service("router", cfg) as svc:
        print(f"router listening on {', '.join(cfg.listen)} (Ctrl-C to stop)", flush=True)
        svc.run()
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("record", help="record the bus to an MCAP file until stopped")
    p.add_argument("out", type=Path, help="output .mcap")
    p.add_argument(
        "--keys", default=keys.ALL_LINES, help=f"key expression to record ({keys.ALL_LINES})"
    )
    p.add_argument("--count", type=int, help="stop after this many messages")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument(
        "--idle-timeout",
        type=float,
        help="stop when nothing arrived for this many seconds (after the first)",
    )
    p.add_argument(
        "--flush-every",
        type=int,
        default=1000,
        help="write the open chunk every N messages (bounds crash loss; 1000)",
    )
    p.add_argument("--no-health", action="store_true", help="do not record service health")
    p.add_argument(
        "--summary",
        dest="verbose_summary",
        action="store_true",
        help="print the recording's summary at the end",
    )
    add_bus_options(p)
    p.set_defaults(func=cmd_record)

    p = subparsers.add_parser(
        "replay",
        help="replay an MCAP recording onto the bus, as recorded (with --config: the virtual "
        "plant of a running twin)",
    )
    p.add_argument("file", type=Path)
    p.add_argument(
        "--config",
        type=Path,
        help="line YAML/JSON of a running twin: its bus, history caches for late or restarted "
        "services, an end-of-stream event after the last message",
    )
    speed = p.add_mutually_exclusive_group()
    speed.add_argument(
        "--speed", type=float, default=1.0, help="plant-time speed-up factor (1 = real time)"
    )
    speed.add_argument("--as-fast-as-possible", action="store_true")
    p.add_argument(
        "--loop",
        action="store_true",
        help="repeat forever (t and seq shifted so they keep increasing)",
    )
    p.add_argument("--passes", type=int, help="with --loop: stop after this many passes")
    p.add_argument(
        "--wait-subscribers",
        type=float,
        default=0.0,
        metavar="S",
        help="wait up to S seconds for subscribers on every channel",
    )
    p.add_argument(
        "--settle",
        type=float,
        default=0.0,
        metavar="S",
        help="wait S seconds before the first message",
    )
    p.add_argument(
        "--allow-mismatch",
        action="store_true",
        help="with --config: replay a recording whose line (provenance, first messages) differs "
        "from the twin's configuration",
    )
    partial_arg(p)
    add_bus_options(p)
    p.set_defaults(func=cmd_replay)

    p = subparsers.add_parser("inspect", help="channels, counts, time span, schemas of a file")
    p.add_argument("file", type=Path)
    partial_arg(p)
    p.set_defaults(func=cmd_inspect)

    p = subparsers.add_parser(
        "recover",
        help="write what a crash-cut or corrupt recording holds to a new, complete MCAP file",
    )
    p.add_argument("file", type=Path, metavar="IN")
    p.add_argument("out", type=Path, metavar="OUT")
    p.set_defaults(func=cmd_recover)

    p = subparsers.add_parser("schemas", help="wire-contract JSON Schemas")
    sp = p.add_subparsers(dest="schemas_command", metavar="SUBCOMMAND", required=True)
    e = sp.add_parser("export", help="write the JSON Schema of every schemas.* model")
    e.add_argument("dir", type=Path)
    e.set_defaults(func=cmd_schemas)

    p = subparsers.add_parser("router", help="run a zenoh router for the twin's processes")
    add_bus_options(p)
    p.set_defaults(func=cmd_router)
