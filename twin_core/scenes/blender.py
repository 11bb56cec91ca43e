"""Periodic section of a convective continuous blender (seed 4.2, 5.2.1, Figs. 4.2, 5.2, 5.3).

Protocol: two particle types are placed left (y < 0, type 1) and right (y > 0, type 2) of a
vertical separating plate through the axis; after ``settle_s`` the plate is removed and the
shaft with its pitched blades turns at the set rpm for ``mix_s``. Recorded:

* frames every ``frame_interval_s`` (mixing indices, seed chapter 4);
* Lacey's index on the seed's 1 x 8 x 8 grid (cells with less than half the mean count dropped,
  seed 4.4.1) for each frame, via :mod:`twin_core.mixing`;
* time-averaged velocity, solid fraction, occupancy and neighbour-cell crossings on a
  10 x 20 x 20 grid after ``steady_after_s`` (seed 5.2.3; the compartment-model ``.npz``);
* the net axial mass flow through the mid plane x = L/2 and the transit times of particles
  across the periodic length (the section's particle RTD, seed Fig. 5.8).

:func:`blender_mixing` (``twin mixing blender``): the mixing analysis of each blade speed's run
(``twin_core.mixing``), the first ``settle_s`` (filling) left out and x wrapped into the
periodic section, and the T95 table across blade speeds (seed Table 4.2 / Fig. 4.7: T95 falls as
the blade speed rises).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from schemas.dem_scene import BlenderScene
from twin_core.dem.frames import FrameReader
from twin_core.dem.sensors import GridFieldSensor, PeriodicTransitSensor, PlaneFlowSensor
from twin_core.scenes import common
from twin_core.scenes.geometry import SceneGeometry, blender_section, rectangle

__all__ = ["blender_mixing", "build", "build_geometry", "lacey_series", "mixing_rate", "run"]

log = logging.getLogger(__name__)


def build_geometry(cfg: BlenderScene, rpm: float) -> SceneGeometry:
    """Blender section meshes plus the separating plate (removed at ``settle_s``)."""
    g = cfg.geometry
    geo = blender_section(
        length=g.length,
        width=g.width,
        height=g.height,
        shaft_radius=g.shaft_radius,
        blade_length=g.blade_length,
        blade_width=g.blade_width,
        blade_thickness=g.blade_thickness,
        tip_clearance=g.tip_clearance,
        pitch_deg=g.pitch_deg,
        blades_per_station=g.blades_per_station,
        n_stations=g.n_stations,
        rpm=rpm,
    )
    plate = rectangle([0.0, 0.0, 0.0], [g.length, 0.0, 0.0], [0.0, 0.0, g.height], name="plate")
    geo.removable.append((plate, cfg.settle_s))
    geo.info["motion_start_s"] = cfg.settle_s
    return geo


def _fill(cfg: BlenderScene, geo: SceneGeometry, rng: np.random.Generator) -> list[np.ndarray]:
    r = cfg.radius
    R = geo.info["radius"] - 1.02 * r
    zc = geo.info["axis_point"][2]
    top = geo.info["domain_hi"][2] - r

    def inside(p: np.ndarray, side: int) -> np.ndarray:
        y, z = p[:, 1], p[:, 2]
        in_u = np.where(z >= zc, np.abs(y) <= R, y**2 + (z - zc) ** 2 <= R**2) & (z <= top)
        return in_u & (side * y > 1.1 * r)

    lo = np.asarray(geo.info["domain_lo"], float)
    hi = np.asarray(geo.info["domain_hi"], float)
    rotor = [geo.rotating[0][0]]
    out = []
    for side in (-1, 1):
        # periodic x: keep a radius from x = L so images do not overlap
        pos = common.lattice_positions(
            cfg.n_per_type,
            lo,
            hi - [r, 0, 0],
            r,
            lambda p, s=side: inside(p, s),
            rng,
            avoid=rotor,
        )
        out.append(pos)
    return out


def build(cfg: BlenderScene, rpm: float) -> tuple[Any, SceneGeometry]:
    """Engine simulation of the section at ``rpm`` with both particle types placed."""
    geo = build_geometry(cfg, rpm)
    sim, pid, _ = common.make_simulation(
        cfg, geo, periodic=(True, False, False), pad=2 * cfg.radius
    )
    rng = np.random.default_rng(cfg.seed)
    for type_id, pos in zip((1, 2), _fill(cfg, geo, rng)):
        sim.add_particles(pos, np.full(len(pos), cfg.radius), pid, type_id)
    return sim, geo


def _grid_edges(cfg: BlenderScene, geo: SceneGeometry) -> list[np.ndarray]:
    lo, hi = geo.info["domain_lo"], geo.info["domain_hi"]
    return [np.linspace(lo[k], hi[k], cfg.grid[k] + 1) for k in range(3)]


def run(
    cfg: BlenderScene,
    rpm: float,
    run_dir: Path,
    *,
    resume: bool = False,
    progress: bool = True,
    pair_chunks: int | None = None,
) -> dict:
    """Run one blade speed into ``run_dir`` and return its results (also in results.json);
    ``pair_chunks`` re-chunks a resumed run's pair scatter (``common.load_checkpoint``)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    geo = build_geometry(cfg, rpm)
    L = cfg.geometry.length
    push = geo.info["blade_push_sign_x"]
    loaded = common.load_checkpoint(run_dir, pair_chunks) if resume else None
    if loaded is None:
        sim, geo = build(cfg, rpm)
        state = common.RunState()
        edges = _grid_edges(cfg, geo)
        state.sensors = {
            "fields": GridFieldSensor(
                *edges,
                cfg.material.density,
                periodic=(True, False, False),
                t_start=cfg.settle_s + cfg.steady_after_s,
            ),
            "axial": PlaneFlowSensor(
                [L / 2, 0, 0], [1, 0, 0], cfg.material.density, periodic_lengths=[L, 0, 0]
            ),
            "transit": PeriodicTransitSensor(
                0, L, direction=int(push) if push != 0 else 1, t_start=cfg.settle_s
            ),
        }
        state.next_frame_t = cfg.settle_s
        frames_resume = False
    else:
        sim, state = loaded
        frames_resume = True
    fi = cfg.output.frame_interval_s or cfg.frame_interval_s
    frames = common.open_frames(
        run_dir, cfg, sim, resume=frames_resume,
        scene="blender", rpm=rpm, t_mix_start=cfg.settle_s, length=L,
    )  # fmt: skip

    def on_sample(s: Any, st: common.RunState) -> None:
        if s.t >= cfg.settle_s - 1e-9:
            for sensor in st.sensors.values():
                sensor.update(s)

    common.run_segments(
        sim,
        cfg.settle_s + cfg.mix_s,
        run_dir,
        state,
        sensor_interval_s=cfg.sensor_interval_s,
        on_sample=on_sample,
        frames=frames,
        frame_interval_s=fi,
        checkpoint_interval_s=cfg.output.checkpoint_interval_s,
        progress=progress,
        label=f"blender {rpm:g} rpm",
    )
    frames.close()
    return analyze(cfg, rpm, run_dir, state, geo, n_particles=len(sim.ids), steps=state.steps)


def lacey_series(
    reader: FrameReader, geo: SceneGeometry, *, shape=(1, 8, 8), min_fill: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """Lacey's index (seed 4.3.1.1, corrected form of the reading notes) of types 1/2 on a
    ``shape`` grid over the section, cells below ``min_fill`` of the mean count excluded
    (seed 4.4.1); returns (t, M)."""
    from twin_core.mixing import GridSpec, cell_counts, occupied_cells
    from twin_core.mixing.variance_indices import lacey

    grid = GridSpec(
        tuple(geo.info["domain_lo"]), tuple(geo.info["domain_hi"]), tuple(shape), min_fill
    )
    ts, ms = [], []
    L = geo.info["domain_hi"][0] - geo.info["domain_lo"][0]
    for f in reader:
        pos = f.positions.copy()
        pos[:, 0] = geo.info["domain_lo"][0] + np.mod(pos[:, 0] - geo.info["domain_lo"][0], L)
        counts = cell_counts(grid, pos, f.types, (1, 2))
        keep = occupied_cells(grid, counts)
        a, n = counts[keep, 0], counts[keep].sum(axis=1)
        ts.append(f.t)
        ms.append(lacey(a, n) if keep.sum() > 1 else np.nan)
    return np.asarray(ts), np.asarray(ms)


def mixing_rate(t: np.ndarray, m: np.ndarray) -> dict:
    """Fit M(t) = M_inf - (M_inf - M_0) exp(-k t) (first-order mixing kinetics, the form
    behind the seed's T95 fits, Eq. 29) by least squares; returns k (1/s), M_inf, M_0, R^2 and
    T95 = ln(20) / k (time to 95 % of the change)."""
    from scipy.optimize import curve_fit

    ok = np.isfinite(m)
    t, m = t[ok], m[ok]
    if len(t) < 4:
        return {"k": float("nan"), "m_inf": float("nan"), "m0": float("nan"), "r2": float("nan")}

    def f(x, minf, m0, k):
        return minf - (minf - m0) * np.exp(-k * x)

    try:
        p, _ = curve_fit(
            f,
            t,
            m,
            p0=(m[-1], m[0], 1.0 / max(t[-1], 1e-3)),
            bounds=([-1, -1, 0], [2, 2, 1e3]),
            maxfev=20000,
        )
    except RuntimeError:
        return {"k": float("nan"), "m_inf": float("nan"), "m0": float("nan"), "r2": float("nan")}
    res = m - f(t, *p)
    sst = float(((m - m.mean()) ** 2).sum())
    return {
        "k": float(p[2]),
        "m_inf": float(p[0]),
        "m0": float(p[1]),
        "r2": 1 - float(res @ res) / sst if sst > 0 else float("nan"),
        "t95": float(np.log(20) / p[2]) if p[2] > 0 else float("inf"),
    }


def analyze(
    cfg: BlenderScene,
    rpm: float,
    run_dir: Path,
    state: common.RunState,
    geo: SceneGeometry,
    *,
    n_particles: int,
    steps: int,
) -> dict:
    """Results of a blender run: fields .npz, mixing curve, axial flow, transit times."""
    fields = state.sensors["fields"]
    axial: PlaneFlowSensor = state.sensors["axial"]
    transit: PeriodicTransitSensor = state.sensors["transit"]
    fields_path = fields.save_npz(run_dir / "fields.npz") if fields.n_samples else None
    if fields_path is not None:
        try:
            add_transitions(run_dir)
        except ValueError as exc:  # too few frames: the model falls back to the crossings
            log.warning("no particle transitions in %s: %s", fields_path, exc)
    t0 = cfg.settle_s
    t_end = cfg.settle_s + cfg.mix_s
    t_steady = t0 + cfg.steady_after_s
    ev = axial.events_
    sel = ev["t"] >= t_steady
    span = max(t_end - t_steady, 1e-12)
    net_flow = float(np.sum(ev["mass"][sel] * ev["n"][sel]) / span) if span > 0 else float("nan")
    reader = FrameReader(run_dir / "frames")
    t, m = lacey_series(reader, geo)
    t_rel = t - t0
    rate = mixing_rate(t_rel, m)
    tr = transit.transit_times_
    np.savez_compressed(run_dir / "mixing.npz", t=t_rel, lacey=m)
    np.savez_compressed(run_dir / "transit_times.npz", transit_s=tr)
    results = {
        "scene": "blender",
        "rpm": rpm,
        "pitch_deg": cfg.geometry.pitch_deg,
        "n_particles": n_particles,
        "blade_push_sign_x": geo.info["blade_push_sign_x"],
        "net_axial_flow_kg_s": net_flow,
        "net_axial_flow_sign": float(np.sign(net_flow)),
        "lacey_final": float(m[-1]) if len(m) else float("nan"),
        "mixing_fit": rate,
        "transit_count": int(len(tr)),
        "transit_mean_s": float(np.mean(tr)) if len(tr) else float("nan"),
        "transit_median_s": float(np.median(tr)) if len(tr) else float("nan"),
        "fields_npz": str(fields_path.name) if fields_path else None,
        "wall_s": state.wall_s,
        "steps": steps,
        "sim_s": t_end,
    }
    common.write_json(run_dir / "results.json", results)
    return results


TRANSITION_LAG_S = 0.2


def add_transitions(run_dir: str | Path, lag_s: float = TRANSITION_LAG_S) -> Any:
    """Count the particles' cell-to-cell transitions at ``lag_s`` over the run's frames
    (:func:`twin_core.compartment.transitions.count_transitions`, the frames' interval times
    the nearest whole number) and add them to ``run_dir/fields.npz``; returns them.

    0.2 s: on the seed-size runs the Markov model of the cells is closest to the particles'
    transits at 0.2 s of the lags 0.1-0.5 s (docs/compartment.md); longer lags drop the
    fastest particles, whose jumps reach a whole period."""
    from dataclasses import replace

    from twin_core.compartment.fields import load_fields, save_fields
    from twin_core.compartment.transitions import count_transitions, frames_arrays

    run_dir = Path(run_dir)
    fields = load_fields(run_dir / "fields.npz")
    t, pos, vel = frames_arrays(FrameReader(run_dir / "frames"))
    lag = max(1, int(round(lag_s / float(np.median(np.diff(t))))))
    if t.size <= lag:
        raise ValueError(
            f"{run_dir}: need > {lag} frames for transitions at {lag_s} s, got {t.size}"
        )
    axial = int(np.flatnonzero(fields.periodic)[0])
    tr = count_transitions(t, pos, vel, fields.edges, axial_axis=axial, lag_frames=lag)
    save_fields(run_dir / "fields.npz", replace(fields, transitions=tr))
    return tr


def blender_mixing(
    cfg: Any, runs_dir: str | Path, out_dir: str | Path, options: Any = None
) -> pd.DataFrame:
    """The T95 table across the blade speeds of a blender scene (``cfg``: its
    ``schemas.dem_scene`` config) from the runs of ``twin dem run`` in ``runs_dir``: for each
    speed :func:`twin_core.mixing.runs.mixing_of_frames` into ``out_dir/rpm_<speed>/``, on the
    section's domain, x periodic, tracer = type 1 (left of the plate), AH along y (where the two
    types start segregated), times from the end of filling (``settle_s``); then
    ``t95_by_speed.csv`` and ``.png``. ``options`` (a ``twin_core.mixing.runs.RunOptions``)
    gives the rest: indices, weighting, mapping, minimum fill, Siiria pairs. Returns the
    table."""
    from dataclasses import replace

    from twin_core.mixing.analysis import t95_by_speed
    from twin_core.mixing.plots import plot_t95_by_speed
    from twin_core.mixing.runs import RunOptions, mixing_of_frames

    if cfg.scene != "blender":
        raise ValueError(f"scene must be a blender scene, got {cfg.scene!r}")
    out = Path(out_dir)
    analyses = {}
    for rpm in cfg.rpms:
        run_dir = Path(runs_dir) / f"rpm_{rpm:g}" / "frames"
        if not run_dir.exists():
            raise ValueError(f"no frames for {rpm:g} rpm at {run_dir}")
        info = build_geometry(cfg, rpm).info
        speed = replace(
            options or RunOptions(), bins="1x8x8", lo=tuple(info["domain_lo"]),
            hi=tuple(info["domain_hi"]), periodic="x", tracer=1, ah_axis=1, start=cfg.settle_s,
            time_from_start=True,
        )  # fmt: skip
        result = mixing_of_frames(run_dir, out / f"rpm_{rpm:g}", speed)
        analyses[rpm] = result.analysis
        log.info("%g rpm: %d particles dropped (left the domain)", rpm, result.dropped_particles)
    table = t95_by_speed(analyses)
    table.to_csv(out / "t95_by_speed.csv")
    plot_t95_by_speed(table, out / "t95_by_speed.png")
    return table
