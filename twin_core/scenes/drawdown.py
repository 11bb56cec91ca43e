"""Drawdown calibration test (seed 3.2.2, Fig. 3.2; responses of Table 3.3).

Protocol: particles fill the upper compartment and settle for ``settle_s`` on the plate that
closes the central opening; the plate is removed and the powder drains into the lower
compartment until ``settle_s + run_s``. Responses (extracted automatically, the seed used image
analysis): mass in the lower container at the end, maximum flow rate through the opening
(``flow_bin_s`` bins), angle of repose of the upper heap and shear angle of the lower heap (each
the mean of the left and right sides, :mod:`twin_core.scenes.heaps`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from schemas.dem_scene import DrawdownScene
from twin_core.dem.sensors import BoxFlowSensor, PlaneFlowSensor, state_view
from twin_core.scenes import common
from twin_core.scenes.geometry import SceneGeometry, drawdown_box
from twin_core.scenes.heaps import fit_slope_angle, surface_profile

__all__ = ["build", "build_geometry", "responses", "run"]


def build_geometry(cfg: DrawdownScene) -> SceneGeometry:
    g = cfg.geometry
    return drawdown_box(g.size_x, g.size_y, g.size_z, g.opening_width, plate_remove_s=cfg.settle_s)


def build(cfg: DrawdownScene) -> tuple[Any, SceneGeometry]:
    geo = build_geometry(cfg)
    sim, pid, _ = common.make_simulation(cfg, geo, pad=2 * cfg.radius)
    r = cfg.radius
    zs = geo.info["shelf_z"]
    hi = np.asarray(geo.info["domain_hi"], float)
    pos = common.lattice_positions(
        cfg.n_particles,
        [0.0, 0.0, zs],
        hi,
        r,
        lambda p: p[:, 2] > zs + 1.1 * r,
        np.random.default_rng(cfg.seed),
    )
    sim.add_particles(pos, np.full(len(pos), r), pid, 1)
    return sim, geo


def responses(state: Any, geo: SceneGeometry, flow: PlaneFlowSensor, cfg: DrawdownScene) -> dict:
    """The four drawdown responses of seed Table 3.3 from the final state and the opening
    flow sensor (plus per-side angles and fit details)."""
    s = state_view(state)
    zs = geo.info["shelf_z"]
    a0, a1 = geo.info["opening"]
    X = geo.info["domain_hi"][0]
    r = float(np.max(s.radii)) if len(s.radii) else cfg.radius
    masses = 4 / 3 * np.pi * s.radii**3 * cfg.material.density
    lower = s.pos[:, 2] < zs
    t_end = cfg.settle_s + cfg.run_s
    tb, fr = flow.flow(cfg.flow_bin_s, 0.0, t_end)
    bin_w = 2 * r
    wall = 2 * r
    # upper heap: from the opening edges to the walls
    xl, hl = surface_profile(s.pos, s.radii, wall, a0, bin_w, zs)
    xr, hr = surface_profile(s.pos, s.radii, a1, X - wall, bin_w, zs)
    up_l, up_r = fit_slope_angle(xl, hl), fit_slope_angle(xr, hr)
    # lower heap: each half of the lower compartment
    xl2, hl2 = surface_profile(s.pos, s.radii, wall, X / 2, bin_w, 0.0, zs)
    xr2, hr2 = surface_profile(s.pos, s.radii, X / 2, X - wall, bin_w, 0.0, zs)
    lo_l, lo_r = fit_slope_angle(xl2, hl2), fit_slope_angle(xr2, hr2)
    return {
        "mass_lower_kg": float(masses[lower].sum()),
        "mass_total_kg": float(masses.sum()),
        "max_flow_kg_s": float(fr[:, -1].max()) if len(fr) else 0.0,
        "angle_of_repose_deg": float(np.nanmean([up_l["angle_deg"], up_r["angle_deg"]])),
        "shear_angle_deg": float(np.nanmean([lo_l["angle_deg"], lo_r["angle_deg"]])),
        "upper_fit": {"left": up_l, "right": up_r},
        "lower_fit": {"left": lo_l, "right": lo_r},
        "profiles": {
            "upper": {"x": np.r_[xl, xr], "h": np.r_[hl, hr]},
            "lower": {"x": np.r_[xl2, xr2], "h": np.r_[hl2, hr2]},
        },
        "flow_t_s": tb,
        "flow_kg_s": fr[:, -1] if len(fr) else np.zeros(0),
    }


def run(
    cfg: DrawdownScene,
    run_dir: Path,
    *,
    resume: bool = False,
    progress: bool = True,
    pair_chunks: int | None = None,
) -> dict:
    """Run the drawdown test into ``run_dir``; returns the results (also results.json);
    ``pair_chunks`` re-chunks a resumed run's pair scatter (``common.load_checkpoint``)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    geo = build_geometry(cfg)
    loaded = common.load_checkpoint(run_dir, pair_chunks) if resume else None
    if loaded is None:
        sim, geo = build(cfg)
        state = common.RunState()
        zs = geo.info["shelf_z"]
        a0, a1 = geo.info["opening"]
        hi = geo.info["domain_hi"]
        state.sensors = {
            "opening": PlaneFlowSensor(
                [0, 0, zs], [0, 0, -1], cfg.material.density, window=([a0, -1, -1], [a1, 1, 1])
            ),
            "lower": BoxFlowSensor([-1, -1, -1], [hi[0] + 1, hi[1] + 1, zs], cfg.material.density),
        }
    else:
        sim, state = loaded
    frames = common.open_frames(run_dir, cfg, sim, resume=loaded is not None, scene="drawdown")

    def on_sample(s: Any, st: common.RunState) -> None:
        for sensor in st.sensors.values():
            sensor.update(s)

    common.run_segments(
        sim,
        cfg.settle_s + cfg.run_s,
        run_dir,
        state,
        sensor_interval_s=cfg.sensor_interval_s,
        on_sample=on_sample,
        frames=frames,
        frame_interval_s=cfg.output.frame_interval_s or cfg.frame_interval_s,
        checkpoint_interval_s=cfg.output.checkpoint_interval_s,
        progress=progress,
        label="drawdown",
    )
    frames.close()
    res = responses(sim, geo, state.sensors["opening"], cfg)
    t, _, m = state.sensors["lower"].content_series()
    res.update(
        {
            "scene": "drawdown",
            "n_particles": int(sim.n_particles),
            "lost_particles": sim.removed_counts.get("lost", (0, 0.0))[0],
            "lower_mass_t_s": t,
            "lower_mass_kg": m,
            "wall_s": state.wall_s,
            "steps": state.steps,
            "sim_s": cfg.settle_s + cfg.run_s,
        }
    )
    common.write_json(run_dir / "results.json", res)
    return res
