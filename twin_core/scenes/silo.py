"""Flat-bottomed silo discharge and Beverloo's law.

Beverloo, Leniger & van de Velde (1961), Chem. Eng. Sci. 15, 260:

    W = C rho_b sqrt(g) (D0 - k d)^2.5

(W mass flow rate, rho_b the bulk density of the packed bed, D0 the orifice diameter, d the
particle diameter). C and k are empirical: the literature puts C at about 0.55-0.65 and k at
1.3-2.9 for spheres (Nedderman 1992, "Statics and kinematics of granular materials", ch. 10);
the defaults C = 0.58, k = 1.5 are Beverloo's and Nedderman's central values for
free-flowing near-spherical grains.

Protocol: the silo is filled on a lattice (or poured: inserted at random in its top quarter at
a constant rate over ``pour_s``) and settles for ``settle_s`` with the orifice plugged; then the
plug is removed. The side wall is a triangulated cylinder or the engine's primitive cylinder
(``wall``). With ``recycle=True`` every particle that has fallen
``3 d`` below the orifice is taken out and put back on top of the bed (constant head, as in
the "recirculating silo" of DEM studies), so a small silo discharges at a steady rate for as
long as wanted. The rate is the slope of the cumulative mass through the orifice plane over the
last 70 % of the discharge window, or over ``fit_window_s``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from schemas.dem_scene import SiloScene
from twin_core.dem.insertion import CylinderRegion, ParticleFactory
from twin_core.dem.sensors import PlaneFlowSensor
from twin_core.scenes import common
from twin_core.scenes.geometry import SceneGeometry, flat_silo

__all__ = ["beverloo_rate", "build", "build_geometry", "run"]

G = 9.81


def beverloo_rate(
    rho_b: float, d0: float, d: float, c: float = 0.58, k: float = 1.5, g: float = G
) -> float:
    """Beverloo's discharge rate W = C rho_b sqrt(g) (D0 - k d)^2.5 (kg/s); 0 if D0 <= k d."""
    if rho_b <= 0 or d0 <= 0 or d <= 0:
        raise ValueError(f"rho_b, d0 and d must be > 0, got {rho_b}, {d0}, {d}")
    return float(c * rho_b * np.sqrt(g) * max(d0 - k * d, 0.0) ** 2.5)


def build_geometry(cfg: SiloScene) -> SceneGeometry:
    """Silo meshes (:func:`flat_silo`) with room below the orifice; with ``wall: cylinder`` the
    side-wall mesh is left out (the primitive cylinder is added by :func:`build`)."""
    geo = flat_silo(
        cfg.silo_radius, cfg.silo_height, cfg.orifice_diameter, plug_remove_s=cfg.settle_s
    )
    if cfg.wall == "cylinder":
        geo.static = [m for m in geo.static if m.name != "wall"]
    # room below the orifice for the falling jet
    geo.info["domain_lo"] = [-cfg.silo_radius, -cfg.silo_radius, -8 * cfg.radius - 0.01]
    return geo


def _fill(cfg: SiloScene, sim: Any, pid: int) -> None:
    """Lattice fill at t = 0, or a factory pouring ``n_particles`` into the top quarter of the
    silo at a constant rate over ``pour_s`` (default half of ``settle_s``)."""
    r = cfg.radius
    if cfg.fill == "poured":
        pour_s = cfg.pour_s if cfg.pour_s is not None else 0.5 * cfg.settle_s
        top = 0.25 * cfg.silo_height
        region = CylinderRegion(
            (0.0, 0.0, cfg.silo_height - top), (0.0, 0.0, 1.0), cfg.silo_radius - 1.05 * r, top
        )
        sim.add_factory(
            ParticleFactory(
                region, cfg.n_particles, rate=cfg.n_particles / pour_s, radius=r,
                material_id=pid, type_id=1, seed=cfg.seed,
            )
        )  # fmt: skip
        return
    Rin = cfg.silo_radius - 1.05 * r
    pos = common.lattice_positions(
        cfg.n_particles,
        [-cfg.silo_radius, -cfg.silo_radius, 0.0],
        [cfg.silo_radius, cfg.silo_radius, cfg.silo_height],
        r,
        lambda p: (np.hypot(p[:, 0], p[:, 1]) < Rin) & (p[:, 2] > 1.1 * r),
        np.random.default_rng(cfg.seed),
    )
    sim.add_particles(pos, np.full(len(pos), r), pid, 1)


def build(cfg: SiloScene) -> tuple[Any, SceneGeometry]:
    """Engine simulation of the silo: meshes, side wall, fill (placed or announced)."""
    geo = build_geometry(cfg)
    sim, pid, wid = common.make_simulation(cfg, geo, pad=2 * cfg.radius)
    r = cfg.radius
    if cfg.wall == "cylinder":
        sim.add_cylinder((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), cfg.silo_radius, material_id=wid,
                         inside=True, extent=(0.0, cfg.silo_height))  # fmt: skip
    _fill(cfg, sim, pid)
    if not cfg.recycle:
        lo = geo.info["domain_lo"]
        sim.add_outlet([lo[0] - 1, lo[1] - 1, lo[2] - 1], [1, 1, -4 * r])
    return sim, geo


def bulk_density(
    pos: np.ndarray, radii: np.ndarray, density: float, silo_radius: float
) -> tuple[float, float]:
    """Bulk density of the bed (centre-counting solid fraction in a core cylinder away from the
    walls, floor and free surface) and the bed height (mean of the 20 highest sphere tops)."""
    r = float(radii.max())
    inside = pos[:, 2] > 0
    top = np.sort(pos[inside, 2] + radii[inside])[-20:].mean()
    rc = silo_radius - 2 * r
    z0, z1 = 2 * r, top - 3 * r
    sel = (np.hypot(pos[:, 0], pos[:, 1]) < rc) & (pos[:, 2] > z0) & (pos[:, 2] < z1)
    vol = np.pi * rc**2 * max(z1 - z0, 1e-12)
    phi = float(np.sum(4 / 3 * np.pi * radii[sel] ** 3) / vol)
    return phi * density, float(top)


def _recycle(sim: Any, cfg: SiloScene, rng: np.random.Generator, z_base: float) -> int:
    """Move particles that fell 3 d below the orifice back on top: new spheres on lattice
    layers from ``z_base`` up, on sites at least 2.1 r from every particle present."""
    from scipy.spatial import cKDTree

    r = cfg.radius
    out = sim.pos[:, 2] < -3 * 2 * r
    k = int(out.sum())
    if k == 0:
        return 0
    sim.remove_particles(out)
    pos = sim.pos
    tree = cKDTree(pos) if len(pos) else None
    a = 2.2 * r
    Rin = cfg.silo_radius - 1.1 * r
    g = np.arange(-Rin, Rin + 1e-12, a)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    sites = np.c_[xx.ravel(), yy.ravel()]
    sites = sites[np.hypot(sites[:, 0], sites[:, 1]) < Rin]
    new: list[np.ndarray] = []
    zl = z_base
    while sum(len(b) for b in new) < k and zl < cfg.silo_height - r:
        layer = np.c_[sites, np.full(len(sites), zl)]
        if tree is not None:
            d, _ = tree.query(layer)
            layer = layer[d > 2.1 * r]
        need = k - sum(len(b) for b in new)
        new.append(layer[rng.permutation(len(layer))[:need]])
        zl += a
    placed = np.vstack(new) if new else np.zeros((0, 3))
    if len(placed):
        sim.add_particles(placed, r, 0, 1, vel=(0.0, 0.0, -0.2))
    return len(placed)


def run(
    cfg: SiloScene,
    run_dir: Path,
    *,
    resume: bool = False,
    progress: bool = True,
    pair_chunks: int | None = None,
) -> dict:
    """Run the silo discharge into ``run_dir``; returns results (also results.json);
    ``pair_chunks`` re-chunks a resumed run's pair scatter (``common.load_checkpoint``)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    loaded = common.load_checkpoint(run_dir, pair_chunks) if resume else None
    geo = build_geometry(cfg)
    if loaded is None:
        sim, geo = build(cfg)
        state = common.RunState()
        state.sensors = {
            "orifice": PlaneFlowSensor(
                [0, 0, 0],
                [0, 0, -1],
                cfg.material.density,
                radius=cfg.orifice_diameter / 2 + cfg.radius,
            )
        }
        state.flags["rng"] = np.random.default_rng(cfg.seed + 1)
    else:
        sim, state = loaded
    frames = common.open_frames(run_dir, cfg, sim, resume=loaded is not None, scene="silo")

    def on_sample(s: Any, st: common.RunState) -> None:
        st.sensors["orifice"].update(s)
        if "rho_b" not in st.flags and s.t >= cfg.settle_s - 0.5 * cfg.sensor_interval_s:
            st.flags["rho_b"], st.flags["bed_height"] = bulk_density(
                s.pos, s.radius, cfg.material.density, cfg.silo_radius
            )
        if cfg.recycle and s.t > cfg.settle_s:
            z_base = st.flags["bed_height"] + 2 * cfg.radius
            st.flags["recycled"] = st.flags.get("recycled", 0) + _recycle(
                s, cfg, st.flags["rng"], z_base
            )

    t_end = cfg.settle_s + cfg.discharge_s
    fit_a, fit_b = cfg.fit_window_s or (0.3 * cfg.discharge_s, cfg.discharge_s)
    common.run_segments(
        sim,
        t_end,
        run_dir,
        state,
        sensor_interval_s=cfg.sensor_interval_s,
        on_sample=on_sample,
        frames=frames,
        frame_interval_s=cfg.output.frame_interval_s or cfg.frame_interval_s,
        checkpoint_interval_s=cfg.output.checkpoint_interval_s,
        progress=progress,
        label="silo",
    )
    frames.close()
    flow: PlaneFlowSensor = state.sensors["orifice"]
    ev = flow.events_
    sel = (ev["t"] >= cfg.settle_s + fit_a) & (ev["t"] <= cfg.settle_s + fit_b)
    order = np.argsort(ev["t"][sel])
    tt = ev["t"][sel][order]
    cm = np.cumsum((ev["mass"] * ev["n"])[sel][order])
    if len(tt) > 2:
        slope, _ = np.polyfit(tt, cm, 1)
    else:
        slope = 0.0
    d0 = geo.info["orifice_diameter_eff"]
    rho_b = state.flags.get("rho_b", float("nan"))
    w_bev = beverloo_rate(rho_b, d0, 2 * cfg.radius, cfg.beverloo_c, cfg.beverloo_k)
    tb, fr = flow.flow(cfg.flow_bin_s, 0.0, t_end)
    res = {
        "scene": "silo",
        "n_particles": int(sim.n_particles),
        "rho_b_kg_m3": rho_b,
        "bed_height_m": state.flags.get("bed_height"),
        "orifice_diameter_eff_m": d0,
        "particle_diameter_m": 2 * cfg.radius,
        "discharge_rate_kg_s": float(slope),
        "beverloo_rate_kg_s": w_bev,
        "ratio_to_beverloo": float(slope / w_bev) if w_bev > 0 else float("nan"),
        "beverloo_c": cfg.beverloo_c,
        "beverloo_k": cfg.beverloo_k,
        "discharged_particles": int(len(ev["t"])),
        "fit_window_s": [fit_a, fit_b],
        "recycled": int(state.flags.get("recycled", 0)),
        "flow_t_s": tb,
        "flow_kg_s": fr[:, -1],
        "wall_s": state.wall_s,
        "steps": state.steps,
        "sim_s": t_end,
    }
    common.write_json(run_dir / "results.json", res)
    return res
