"""``twin dem run SCENE.yaml [--out DIR] [--resume] [--threads N]``: run a DEM scene of the seed
(blender section, drawdown test, feeder, silo) from its config file and write results, fields,
frames, STL geometry and PNG figures."""

from __future__ import annotations

import argparse
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
    r.add_argument("--threads", type=int, default=None, help="numba threads (default: all)")
    r.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    r.set_defaults(func=cmd_run)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def _summary(res: dict) -> dict:
    return {k: v for k, v in res.items() if isinstance(v, int | float | str | bool) or v is None}


def cmd_run(args: argparse.Namespace) -> int:
    from schemas.dem_scene import load_scene
    from twin_core.dem.frames import FrameReader
    from twin_core.dem.stl import write_stl
    from twin_core.dem.vtk import write_particles_vtp, write_pvd
    from twin_core.scenes import blender, drawdown, feeder, figures, silo

    try:
        cfg = load_scene(args.scene)
    except ValueError as exc:
        log.error("invalid scene %s: %s", args.scene, exc)
        return 2
    if args.threads is not None:
        import numba

        if args.threads < 1:
            log.error("--threads must be >= 1, got %s", args.threads)
            return 2
        numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    out = args.out or Path("out") / "dem" / cfg.name
    out.mkdir(parents=True, exist_ok=True)
    progress = not args.no_progress
    runs: list[tuple[str, dict, Path]] = []

    if cfg.scene == "blender":
        geo0 = blender.build_geometry(cfg, cfg.rpms[0])
        for rpm in cfg.rpms:
            d = out / f"rpm_{rpm:g}"
            runs.append(
                (f"rpm_{rpm:g}", blender.run(cfg, rpm, d, resume=args.resume, progress=progress), d)
            )
    elif cfg.scene == "drawdown":
        geo0 = drawdown.build_geometry(cfg)
        runs.append(
            ("drawdown", drawdown.run(cfg, out, resume=args.resume, progress=progress), out)
        )
    elif cfg.scene == "feeder":
        geo0 = feeder.build_geometry(cfg)
        runs.append(
            (
                "runout",
                feeder.run(cfg, out / "runout", resume=args.resume, progress=progress),
                out / "runout",
            )
        )
        for level in cfg.refill_levels:
            d = out / f"refill_{round(100 * level)}"
            runs.append(
                (
                    d.name,
                    feeder.run(cfg, d, refill_level=level, resume=args.resume, progress=progress),
                    d,
                )
            )
    else:
        geo0 = silo.build_geometry(cfg)
        runs.append(("silo", silo.run(cfg, out, resume=args.resume, progress=progress), out))

    if cfg.output.stl:
        for m in geo0.all_meshes():
            write_stl(out / f"geometry_{m.name}.stl", m.vertices, m.triangles, name=m.name)
    for _name, _res, d in runs:
        fr = FrameReader(d / "frames")
        if cfg.output.figures and len(fr):
            figures.snapshot(d / "snapshot_start.png", fr[0], cfg.name)
            figures.snapshot(d / "snapshot_end.png", fr[-1], cfg.name)
        if cfg.output.vtk and len(fr):
            entries = []
            (d / "vtk").mkdir(exist_ok=True)
            for i, f in enumerate(fr):
                write_particles_vtp(d / "vtk" / f"particles_{i:05d}.vtp", f)
                entries.append((f.t, f"particles_{i:05d}.vtp"))
            write_pvd(d / "vtk" / "particles.pvd", entries)
    if cfg.output.figures:
        _scene_figures(cfg, runs, out)
    summary = {name: _summary(res) for name, res, _ in runs}
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=str))
    print(json.dumps(summary, indent=1, default=str))
    return 0


def _scene_figures(cfg, runs, out: Path) -> None:
    import numpy as np

    from twin_core.feeder.feed_factor import feed_factor
    from twin_core.scenes import figures

    if cfg.scene == "blender":
        series = []
        for name, _res, d in runs:
            z = np.load(d / "mixing.npz")
            series.append((z["t"], z["lacey"], name))
        figures.curves(
            out / "mixing_lacey.png",
            series,
            "mixing time (s)",
            "Lacey index (1x8x8)",
            "blender mixing",
        )
        hist = []
        for name, _res, d in runs:
            tr = np.load(d / "transit_times.npz")["transit_s"]
            if len(tr):
                h, e = np.histogram(tr, bins=30, density=True)
                hist.append((0.5 * (e[1:] + e[:-1]), h, name))
        if hist:
            figures.curves(
                out / "transit_rtd.png",
                hist,
                "transit time over the period (s)",
                "E(t) (1/s)",
                "section particle RTD",
            )
    elif cfg.scene == "drawdown":
        _, res, d = runs[0]
        figures.curves(
            d / "flow_rate.png",
            [(res["flow_t_s"], res["flow_kg_s"], "opening")],
            "t (s)",
            "flow rate (kg/s)",
            "drawdown flow",
        )
        figures.heap_profiles(d / "heap_profiles.png", res)
    elif cfg.scene == "feeder":
        figures.curves(
            out / "flow_rate.png",
            [(r["flow_t_s"], r["flow_kg_s"], n) for n, r, _ in runs],
            "t (s)",
            "outlet flow (kg/s)",
            "feeder flow rate",
        )
        _, res, d = runs[0]
        ffc = res["feed_factor"]
        fit = ffc.get("fit", {})
        if "ff_max" in fit and len(ffc["w_active_kg"]):
            w = np.asarray(ffc["w_active_kg"])
            wf = np.linspace(0, w.max(), 100)
            figures.xy_fit(
                d / "feed_factor.png",
                w,
                ffc["ff_g_rev"],
                wf,
                feed_factor(wf, fit["ff_max"], fit["ff_min"], fit["beta"]),
                "active feeder weight (kg)",
                "feed factor (g/rev)",
                f"Eq. (2) fit, R^2 = {fit['r2']:.3f}",
            )
        refills = [(n, r) for n, r, _ in runs if r.get("refill_level") is not None]
        if refills:
            figures.curves(
                out / "outlet_fraction_type2.png",
                [(r["flow_t_s"], r["outlet_fraction_type2"], n) for n, r in refills],
                "t (s)",
                "fraction of type 2 at the outlet",
                "refill particles at the outlet",
            )
    else:
        _, res, d = runs[0]
        figures.curves(
            d / "flow_rate.png",
            [(res["flow_t_s"], res["flow_kg_s"], "orifice")],
            "t (s)",
            "discharge (kg/s)",
            "silo discharge",
            hline=(res["beverloo_rate_kg_s"], "Beverloo"),
        )
