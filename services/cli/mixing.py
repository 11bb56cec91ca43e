"""`twin mixing compute`: mixing indices, T95 fits and figures from a DEM frames directory."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

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


def _compute(args: argparse.Namespace) -> int:
    from twin_core.dem.frames import FrameReader
    from twin_core.mixing import GridSpec, MixingConfig
    from twin_core.mixing.analysis import analyze, plot_analysis

    reader = FrameReader(args.frames)
    meta = reader.meta
    lo = _triple(args.lo, "--lo") if args.lo else meta.get("domain_lo")
    hi = _triple(args.hi, "--hi") if args.hi else meta.get("domain_hi")
    if lo is None or hi is None:
        raise SystemExit("the frames meta has no domain_lo/domain_hi: pass --lo and --hi")
    if args.periodic is not None:
        periodic = [ax in args.periodic.lower() for ax in "xyz"]
    else:
        periodic = list(meta.get("periodic", [False, False, False]))
    box = tuple(float(h - l) if per else np.inf for l, h, per in zip(lo, hi, periodic))
    grid = GridSpec.parse(args.grid, lo, hi)
    sm_pairs = None if args.sm_pairs == "exact" else int(args.sm_pairs)
    cfg = MixingConfig(grid=grid, box=box, tracer=args.tracer, sm_pairs=sm_pairs)
    frames = [f for f in reader if args.start is None or f.t >= args.start]
    log.info("%d frames, %d particles", len(frames), frames[0].n if frames else 0)
    an = analyze(frames, cfg, args.indices)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    an.indices.to_csv(out / "indices.csv", index=False)
    an.progress.to_csv(out / "progress.csv", index=False)
    table = an.t95_table()
    table.to_csv(out / "t95.csv")
    plot_analysis(an, out / "mixing_indices.png")
    (out / "summary.json").write_text(
        json.dumps(
            {"frames": len(frames), "grid": args.grid, "t95_s": table["T95_s"].to_dict()}, indent=2
        )
    )
    print(table.to_string(float_format=lambda v: f"{v:.3f}"))
    print(f"wrote {out}/indices.csv, progress.csv, t95.csv, mixing_indices.png")
    return 0


def _blender(args: argparse.Namespace) -> int:
    from schemas.dem_scene import load_scene
    from twin_core.dem.frames import FrameReader
    from twin_core.mixing import GridSpec, MixingConfig
    from twin_core.mixing.analysis import analyze, plot_analysis, plot_t95_by_speed, t95_by_speed
    from twin_core.scenes.blender import build_geometry

    cfg = load_scene(args.scene)
    if cfg.scene != "blender":
        raise SystemExit(f"scene must be a blender scene, got {cfg.scene!r}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sm_pairs = None if args.sm_pairs == "exact" else int(args.sm_pairs)
    analyses = {}
    for rpm in cfg.rpms:
        run_dir = Path(args.runs) / f"rpm_{rpm:g}" / "frames"
        if not run_dir.exists():
            raise SystemExit(f"no frames for {rpm:g} rpm at {run_dir}")
        info = build_geometry(cfg, rpm).info
        lo, hi = info["domain_lo"], info["domain_hi"]
        grid = GridSpec(tuple(lo), tuple(hi), (1, 8, 8))
        # tracer = type 1 (left of the plate); x is periodic; AH along y, the direction in
        # which the two types start segregated
        mcfg = MixingConfig(
            grid=grid, box=(hi[0] - lo[0], np.inf, np.inf), tracer=1, ah_axis=1, sm_pairs=sm_pairs
        )
        frames = [f for f in FrameReader(run_dir) if f.t >= cfg.settle_s - 1e-9]
        for f in frames:  # wrap x into the periodic section
            f.positions[:, 0] = lo[0] + np.mod(f.positions[:, 0] - lo[0], hi[0] - lo[0])
            f.t = f.t - cfg.settle_s
        an = analyze(frames, mcfg, args.indices, allow_lost=True)
        analyses[rpm] = an
        tag = f"{rpm:g}rpm"
        an.indices.to_csv(out / f"indices_{tag}.csv", index=False)
        an.t95_table().to_csv(out / f"t95_{tag}.csv")
        plot_analysis(an, out / f"mixing_indices_{tag}.png")
        log.info(
            "%g rpm: %d frames, %d particles dropped (left the domain)",
            rpm,
            len(frames),
            an.indices.attrs.get("dropped_particles", 0),
        )
    table = t95_by_speed(analyses)
    table.to_csv(out / "t95_by_speed.csv")
    plot_t95_by_speed(table, out / "t95_by_speed.png")
    print(table.to_string(float_format=lambda v: f"{v:.2f}"))
    speeds = sorted(cfg.rpms)
    if len(speeds) > 1:
        cols = [f"{r:g} rpm" for r in speeds]
        falls = (
            table[cols]
            .dropna()
            .apply(lambda row: bool(np.all(np.diff(row.to_numpy()) < 0)), axis=1)
        )
        print(f"T95 falls as blade speed rises for {int(falls.sum())} of {len(falls)} indices")
    print(f"wrote {out}/t95_by_speed.csv, t95_by_speed.png and per-speed CSV/PNG")
    return 0
