"""``twin dem run SCENE.yaml [--out DIR] [--resume [--pair-chunks N]] [--threads auto|N]``: run a DEM scene of the seed
(blender section, drawdown test, feeder, silo) from its config file and write results, fields,
frames, STL geometry and PNG figures. ``twin dem warmup``: compile the engine's kernels into
numba's cache, saying what it compiles (once after installing; ``twin dem run`` runs it first)."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
from pathlib import Path

log = logging.getLogger("twin.dem")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("dem", help="DEM scenes of the seed")
    sub = p.add_subparsers(dest="dem_command", metavar="DEM_COMMAND")
    r = sub.add_parser("run", help="run a scene config (YAML)")
    r.add_argument("scene", type=Path, help="scene YAML (twin_core/scenes/configs/*.yaml)")
    r.add_argument(
        "--out", type=Path, default=None, help="output directory (default out/dem/<name>)"
    )
    r.add_argument("--resume", action="store_true", help="continue from the last checkpoint")
    r.add_argument(
        "--pair-chunks",
        default=None,
        help="with --resume: split the pair forces into N chunks (one per thread that should "
        "share them) instead of the saved run's count, e.g. 2 to continue a one-thread run on "
        "two threads (not bit-identical to the uninterrupted run); a new run uses the thread "
        "count",
    )
    r.add_argument(
        "--threads",
        default="auto",
        help="numba threads, or 'auto' (default): 1 or all, chosen by measured throughput "
        "while it runs (twin_core.dem.threads)",
    )
    r.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    r.set_defaults(func=cmd_run)
    w = sub.add_parser(
        "warmup", help="compile the engine's numba kernels into the cache (once per install)"
    )
    w.set_defaults(func=cmd_warmup)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def cmd_run(args: argparse.Namespace) -> int:
    from schemas.dem_scene import load_scene
    from twin_core.scenes.runner import run_scene

    try:
        cfg = load_scene(args.scene)
    except ValueError as exc:
        raise ValueError(f"invalid scene, {args.scene}: {exc}") from None
    from twin_core.dem.threads import adaptive_threads, prefer_openmp

    prefer_openmp()
    policy = contextlib.nullcontext()
    if args.threads == "auto":
        policy = adaptive_threads()
    else:
        import numba

        try:
            threads = int(args.threads)
        except ValueError:
            raise ValueError(
                f"--threads must be 'auto' or an integer, got {args.threads!r}"
            ) from None
        if threads < 1:
            raise ValueError(f"--threads must be >= 1, got {threads}")
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    pair_chunks = _pair_chunks(args.pair_chunks, args.resume)
    out = args.out or Path("out") / "dem" / cfg.name
    with policy:
        summary = run_scene(
            cfg, out, resume=args.resume, progress=not args.no_progress, pair_chunks=pair_chunks
        )
    print(json.dumps(summary, indent=1, default=str))
    return 0


def _pair_chunks(value: str | None, resume: bool) -> int | None:
    """The ``--pair-chunks`` value: None (keep the saved count) or an integer >= 1."""
    if value is None:
        return None
    if not resume:
        raise ValueError(f"--pair-chunks applies to --resume only, got --pair-chunks {value}")
    try:
        k = int(value)
    except ValueError:
        raise ValueError(f"--pair-chunks must be an integer >= 1, got {value!r}") from None
    if k < 1:
        raise ValueError(f"--pair-chunks must be an integer >= 1, got {k}")
    return k


def cmd_warmup(args: argparse.Namespace) -> int:
    from twin_core.dem.warmup import compile_kernels

    times = compile_kernels(report=log.info)
    print(json.dumps({"total_s": round(sum(times.values()), 2), "phases_s": times}, indent=1))
    return 0
