"""``twin demo``: replay the bundled recording over zenoh while ``twin record`` captures it in
another process; check the capture equals the source message for message."""

from __future__ import annotations

import argparse
from pathlib import Path


def cmd_demo(args: argparse.Namespace) -> int:
    from services.demo import BUNDLED_RECORDING, run_replay_check

    recording = args.recording or BUNDLED_RECORDING
    mode = "as fast as possible" if args.as_fast_as_possible else f"at {args.speed:g}x"
    print(
        f"twin demo: replaying {recording} {mode} while `twin record` captures the bus", flush=True
    )
    result = run_replay_check(
        recording,
        speed=args.speed,
        as_fast_as_possible=args.as_fast_as_possible,
        capture=args.capture,
        timeout_s=args.timeout,
    )
    print(result.summary(), flush=True)
    return 0 if result.ok else 1


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "demo", help="replay the bundled recording over zenoh and check a parallel capture"
    )
    p.add_argument("--recording", type=Path, help="MCAP file (default: the bundled recording)")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument(
        "--speed",
        type=float,
        default=120.0,
        help="plant-time speed-up (default 120: 30 min in 15 s)",
    )
    speed.add_argument("--as-fast-as-possible", action="store_true")
    p.add_argument("--capture", type=Path, help="where to write the capture (default: temp dir)")
    p.add_argument("--timeout", type=float, default=300.0, help="give up after this many seconds")
    p.set_defaults(func=cmd_demo)
