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
from typing import Any

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


def explicit_bus(args: argparse.Namespace) -> bool:
    """Whether the command line names the bus (``--bus-config``, ``--mode``, ``--listen``,
    ``--connect``): then it is used as given, nothing is looked up."""
    return any(getattr(args, n, None) for n in ("bus_config", "mode", "listen", "connect"))


def _line_spec(args: argparse.Namespace):
    from schemas.line import LineSpec
    from services.cli.live import DEFAULT_CONFIG

    return LineSpec.from_file(args.config or DEFAULT_CONFIG)


def record_bus_choice(args: argparse.Namespace) -> tuple[Any, str, str, str, Any]:
    """The recorder's bus, its name on the bus, the key expression it records (``--keys``, by
    default every line; of a running twin, its line: the only keys a secured twin lets a tool
    subscribe to), a line saying where it records and the line of the running twin it follows
    across restarts (None: not a twin's).

    Bus options given: as given (name ``recorder``). Else, when a ``twin up`` of the line
    (``--config``, default ``line1.yaml``) runs here: a client of its router found through the
    run's lock file, as the ``record`` identity (its password from the run directory). Else a
    peer listening on the line's endpoint, for ``twin replay`` to connect to (peer to peer)."""
    from schemas.bus_config import BusConfig
    from services.common import running_twin
    from services.security import tool_bus

    if explicit_bus(args):
        cfg = bus_config_from_args(args)
        where = f"on the bus of the options ({', '.join(cfg.connect or cfg.listen)})"
        return cfg, "recorder", args.keys or keys.ALL_LINES, where, None
    spec = _line_spec(args)
    info = running_twin(spec)
    if info is not None:
        cfg = tool_bus(spec, "record")
        where = f"from the running twin of line {spec.name} (run dir {info.run_dir})"
        return cfg, "record", args.keys or keys.everything(spec.name), where, spec
    endpoints = list(spec.client_bus().connect)
    cfg = BusConfig(mode="peer", listen=endpoints, connect=[], line=spec.name)
    where = (
        f"no twin of line {spec.name} runs here: listening on {', '.join(endpoints)} for "
        "`twin replay` (peer to peer)"
    )
    return cfg, "recorder", args.keys or keys.ALL_LINES, where, None


def cmd_record(args: argparse.Namespace) -> int:
    import zenoh

    from services.recording import read_recording, record_bus, summarize

    check_output_file(args.out)
    if args.idle_timeout is not None and not args.idle_timeout > 0:
        raise ValueError(f"--idle-timeout must be a number > 0, got {args.idle_timeout}")
    cfg, name, key_expr, where, twin = record_bus_choice(args)
    print(
        f"recording {key_expr} -> {args.out} {where} (Ctrl-C to stop)", file=sys.stderr, flush=True
    )
    try:
        stats = record_bus(
            args.out,
            cfg,
            key_expr=key_expr,
            count=args.count,
            duration_s=args.duration,
            idle_timeout_s=args.idle_timeout,
            flush_every=args.flush_every,
            exclude_health=args.no_health,
            service_name=name,
            on_ready=lambda: print("ready", flush=True),
            twin=twin,
        )
    except zenoh.ZError:
        ends = cfg.connect if cfg.mode == "client" else cfg.listen
        raise RuntimeError(
            f"cannot record: the bus refused or its endpoint is in use (another program?), "
            f"bus.{'connect' if cfg.mode == 'client' else 'listen'}: {', '.join(ends)}"
        ) from None
    print(
        f"recorded {stats.total} messages on {len(stats.counts)} channels in {stats.wall_s:.1f} s "
        f"(stopped by {stats.reason}); rejected: {stats.rejected or 'none'}",
        flush=True,
    )
    if args.verbose_summary:
        print(summarize(read_recording(args.out)))
    return 0


def replay_choice(args: argparse.Namespace) -> dict[str, Any]:
    """The replay's target, as :class:`~services.recording.BusReplay` options.

    ``--config``: the virtual plant of that line's running twin. Bus options: the bus as given.
    Neither: the running twin of the default line (``line1.yaml``) when one runs here (found
    through the run's lock file; its own configuration, ``<run dir>/line.json``, as if given
    with ``--config``); else a client of the line's endpoint, where ``twin record`` listens
    (peer to peer); a RuntimeError when nobody listens there."""
    from schemas.line import LineSpec
    from services.common import running_line, running_twin
    from services.security import tool_bus

    if args.config or not explicit_bus(args):
        spec = LineSpec.from_file(args.config) if args.config else _line_spec(args)
        info = running_twin(spec)
        if not args.config and info is not None:
            spec = running_line(info)
            print(
                f"twin replay: into the running twin of line {spec.name} (run dir "
                f"{info.run_dir}) as its plant",
                file=sys.stderr,
                flush=True,
            )
        cfg = spec.client_bus().model_copy(update={"timestamping": False})
        hint = (
            f"no twin of line {spec.name} runs here and nobody (`twin record`) listens on "
            f"{', '.join(cfg.connect)}; start `twin up` or `twin record` first, or give "
            "--connect, bus.connect"
        )
        if args.config or info is not None:
            return {
                "spec": spec,
                "config": tool_bus(spec, "plant"),
                "settle_s": 0.5,
                "service_name": "plant",
                "allow_mismatch": args.allow_mismatch,
                "peer_hint": hint if info is None else None,
            }
        return {
            "config": cfg,
            "settle_s": args.settle,
            "wait_for_subscribers_s": args.wait_subscribers or 5.0,
            "peer_hint": hint,
        }
    return {
        "config": bus_config_from_args(args),
        "settle_s": args.settle,
        "wait_for_subscribers_s": args.wait_subscribers,
    }


def cmd_replay(args: argparse.Namespace) -> int:
    import zenoh

    from services.recording import read_recording, replay_to_bus

    rec = read_recording(args.file)
    rec.require_complete(args.allow_partial)
    line = replay_choice(args)
    hint = line.pop("peer_hint", None)
    try:
        stats = replay_to_bus(
            rec,
            speed=args.speed,
            as_fast_as_possible=args.as_fast_as_possible,
            loop=args.loop,
            max_passes=args.passes,
            **{"wait_for_subscribers_s": args.wait_subscribers, **line},
        )
    except zenoh.ZError:
        if hint is None:
            raise
        raise RuntimeError(hint) from None
    print(
        f"replayed {stats.published} messages ({stats.passes} pass(es), plant span "
        f"{stats.plant_span_s:.1f} s) in {stats.wall_s:.2f} s = {stats.rate_msg_s:.0f} msg/s"
        + (" (stopped)" if stats.stopped else ""),
        flush=True,
    )
    own = line.get("service_name", "replay")
    if stats.published and not [n for n in stats.acknowledged_by if n != own]:
        print(
            "twin replay: warning: no service or recorder on the bus acknowledged the messages "
            "(nobody subscribed?)",
            file=sys.stderr,
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
    holes = [*rec.recovered_holes, *rec.holes()]
    for h in holes:  # every hole of what was written, also in its 'recovery' metadata
        print(h.describe(), file=sys.stderr, flush=True)
    n_holes = f"{len(holes)} hole" + ("s" if len(holes) != 1 else "")
    named = f"; {n_holes} named in its 'recovery' metadata" if holes else ""
    print(f"recovered {n} messages to {out}{named} ({rec.loss_report()})", flush=True)
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
        "--keys",
        help=f"key expression to record (default {keys.ALL_LINES}; of a running twin, its line's)",
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
        "--config",
        type=Path,
        help="line YAML/JSON whose running twin to record (default line1.yaml; found through "
        "the run's lock file in its state_dir); no twin running: listen for `twin replay`",
    )
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
