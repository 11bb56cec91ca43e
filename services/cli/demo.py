"""``twin demo``: the whole twin on the bundled recording.

1. Replay the recording over zenoh while ``twin record`` captures it in another process, and
   check the capture equals the source message for message (the wire contract end to end).
2. Start the live twin's services (``twin up``), replay the recording into them at high speed,
   print the OOS alerts as they come, and write a run report (``report.json``, ``report.md``)
   with the measured vs predicted outlet figure (``outlet.png``) to ``--out``.
"""

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
    if not result.ok:
        return 1
    if args.check_only:
        return 0
    from services.twin_demo import run_full_twin_demo

    print(
        f"\ntwin demo: the live twin (feeder, blender, rtd, oos, closeloop, recorder services) on the same "
        f"recording at {args.twin_speed:g}x; report and figure to {args.out}/",
        flush=True,
    )
    report = run_full_twin_demo(recording, args.out, speed=args.twin_speed, opcua=args.opcua)
    print(f"report: {Path(args.out) / 'report.md'}  figure: {Path(args.out) / 'outlet.png'}")
    healthy = (
        report["predictions"] > 0
        and report["duplicates_seen"] == 0
        and all(code == 0 for code in report["exit_codes"].values())
    )
    if not healthy:
        print(
            f"twin demo: FAILED (exit codes {report['exit_codes']}, "
            f"duplicates {report['duplicates_seen']}, predictions {report['predictions']})"
        )
    return 0 if healthy else 1


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
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="run report directory")
    p.add_argument(
        "--twin-speed", type=float, default=200.0, help="replay speed-up into the live twin"
    )
    p.add_argument(
        "--check-only", action="store_true", help="only the replay/record check (step 1)"
    )
    p.add_argument(
        "--opcua",
        action="store_true",
        help="feed the live twin through the OPC UA bridge from a loopback OPC UA plant serving "
        "the recording (divert commands written back to its gate node)",
    )
    p.set_defaults(func=cmd_demo)
