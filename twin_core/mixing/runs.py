"""The mixing of a DEM run as a library call (``twin mixing compute``).

:func:`mixing_of_frames`: a frames directory into tables and figures, that is
:func:`analyze_run` (in memory) and :func:`write_run` (tables and figures). The same across the
blade speeds of a blender scene's runs (``twin mixing blender``) needs the scene's geometry, so
it is ``twin_core.scenes.blender.blender_mixing`` (scenes build on this package).

From the frames and their metadata (``domain_lo``, ``domain_hi``, ``periodic`` as written by
``twin dem run``) it drops particles that left the domain (counted), takes the domain from the
options, the metadata or, failing both, the particle extents (said in the result), wraps
periodic axes, colours the bed if asked (:func:`~twin_core.mixing.species.split_species`),
builds the sampling grid, computes the indices and T95 fits
(:func:`~twin_core.mixing.analysis.analyze`) and, when the frames carry velocities, the
velocity fields and homogeneity indices (:mod:`twin_core.mixing.fields`).
:func:`write_run` writes the tables and the figures (drawn by :mod:`twin_core.mixing.plots`).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from twin_core.dem.frames import Frame
from twin_core.mixing.analysis import MixingAnalysis, analyze
from twin_core.mixing.fields import VelocityFields, homogeneity_series, velocity_fields
from twin_core.mixing.grid import CylindricalGrid, GridSpec, parse_bins
from twin_core.mixing.series import MixingConfig, common_subset, frame_velocities
from twin_core.mixing.species import split_species

__all__ = ["RunOptions", "RunResult", "analyze_run", "mixing_of_frames", "write_run"]


@dataclass
class RunOptions:
    """What to compute (see :func:`analyze_run`).

    ``bins``: grid text of :func:`~twin_core.mixing.grid.parse_bins` (``"1x8x8"``,
    ``"cartesian:8x8x52"``, ``"cylindrical:8x4x10,axis=z"``); ``lo``, ``hi``: the domain (m),
    default the frames' metadata, else the particle extents; ``periodic``: axes such as ``"x"``
    (default the metadata). ``slab``: ``(axis, centre, thickness)`` samples one 2-D slice.
    ``split``: colour the bed at the first frame along ``x``, ``y``, ``z``, ``r`` or ``radius``
    (equal volumes with ``weight="volume"``, equal numbers otherwise); the tracer is then the
    lower side. ``start``: first frame time used; ``time_from_start`` measures times from it
    (from the first frame without ``start``).
    ``homogeneity``: particle attributes whose homogeneity index is followed.
    """

    indices: str | Sequence[str] = "all"
    bins: str = "1x8x8"
    lo: tuple[float, float, float] | None = None
    hi: tuple[float, float, float] | None = None
    periodic: str | None = None
    tracer: int | None = None
    weight: str = "number"
    mapping: str = "point"
    min_fill: float = 0.5
    slab: tuple[str, float, float] | None = None
    split: str | None = None
    sm_pairs: int | None = 20_000
    ah_axis: int = 2
    start: float | None = None
    time_from_start: bool = False
    homogeneity: tuple[str, ...] = ()
    fit_onset: bool = True


@dataclass
class RunResult:
    """The analysis of one run and what was done to its frames to get there."""

    analysis: MixingAnalysis
    grid: GridSpec | CylindricalGrid
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    domain_source: str
    periodic: tuple[bool, bool, bool]
    n_frames: int
    n_particles: int
    dropped_particles: int
    velocity: VelocityFields | None = None
    homogeneity: pd.DataFrame | None = None
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict:
        table = self.analysis.t95_table()
        return {
            "frames": self.n_frames,
            "particles": self.n_particles,
            "dropped_particles": self.dropped_particles,
            "domain_lo": list(self.lo),
            "domain_hi": list(self.hi),
            "domain_source": self.domain_source,
            "periodic": list(self.periodic),
            "grid": _grid_text(self.grid),
            "weight": self.analysis.indices.attrs.get("weight", "number"),
            "mapping": self.analysis.indices.attrs.get("mapping", "point"),
            "t95_s": _finite(table["T95_s"]),
            "t95_onset_s": _finite(table["T95_onset_s"]),
            "onset_s": _finite(table["t0_s"]),
            "notes": self.notes,
        }


def _finite(col: pd.Series) -> dict:
    return {k: (float(v) if np.isfinite(v) else None) for k, v in col.items()}


def _grid_text(grid: GridSpec | CylindricalGrid) -> str:
    shape = "x".join(map(str, grid.shape))
    if isinstance(grid, CylindricalGrid):
        return f"cylindrical:{shape},axis={'xyz'[grid.axis]},radial={grid.radial}"
    return f"cartesian:{shape}"


def particle_extents(frames: Iterable) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corner of the space the particles (with their radii) ever occupied."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for f in frames:
        pos, r = np.asarray(f.positions, float), np.asarray(f.radii, float)[:, None]
        if len(pos):
            lo = np.minimum(lo, (pos - r).min(axis=0))
            hi = np.maximum(hi, (pos + r).max(axis=0))
    if not np.all(np.isfinite(lo)):
        raise ValueError("the frames hold no particles")
    return lo, hi


def _domain(frames, meta: dict, options: RunOptions) -> tuple[np.ndarray, np.ndarray, str]:
    if options.lo is not None and options.hi is not None:
        return np.asarray(options.lo, float), np.asarray(options.hi, float), "options"
    if meta.get("domain_lo") is not None and meta.get("domain_hi") is not None:
        return np.asarray(meta["domain_lo"], float), np.asarray(meta["domain_hi"], float), "meta"
    lo, hi = particle_extents(frames)
    return lo, hi, "particle extents"


def _periodic(meta: dict, options: RunOptions) -> tuple[bool, bool, bool]:
    if options.periodic is not None:
        text = options.periodic.lower()
        bad = set(text) - set("xyz, ")
        if bad:
            raise ValueError(f"periodic must name axes among x, y, z, got {options.periodic!r}")
        return tuple(ax in text for ax in "xyz")  # type: ignore[return-value]
    return tuple(bool(p) for p in meta.get("periodic", (False, False, False)))  # type: ignore[return-value]


def _colour_by_id(first, options: RunOptions):
    """The species of each particle id from the split of the first frame: (sorted ids, types)."""
    colour = split_species(first.positions, first.radii, options.split, options.weight)
    ids = np.asarray(first.ids)
    order = np.argsort(ids)
    return ids[order], colour[order]


def _prepared(frames: list, lo, hi, periodic, options: RunOptions) -> list[Frame]:
    """Frames with periodic axes wrapped into the domain, times shifted and species split."""
    colour = _colour_by_id(frames[0], options) if options.split is not None else None
    t0 = 0.0
    if options.time_from_start:
        t0 = frames[0].t if options.start is None else options.start
    out = []
    for f in frames:
        pos = np.array(f.positions, float)
        for ax in np.flatnonzero(periodic):
            pos[:, ax] = lo[ax] + np.mod(pos[:, ax] - lo[ax], hi[ax] - lo[ax])
        ids = np.asarray(f.ids)
        kinds = f.types if colour is None else colour[1][np.searchsorted(colour[0], ids)]
        out.append(Frame(float(f.t - t0), ids, kinds, np.asarray(f.radii), pos, frame_velocities(f)))  # fmt: skip
    return out


def analyze_run(
    frames: Iterable, meta: dict | None = None, options: RunOptions | None = None
) -> RunResult:
    """Mixing indices, T95 and delayed-onset fits, velocity fields and homogeneity of a run.

    Particles missing from some frame (they left the domain) are dropped from all frames and
    counted; the domain comes from ``options``, else ``meta``, else the particle extents (noted
    in :attr:`RunResult.notes`)."""
    meta = meta or {}
    options = options or RunOptions()
    frames = [f for f in frames if options.start is None or f.t >= options.start - 1e-9]
    if len(frames) < 2:
        raise ValueError(f"need at least 2 frames, got {len(frames)}")
    frames, dropped = common_subset(frames)
    notes = []
    if dropped:
        notes.append(f"{dropped} particles left the domain and were dropped from every frame")
    lo, hi, source = _domain(frames, meta, options)
    if source == "particle extents":
        notes.append("the frames carry no domain: it was derived from the particle extents")
    periodic = _periodic(meta, options)
    frames = _prepared(frames, lo, hi, periodic, options)
    grid = parse_bins(options.bins, lo, hi, min_fill=options.min_fill)
    if options.slab is not None:
        grid = grid.slab(*options.slab)
    box = tuple(float(h - l) if p else np.inf for l, h, p in zip(lo, hi, periodic))
    cfg = MixingConfig(
        grid=grid, box=box, tracer=options.tracer, weight=options.weight,
        mapping=options.mapping, sm_pairs=options.sm_pairs, ah_axis=options.ah_axis,
    )  # fmt: skip
    an = analyze(frames, cfg, options.indices, fit_onset=options.fit_onset)
    moving = any(np.any(frame_velocities(f)) for f in frames)
    kwargs = {"weight": options.weight, "mapping": options.mapping, "box": box}
    return RunResult(
        analysis=an,
        grid=grid,
        lo=tuple(map(float, lo)),
        hi=tuple(map(float, hi)),
        domain_source=source,
        periodic=periodic,
        n_frames=len(frames),
        n_particles=len(frames[0].ids),
        dropped_particles=dropped,
        velocity=velocity_fields(frames, grid, **kwargs) if moving else None,
        homogeneity=(
            homogeneity_series(frames, options.homogeneity, grid, **kwargs)
            if options.homogeneity
            else None
        ),
        notes=notes,
    )


def write_run(result: RunResult, out: str | Path) -> list[Path]:
    """Write the run's tables and figures to ``out``: ``indices.csv``, ``progress.csv``,
    ``t95.csv``, ``summary.json``, ``mixing_indices.png`` and, when computed,
    ``velocity_mean.csv``, ``velocity_frames.csv``, ``velocity.png``, ``homogeneity.csv``,
    ``homogeneity.png``. Returns the paths written."""
    from twin_core.mixing import plots

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    an = result.analysis
    written = [out / "indices.csv", out / "progress.csv", out / "t95.csv", out / "summary.json"]
    an.indices.to_csv(written[0], index=False)
    an.progress.to_csv(written[1], index=False)
    an.t95_table().to_csv(written[2])
    written[3].write_text(json.dumps(result.summary(), indent=2))
    written.append(plots.plot_analysis(an, out / "mixing_indices.png"))
    if result.velocity is not None:
        written.append(out / "velocity_mean.csv")
        result.velocity.mean_table(result.grid).to_csv(written[-1], index=False)
        written.append(out / "velocity_frames.csv")
        result.velocity.frame_table().to_csv(written[-1], index=False)
        fig = plots.velocity_figure(result.velocity, result.grid)
        written.append(plots.save_figure(fig, out / "velocity.png"))
    if result.homogeneity is not None:
        written.append(out / "homogeneity.csv")
        result.homogeneity.to_csv(written[-1], index=False)
        fig = plots.homogeneity_figure(result.homogeneity)
        written.append(plots.save_figure(fig, out / "homogeneity.png"))
    return written


def mixing_of_frames(
    frames_dir: str | Path, out_dir: str | Path, options: RunOptions | None = None
) -> RunResult:
    """:func:`analyze_run` of a frames directory (its metadata included) and
    :func:`write_run` into ``out_dir``."""
    from twin_core.dem.frames import FrameReader

    reader = FrameReader(frames_dir)
    result = analyze_run(reader, reader.meta, options)
    write_run(result, out_dir)
    return result
