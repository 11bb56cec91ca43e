"""`twin mixing compute`: mixing indices, T95 fits and figures from a DEM frames directory."""

from __future__ import annotations

import argparse
import logging

import numpy as np

log = logging.getLogger("twin.mixing")


def _triple(text: str, name: str) -> tuple[float, float, float]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise SystemExit(f"{name} must be three comma-separated numbers, got {text!r}") from None
    if len(vals) != 3:
        raise SystemExit(f"{name} must be three comma-separated numbers, got {text!r}")
    return vals  # type: ignore[return-value]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("mixing", help="mixing indices and T95 mixing times (seed chapter 4)")
    msub = p.add_subparsers(dest="mixing_command", metavar="ACTION")
    c = msub.add_parser("compute", help="indices of every frame, T95 fits, CSV and figures")
    c.add_argument("frames", help="frames directory written by `twin dem run`")
    c.add_argument("--indices", default="all", help="'all' or a comma list, e.g. LI,RSD,SI")
    c.add_argument("--grid", default="1x8x8", help="cells along x, y, z (seed: 1x8x8)")
    c.add_argument("--lo", help="grid box lower corner x,y,z in m (default: from the frames meta)")
    c.add_argument("--hi", help="grid box upper corner x,y,z in m (default: from the frames meta)")
    c.add_argument("--periodic", default=None, help="periodic axes, e.g. 'x' (default: meta)")
    c.add_argument("--tracer", type=int, default=None, help="type id of the tracer particles")
    c.add_argument("--sm-pairs", default="20000", help="Siiria pairs sampled, or 'exact'")
    c.add_argument("--start", type=float, default=None, help="first frame time used (s)")
    c.add_argument("--out", required=True, help="output directory")
    c.set_defaults(func=_compute)
    b = msub.add_parser(
        "blender",
        help="T95 table and figure across blade speeds from `twin dem run` blender runs "
        "(seed Table 4.2 / Fig. 4.7)",
    )
    b.add_argument("scene", help="the blender scene YAML the runs were made with")
    b.add_argument("--runs", required=True, help="the --out directory of `twin dem run`")
    b.add_argument("--indices", default="all", help="'all' or a comma list")
    b.add_argument("--sm-pairs", default="20000", help="Siiria pairs sampled, or 'exact'")
    b.add_argument("--out", required=True, help="output directory")
    b.set_defaults(func=_blender)


def _sm_pairs(text: str) -> int | None:
    return None if text == "exact" else int(text)


def _compute(args: argparse.Namespace) -> int:
    from twin_core.mixing.runs import mixing_of_frames

    try:
        table = mixing_of_frames(
            args.frames,
            args.out,
            indices=args.indices,
            grid=args.grid,
            lo=_triple(args.lo, "--lo") if args.lo else None,
            hi=_triple(args.hi, "--hi") if args.hi else None,
            periodic=args.periodic,
            tracer=args.tracer,
            sm_pairs=_sm_pairs(args.sm_pairs),
            start_s=args.start,
        )
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    print(table.to_string(float_format=lambda v: f"{v:.3f}"))
    print(f"wrote {args.out}/indices.csv, progress.csv, t95.csv, mixing_indices.png")
    return 0


def _blender(args: argparse.Namespace) -> int:
    from schemas.dem_scene import load_scene
    from twin_core.scenes.blender import blender_mixing

    cfg = load_scene(args.scene)
    try:
        table = blender_mixing(
            cfg, args.runs, args.out, indices=args.indices, sm_pairs=_sm_pairs(args.sm_pairs)
        )
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    print(table.to_string(float_format=lambda v: f"{v:.2f}"))
    cols = [f"{r:g} rpm" for r in sorted(cfg.rpms)]
    if len(cols) > 1:
        falls = table[cols].dropna().apply(lambda row: bool(np.all(np.diff(row) < 0)), axis=1)
        print(f"T95 falls as blade speed rises for {int(falls.sum())} of {len(falls)} indices")
    print(f"wrote {args.out}/t95_by_speed.csv, t95_by_speed.png and per-speed CSV/PNG")
    return 0
