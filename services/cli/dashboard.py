"""``twin dashboard``: the live twin, or a recording, in the browser (``services.dashboard``)."""

from __future__ import annotations

import argparse
import math
import signal
import sys
from pathlib import Path
from typing import Any

from services.cli.live import DEFAULT_CONFIG


def _check_args(args: argparse.Namespace) -> None:
    """One-line errors for bad options (ValueError naming option and value)."""
    from services.dashboard import is_loopback

    if not (0 < args.port < 65536):
        raise ValueError(f"--port must be in 1..65535, got {args.port}")
    if not math.isfinite(args.speed) or args.speed <= 0:
        raise ValueError(f"--speed must be a finite number > 0, got {args.speed}")
    if args.period_ms < 20:
        raise ValueError(f"--period-ms must be >= 20, got {args.period_ms}")
    if args.max_points < 10:
        raise ValueError(f"--max-points must be >= 10, got {args.max_points}")
    if not math.isfinite(args.window_s) or args.window_s <= 0:
        raise ValueError(f"--window-s must be a finite number > 0, got {args.window_s}")
    if not is_loopback(args.address) and not args.allow_remote:
        raise ValueError(
            f"--address is not a loopback address (add --allow-remote to serve the page to "
            f"the network), got {args.address!r}"
        )
    if args.recording and not Path(args.recording).is_file():
        raise ValueError(f"--recording file not found, got {args.recording!r}")


def _stop_on_signals(server: Any) -> None:
    def handler(signum: int, frame: Any) -> None:  # noqa: ARG001
        server.io_loop.add_callback_from_signal(server.io_loop.stop)

    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, handler)


def cmd_dashboard(args: argparse.Namespace) -> int:
    from schemas.line import LineSpec
    from services.dashboard import (
        BusFeed,
        DashboardHub,
        is_loopback,
        make_server,
        start_recording_feed,
    )

    _check_args(args)
    spec = LineSpec.from_file(args.config or DEFAULT_CONFIG)
    hub = DashboardHub(spec, max_points=args.max_points)
    stopping = False
    link = None
    if args.recording:
        from services.recording import read_recording, recording_mismatches

        rec = read_recording(args.recording)
        rec.require_complete(args.allow_partial)
        found = recording_mismatches(rec, spec)
        if found and not args.allow_mismatch:
            raise ValueError(
                f"the recording does not match the line configuration of --config "
                f"(--allow-mismatch shows it anyway), {'; '.join(str(x) for x in found)}"
            )
    else:
        from services.bus import TwinLink, open_session

        feed = BusFeed(None, hub)
        live = f"live bus {', '.join(spec.client_bus().connect)}"

        def connect(config: Any, again: bool) -> tuple[Any, Any]:  # noqa: ARG001
            bus = open_session(config)
            feed.attach(bus)
            hub.set_source(f"live bus {', '.join(config.connect)}")

            def close() -> None:
                feed.undeclare()
                bus.close()

            return bus, close

        def say(text: str) -> None:
            print(text, file=sys.stderr, flush=True)
            if "lost the twin" in text:
                hub.set_source(f"{live}: LOST THE TWIN, waiting for it (the data shown is old)")

        link = TwinLink(spec, "operator", connect, name="twin dashboard", say=say).open()
    server = make_server(
        hub,
        address=args.address,
        port=args.port,
        period_ms=args.period_ms,
        window_s=args.window_s,
    )
    server.start()
    if args.recording:
        start_recording_feed(rec, hub, args.speed, lambda: stopping)
    if not is_loopback(args.address):
        print(
            f"twin dashboard: warning: serving on {args.address}: whoever reaches it sees the "
            f"line's data (the page has no login)",
            file=sys.stderr,
            flush=True,
        )
    print(
        f"twin dashboard: line {spec.name}, {hub.source}, http://{args.address}:{args.port}/",
        flush=True,
    )
    _stop_on_signals(server)
    try:
        server.io_loop.start()
    finally:
        stopping = True
        server.stop()
        if link is not None:
            link.close()
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "dashboard", help="the live twin or a recording in the browser (Bokeh server, loopback)"
    )
    p.add_argument("--config", help=f"line YAML/JSON (default {DEFAULT_CONFIG.name})")
    p.add_argument(
        "--recording", help="show this MCAP recording instead of the live bus (replayed)"
    )
    p.add_argument("--speed", type=float, default=1.0, help="replay speed of --recording")
    p.add_argument("--allow-partial", action="store_true", help="show a damaged recording")
    p.add_argument(
        "--allow-mismatch",
        action="store_true",
        help="show a recording whose feeders or sensor differ from --config",
    )
    p.add_argument("--port", type=int, default=5006)
    p.add_argument("--address", default="127.0.0.1", help="listen address (default loopback)")
    p.add_argument(
        "--allow-remote",
        action="store_true",
        help="allow a non-loopback --address (the page has no login)",
    )
    p.add_argument("--period-ms", type=int, default=200, help="page refresh period, ms")
    p.add_argument("--max-points", type=int, default=600, help="points per plotted series")
    p.add_argument("--window-s", type=float, default=3600.0, help="plant time shown, s")
    p.set_defaults(func=cmd_dashboard)
