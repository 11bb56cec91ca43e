"""A DEM scene of the seed run end to end (``twin dem run``), as one library call: :func:`run_scene`.

The scene's runs (a blender section per blade speed; a drawdown test; a feeder run-out and its
refills; a silo discharge: ``twin_core.scenes.<scene>.run``) into ``out_dir``, then what the
scene's ``output`` asks for: the geometry as STL, snapshots of the first and last frames and the
scene's curves (``twin_core.scenes.plots``), the frames as VTK (``particles.pvd``), and
``summary.json`` with the scalar results of each run.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["run_scene"]

log = logging.getLogger(__name__)

Run = tuple[str, dict, Path]


def _runs(
    cfg: Any, out: Path, resume: bool, progress: bool, pair_chunks: int | None
) -> tuple[Any, list[Run]]:
    """(geometry of the first run, [(name, results, run directory)]) of the scene."""
    from twin_core.scenes import blender, drawdown, feeder, silo

    kw = {"resume": resume, "progress": progress, "pair_chunks": pair_chunks}
    if cfg.scene == "blender":
        runs = []
        for rpm in cfg.rpms:
            d = out / f"rpm_{rpm:g}"
            runs.append((d.name, blender.run(cfg, rpm, d, **kw), d))
        return blender.build_geometry(cfg, cfg.rpms[0]), runs
    if cfg.scene == "drawdown":
        return drawdown.build_geometry(cfg), [("drawdown", drawdown.run(cfg, out, **kw), out)]
    if cfg.scene == "feeder":
        runs = [("runout", feeder.run(cfg, out / "runout", **kw), out / "runout")]
        for level in cfg.refill_levels:
            d = out / f"refill_{round(100 * level)}"
            runs.append((d.name, feeder.run(cfg, d, refill_level=level, **kw), d))
        return feeder.build_geometry(cfg), runs
    return silo.build_geometry(cfg), [("silo", silo.run(cfg, out, **kw), out)]


def _frame_outputs(cfg: Any, runs: list[Run]) -> None:
    """Snapshots of the first and last frames; the frames as VTK."""
    from twin_core.dem.frames import FrameReader
    from twin_core.dem.vtk import write_particles_vtp, write_pvd
    from twin_core.scenes import plots

    for _name, _res, d in runs:
        fr = FrameReader(d / "frames")
        if cfg.output.figures and len(fr):
            plots.snapshot(d / "snapshot_start.png", fr[0], cfg.name)
            plots.snapshot(d / "snapshot_end.png", fr[-1], cfg.name)
        if cfg.output.vtk and len(fr):
            (d / "vtk").mkdir(exist_ok=True)
            entries = []
            for i, f in enumerate(fr):
                write_particles_vtp(d / "vtk" / f"particles_{i:05d}.vtp", f)
                entries.append((f.t, f"particles_{i:05d}.vtp"))
            write_pvd(d / "vtk" / "particles.pvd", entries)


def _blender_figures(runs: list[Run], out: Path) -> None:
    from twin_core.scenes import plots

    series = []
    for name, _res, d in runs:
        z = np.load(d / "mixing.npz")
        series.append((z["t"], z["lacey"], name))
    plots.curves(
        out / "mixing_lacey.png", series, "mixing time (s)", "Lacey index (1x8x8)", "blender mixing"
    )
    hist = []
    for name, _res, d in runs:
        tr = np.load(d / "transit_times.npz")["transit_s"]
        if len(tr):
            h, e = np.histogram(tr, bins=30, density=True)
            hist.append((0.5 * (e[1:] + e[:-1]), h, name))
    if hist:
        plots.curves(
            out / "transit_rtd.png",
            hist,
            "transit time over the period (s)",
            "E(t) (1/s)",
            "section particle RTD",
        )


def _feeder_figures(runs: list[Run], out: Path) -> None:
    from twin_core.feeder.feed_factor import feed_factor
    from twin_core.scenes import plots

    plots.curves(
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
        plots.xy_fit(
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
        plots.curves(
            out / "outlet_fraction_type2.png",
            [(r["flow_t_s"], r["outlet_fraction_type2"], n) for n, r in refills],
            "t (s)",
            "fraction of type 2 at the outlet",
            "refill particles at the outlet",
        )


def _drawdown_figures(runs: list[Run]) -> None:
    from twin_core.scenes import plots

    _, res, d = runs[0]
    series = [(res["flow_t_s"], res["flow_kg_s"], "opening")]
    plots.curves(d / "flow_rate.png", series, "t (s)", "flow rate (kg/s)", "drawdown flow")
    plots.heap_profiles(d / "heap_profiles.png", res)


def _silo_figures(runs: list[Run]) -> None:
    from twin_core.scenes import plots

    _, res, d = runs[0]
    series = [(res["flow_t_s"], res["flow_kg_s"], "orifice")]
    beverloo = (res["beverloo_rate_kg_s"], "Beverloo")
    plots.curves(
        d / "flow_rate.png", series, "t (s)", "discharge (kg/s)", "silo discharge", hline=beverloo
    )


def _scene_figures(cfg: Any, runs: list[Run], out: Path) -> None:
    """The scene's curves: Lacey index and transit RTD (blender), flow rate and heap profiles
    (drawdown), flow rate, feed-factor fit and refill tracer (feeder), discharge against
    Beverloo (silo)."""
    if cfg.scene == "blender":
        _blender_figures(runs, out)
    elif cfg.scene == "feeder":
        _feeder_figures(runs, out)
    elif cfg.scene == "drawdown":
        _drawdown_figures(runs)
    else:
        _silo_figures(runs)


def _scalars(res: dict) -> dict:
    return {k: v for k, v in res.items() if isinstance(v, int | float | str | bool) or v is None}


def run_scene(
    cfg: Any,
    out_dir: str | Path,
    *,
    resume: bool = False,
    progress: bool = True,
    pair_chunks: int | None = None,
) -> dict[str, dict]:
    """Run a scene (``schemas.dem_scene`` config) into ``out_dir`` with its outputs (module
    docstring); returns the scalar results by run (also in ``summary.json``). ``resume``:
    continue each run from its last checkpoint, its pair scatter in the saved chunks or, with
    ``pair_chunks``, re-chunked (to use more threads than the run was started with). The engine's kernels are compiled (or loaded
    from numba's cache) first, phase by phase, each phase logged before it starts."""
    from twin_core.dem.stl import write_stl
    from twin_core.dem.warmup import compile_kernels

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    compile_kernels(report=log.info)
    geo0, runs = _runs(cfg, out, resume, progress, pair_chunks)
    if cfg.output.stl:
        for m in geo0.all_meshes():
            write_stl(out / f"geometry_{m.name}.stl", m.vertices, m.triangles, name=m.name)
    _frame_outputs(cfg, runs)
    if cfg.output.figures:
        _scene_figures(cfg, runs, out)
    summary = {name: _scalars(res) for name, res, _ in runs}
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary
