"""The mixing of DEM runs as library calls (``twin mixing compute`` and ``twin mixing blender``).

:func:`mixing_of_frames`: the mixing indices of every frame of a run on a grid, their T95 fits
(``twin_core.mixing.analysis.analyze``), written as CSV with a figure. :func:`blender_mixing`:
the same for each blade speed of a blender scene's runs (``twin dem run``), the first
``settle_s`` (filling) left out and x wrapped into the periodic section, and the T95 table across
blade speeds (seed Table 4.2 / Fig. 4.7: T95 falls as the blade speed rises).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

__all__ = ["blender_mixing", "mixing_of_frames"]

log = logging.getLogger(__name__)


def mixing_of_frames(
    frames_dir: str | Path,
    out_dir: str | Path,
    *,
    indices: str = "all",
    grid: str = "1x8x8",
    lo: Sequence[float] | None = None,
    hi: Sequence[float] | None = None,
    periodic: str | None = None,
    tracer: int | None = None,
    sm_pairs: int | None = 20000,
    start_s: float | None = None,
) -> pd.DataFrame:
    """Indices, progress and T95 of a frames directory into ``out_dir`` (``indices.csv``,
    ``progress.csv``, ``t95.csv``, ``mixing_indices.png``, ``summary.json``); returns the T95
    table. The grid box and periodic axes default to the frames' meta; ``periodic`` names axes
    (e.g. ``"x"``); ``sm_pairs`` None: the exact Siiria index."""
    import json

    from twin_core.dem.frames import FrameReader
    from twin_core.mixing import GridSpec, MixingConfig
    from twin_core.mixing.analysis import analyze
    from twin_core.mixing.plots import plot_analysis

    reader = FrameReader(frames_dir)
    meta = reader.meta
    lo = lo if lo is not None else meta.get("domain_lo")
    hi = hi if hi is not None else meta.get("domain_hi")
    if lo is None or hi is None:
        raise ValueError("the frames meta has no domain_lo/domain_hi: give lo and hi")
    per = (
        [ax in periodic.lower() for ax in "xyz"]
        if periodic is not None
        else list(meta.get("periodic", [False, False, False]))
    )
    box = tuple(float(h - low) if p else np.inf for low, h, p in zip(lo, hi, per))
    cfg = MixingConfig(grid=GridSpec.parse(grid, lo, hi), box=box, tracer=tracer, sm_pairs=sm_pairs)
    frames = [f for f in reader if start_s is None or f.t >= start_s]
    an = analyze(frames, cfg, indices)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    an.indices.to_csv(out / "indices.csv", index=False)
    an.progress.to_csv(out / "progress.csv", index=False)
    table = an.t95_table()
    table.to_csv(out / "t95.csv")
    plot_analysis(an, out / "mixing_indices.png")
    summary = {"frames": len(frames), "grid": grid, "t95_s": table["T95_s"].to_dict()}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return table


def _blender_run(cfg: Any, rpm: float, runs_dir: Path, indices: str, sm_pairs: int | None) -> Any:
    """The mixing analysis of one blade speed's run: tracer = type 1 (left of the plate), x
    periodic, the Ashton index along y (where the two types start segregated)."""
    from twin_core.dem.frames import FrameReader
    from twin_core.mixing import GridSpec, MixingConfig
    from twin_core.mixing.analysis import analyze
    from twin_core.scenes.blender import build_geometry

    run_dir = runs_dir / f"rpm_{rpm:g}" / "frames"
    if not run_dir.exists():
        raise ValueError(f"no frames for {rpm:g} rpm at {run_dir}")
    info = build_geometry(cfg, rpm).info
    lo, hi = info["domain_lo"], info["domain_hi"]
    mcfg = MixingConfig(
        grid=GridSpec(tuple(lo), tuple(hi), (1, 8, 8)),
        box=(hi[0] - lo[0], np.inf, np.inf),
        tracer=1,
        ah_axis=1,
        sm_pairs=sm_pairs,
    )
    frames = [f for f in FrameReader(run_dir) if f.t >= cfg.settle_s - 1e-9]
    for f in frames:  # wrap x into the periodic section; mixing time from the end of filling
        f.positions[:, 0] = lo[0] + np.mod(f.positions[:, 0] - lo[0], hi[0] - lo[0])
        f.t = f.t - cfg.settle_s
    return analyze(frames, mcfg, indices, allow_lost=True)


def blender_mixing(
    cfg: Any,
    runs_dir: str | Path,
    out_dir: str | Path,
    *,
    indices: str = "all",
    sm_pairs: int | None = 20000,
) -> pd.DataFrame:
    """The T95 table across the blade speeds of a blender scene (``cfg``: its
    ``schemas.dem_scene`` config) from the runs of ``twin dem run`` in ``runs_dir``, written to
    ``out_dir`` (per speed ``indices_<rpm>rpm.csv``, ``t95_<rpm>rpm.csv``,
    ``mixing_indices_<rpm>rpm.png``; ``t95_by_speed.csv`` and ``.png``); returns the table."""
    from twin_core.mixing.analysis import t95_by_speed
    from twin_core.mixing.plots import plot_analysis, plot_t95_by_speed

    if cfg.scene != "blender":
        raise ValueError(f"scene must be a blender scene, got {cfg.scene!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    analyses = {}
    for rpm in cfg.rpms:
        an = analyses[rpm] = _blender_run(cfg, rpm, Path(runs_dir), indices, sm_pairs)
        tag = f"{rpm:g}rpm"
        an.indices.to_csv(out / f"indices_{tag}.csv", index=False)
        an.t95_table().to_csv(out / f"t95_{tag}.csv")
        plot_analysis(an, out / f"mixing_indices_{tag}.png")
        dropped = an.indices.attrs.get("dropped_particles", 0)
        log.info("%g rpm: %d particles dropped (left the domain)", rpm, dropped)
    table = t95_by_speed(analyses)
    table.to_csv(out / "t95_by_speed.csv")
    plot_t95_by_speed(table, out / "t95_by_speed.png")
    return table
