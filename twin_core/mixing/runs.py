"""The mixing of a DEM run as a library call (``twin mixing compute``).

:func:`mixing_of_frames`: the mixing indices of every frame of a run on a grid, their T95 fits
(``twin_core.mixing.analysis.analyze``), written as CSV with a figure. The same across the blade
speeds of a blender scene's runs (``twin mixing blender``) needs the scene's geometry, so it is
``twin_core.scenes.blender.blender_mixing`` (scenes build on this package).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

__all__ = ["mixing_of_frames"]


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
