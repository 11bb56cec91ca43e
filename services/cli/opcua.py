"""``twin bridge opcua`` (a line's OPC UA server into the twin), ``twin plant opcua`` (the
loopback OPC UA plant serving a recording) and ``twin import`` (a historian or PAT export
into a recording), all on one mapping (``BRIDGE.yaml``, ``schemas.opcua.BridgeConfig``)."""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from pathlib import Path

log = logging.getLogger("twin.opcua")


def cmd_bridge(args: argparse.Namespace) -> int:
    from schemas.line import LineSpec
    from schemas.opcua import BridgeConfig
    from services.opcua_bridge import OpcuaBridge
    from services.security import tool_bus

    config = BridgeConfig.from_file(args.config)
    spec = LineSpec.from_file(args.line)
    if spec.name != config.line:
        raise ValueError(f"line must be the twin's, got {config.line!r} for {spec.name!r}")
    bridge = OpcuaBridge(
        config,
        tool_bus(spec, "plant"),
        spec=spec,
        insecure=args.insecure,
        install_signal_handlers=True,
    )
    print(f"bridging {config.endpoint} -> line {spec.name} (Ctrl-C to stop)", flush=True)
    return bridge.serve()


def _pki_folder(args: argparse.Namespace) -> Path | None:
    """Where a secured plant keeps its per-run certificates and password: ``--pki``, else
    beside ``--write-config`` (``BRIDGE.yaml`` -> ``BRIDGE-pki/``), else a temporary folder."""
    if args.pki is not None:
        return args.pki
    if args.write_config is not None:
        return args.write_config.with_name(f"{args.write_config.stem}-pki")
    return None


def cmd_plant_opcua(args: argparse.Namespace) -> int:
    import yaml

    from services.bus import StopFlag
    from services.opcua_bridge import quiet_opcua_stack
    from services.opcua_plant import LoopbackPlant, read_users, recording_messages

    if args.insecure and (args.users is not None or args.pki is not None):
        raise ValueError("--insecure serves without security: --users and --pki do not apply")
    if not args.recording.exists():
        raise FileNotFoundError(2, "No such file or directory", str(args.recording))
    users = read_users(args.users) if args.users is not None else None
    quiet_opcua_stack()
    plant = LoopbackPlant(
        recording_messages(args.recording),
        port=args.port,
        speed=args.speed,
        insecure=args.insecure,
        pki=None if args.insecure else _pki_folder(args),
        users=users,
    )
    stop = StopFlag(install=True)

    async def main() -> int:
        await plant.start()
        if plant.insecure:
            print(
                "warning: --insecure: security None, anonymous sessions; anyone reaching "
                f"{plant.endpoint} may read every node and write the gate's command",
                file=sys.stderr,
                flush=True,
            )
        else:
            print(
                f"security: Basic256Sha256 SignAndEncrypt, users {', '.join(plant.users)}; "
                f"server certificate {plant.certificate}, trusted client certificate "
                f"{plant.pki.client_certificate} (made for this run in {plant.pki.folder})",
                file=sys.stderr,
                flush=True,
            )
        if args.write_config:
            args.write_config.write_text(
                yaml.safe_dump(plant.bridge_config().model_dump(mode="json"), sort_keys=False)
            )
        print(f"serving {args.recording} on {plant.endpoint} at {args.speed:g}x", flush=True)
        try:
            play = asyncio.ensure_future(plant.play())
            while not play.done() and not stop.is_set():
                await asyncio.sleep(0.2)
            return play.result() if play.done() else 0
        finally:
            await plant.stop()

    ticks = asyncio.run(main())
    print(f"served {ticks} ticks; {len(plant.commands)} divert commands written to the gate")
    return 0


def cmd_import(args: argparse.Namespace) -> int:
    from schemas.opcua import BridgeConfig
    from services.cli.bus import check_output_file
    from services.recording import write_messages
    from twin_core.plant.opcua_import import BadRows, import_export

    check_output_file(args.out)
    if not args.export.exists():
        raise FileNotFoundError(2, "No such file or directory", str(args.export))
    config = BridgeConfig.from_file(args.config)
    try:
        messages, report = import_export(
            args.export,
            config,
            time_column=args.time_column,
            timezone=args.timezone,
            skip_bad_rows=args.skip_bad_rows,
        )
    except BadRows as exc:  # every bad row named, then the one-line error
        for b in exc.bad:
            print(f"bad row: {b.describe()}", file=sys.stderr)
        raise
    if not messages:
        raise ValueError(f"no message could be built from the export, {args.export}")
    write_messages(args.out, messages)
    summary, *found = report.lines()
    print(summary)
    for line in found:  # bad rows skipped, duplicates, conflicts, gaps, stamps without message
        print(line, file=sys.stderr)
    print(f"wrote {args.out}", flush=True)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("bridge", help="bridge a line's OPC UA server into the twin")
    sp = p.add_subparsers(dest="bridge_command", metavar="SUBCOMMAND", required=True)
    b = sp.add_parser("opcua", help="OPC UA subscriptions -> the twin's bus; divert commands back")
    b.add_argument("--config", type=Path, required=True, help="BRIDGE.yaml (the node mapping)")
    b.add_argument("--line", type=Path, required=True, help="the twin's line YAML/JSON")
    b.add_argument(
        "--insecure",
        action="store_true",
        help="write divert commands even without a secured bus and OPC UA session",
    )
    b.set_defaults(func=cmd_bridge)

    p = subparsers.add_parser(
        "plant-opcua", help="serve a recording as an OPC UA plant on loopback (tests, demos)"
    )
    p.add_argument("recording", type=Path)
    p.add_argument("--port", type=int, default=4840)
    p.add_argument("--speed", type=float, default=1.0, help="plant-time speed-up")
    p.add_argument(
        "--write-config",
        type=Path,
        help="write the BRIDGE.yaml of its nodes (and the bridge's security) here",
    )
    p.add_argument(
        "--insecure",
        action="store_true",
        help="serve without security (policy None, anonymous sessions); default: Basic256Sha256 "
        "SignAndEncrypt with user/password",
    )
    p.add_argument(
        "--users",
        type=Path,
        help="user:password lines (a 0600 file); default: user twin with a password made per run",
    )
    p.add_argument(
        "--pki",
        type=Path,
        help="folder of the per-run certificates and password (default: beside --write-config, "
        "else a temporary folder)",
    )
    p.set_defaults(func=cmd_plant_opcua)

    p = subparsers.add_parser(
        "import", help="a historian / PAT CSV export -> a recording, with the bridge's mapping"
    )
    p.add_argument("export", type=Path, help="wide CSV file, or a folder of <tag>.csv files")
    p.add_argument("--config", type=Path, required=True, help="BRIDGE.yaml (tags, units)")
    p.add_argument("--out", type=Path, required=True, help="output .mcap")
    p.add_argument("--time-column", default="timestamp", help="time column (default timestamp)")
    p.add_argument("--timezone", help="time zone of stamps that carry none, e.g. Europe/Berlin")
    p.add_argument(
        "--skip-bad-rows",
        action="store_true",
        help="leave out rows with a bad stamp or value (counted and named); "
        "without it a bad row stops the import (exit 2)",
    )
    p.set_defaults(func=cmd_import)
