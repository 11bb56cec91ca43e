"""`twin mixing compute|blender`: mixing indices, T95 fits, fields and figures of DEM runs."""

from __future__ import annotations

import argparse
import logging

log = logging.getLogger("twin.mixing")


def _triple(text: str | None, name: str) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise SystemExit(f"{name} must be three comma-separated numbers, got {text!r}") from None
    if len(vals) != 3:
        raise SystemExit(f"{name} must be three comma-separated numbers, got {text!r}")
    return vals  # type: ignore[return-value]


def _slab(text: str | None) -> tuple[str, float, float] | None:
    if text is None:
        return None
    try:
        axis, centre, thickness = text.split(":")
        return axis, float(centre), float(thickness)
    except ValueError:
        raise SystemExit(f"--slice must look like AXIS:CENTRE:THICKNESS, got {text!r}") from None


def _sm_pairs(text: str) -> int | None:
    if text == "exact":
        return None
    try:
        return int(text)
    except ValueError:
        raise SystemExit(f"--sm-pairs must be an integer or 'exact', got {text!r}") from None


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--indices", default="all", help="'all' or a comma list, e.g. LI,RSD,SI,SSI")
    p.add_argument("--sm-pairs", default="20000", help="Siiria pairs sampled, or 'exact'")
    p.add_argument("--weight", choices=("number", "volume"), default="number",
                   help="number fractions (seed) or volume fractions, cells weighted by volume")  # fmt: skip
    p.add_argument("--mapping", choices=("point", "fractional"), default="point",
                   help="a particle in its centre's cell, or split over cells by volume")  # fmt: skip
    p.add_argument("--min-fill", type=float, default=0.5,
                   help="drop cells holding less than this share of their volume's amount")  # fmt: skip
    p.add_argument("--out", required=True, help="output directory")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("mixing", help="mixing indices and T95 mixing times (seed chapter 4)")
    msub = p.add_subparsers(dest="mixing_command", metavar="ACTION")
    c = msub.add_parser("compute", help="indices of every frame, T95 fits, fields, CSV, figures")
    c.add_argument("frames", help="frames directory written by `twin dem run`")
    c.add_argument("--bins", "--grid", dest="bins", default="1x8x8",
                   help="cartesian:NXxNYxNZ (or NXxNYxNZ) or cylindrical:NTxNRxNA[,axis=z]")  # fmt: skip
    c.add_argument("--slice", help="sample one slab AXIS:CENTRE:THICKNESS (m), e.g. z:0.05:0.004")
    c.add_argument("--lo", help="domain lower corner x,y,z in m (default: meta or extents)")
    c.add_argument("--hi", help="domain upper corner x,y,z in m (default: meta or extents)")
    c.add_argument("--periodic", default=None, help="periodic axes, e.g. 'x' (default: meta)")
    c.add_argument("--tracer", type=int, default=None, help="type id of the tracer particles")
    c.add_argument("--split", choices=("x", "y", "z", "r", "radius"),
                   help="colour the first frame's bed in two halves along this (by --weight)")  # fmt: skip
    c.add_argument("--homogeneity", default="", help="attributes, e.g. radius,speed")
    c.add_argument("--start", type=float, default=None, help="first frame time used (s)")
    _common(c)
    c.set_defaults(func=_compute)
    b = msub.add_parser("blender", help="T95 table and figure across blade speeds from "
                        "`twin dem run` blender runs (seed Table 4.2 / Fig. 4.7)")  # fmt: skip
    b.add_argument("scene", help="the blender scene YAML the runs were made with")
    b.add_argument("--runs", required=True, help="the --out directory of `twin dem run`")
    _common(b)
    b.set_defaults(func=_blender)


def _compute(args: argparse.Namespace) -> int:
    from twin_core.mixing.runs import RunOptions, mixing_of_frames

    options = RunOptions(
        indices=args.indices, bins=args.bins, lo=_triple(args.lo, "--lo"),
        hi=_triple(args.hi, "--hi"), periodic=args.periodic, tracer=args.tracer,
        weight=args.weight, mapping=args.mapping, min_fill=args.min_fill,
        slab=_slab(args.slice), split=args.split, sm_pairs=_sm_pairs(args.sm_pairs),
        start=args.start, homogeneity=tuple(a for a in args.homogeneity.split(",") if a),
    )  # fmt: skip
    try:
        result = mixing_of_frames(args.frames, args.out, options)
    except ValueError as exc:
        raise SystemExit(f"twin mixing compute: {exc}") from None
    cols = ["T95_s", "R2", "t0_s", "T95_onset_s", "R2_onset"]
    print(result.analysis.t95_table()[cols].to_string(float_format=lambda v: f"{v:.3f}"))
    for note in result.notes:
        print(f"note: {note}")
    print(f"wrote tables and figures to {args.out}")
    return 0


def _blender(args: argparse.Namespace) -> int:
    from schemas.dem_scene import load_scene
    from twin_core.mixing.runs import RunOptions
    from twin_core.scenes.blender import blender_mixing

    cfg = load_scene(args.scene)
    options = RunOptions(
        indices=args.indices, weight=args.weight, mapping=args.mapping,
        min_fill=args.min_fill, sm_pairs=_sm_pairs(args.sm_pairs),
    )  # fmt: skip
    try:
        table = blender_mixing(cfg, args.runs, args.out, options)
    except ValueError as exc:
        raise SystemExit(f"twin mixing blender: {exc}") from None
    print(table.to_string(float_format=lambda v: f"{v:.2f}"))
    cols = [f"{r:g} rpm" for r in sorted(cfg.rpms)]
    falls = (table[cols].dropna().diff(axis=1).iloc[:, 1:] < 0).all(axis=1)
    print(f"T95 falls as blade speed rises for {int(falls.sum())} of {len(falls)} indices")
    print(f"wrote {args.out}/t95_by_speed.csv, t95_by_speed.png and rpm_*/ tables and figures")
    return 0
