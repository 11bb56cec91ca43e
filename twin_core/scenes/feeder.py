"""Loss-in-weight twin-screw feeder run-out and refills (seed 3.2.3, 3.3.2.1, 3.3.2.2).

Protocol: the hopper is filled (type 1) on a lattice and settles for ``settle_s`` with the screws
and the impeller at rest; then the screws turn at ``screw_rpm`` and the bridge-breaking
impeller at ``impeller_rpm`` until ``settle_s + run_s``. Particles leaving the outlet barrel are
counted at the outlet plane and removed by a sink just beyond it. With a refill level the run
adds ``refill_particles`` of type 2 on top of the bed when the hopper mass first falls to that
fraction of the initial fill (seed Figs. 3.8-3.11).

Extracted (seed 3.3.2.1): outlet flow rate vs time by type; feeder weight vs time and its
active part (minus the stagnant mass left at the end of the run-out); feed factor
FF = flow / screw speed (g/rev, seed Eq. 1) against the active weight and the fit of seed Eq. (2)
with :func:`twin_core.feeder.feed_factor.fit_feed_factor`; the validity checks (largest
particle overlap relative to the radius below 4 %, mass balance of particles in = in feeder +
discharged).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from schemas.dem_scene import FeederScene
from twin_core.dem.sensors import BoxFlowSensor, ContactSensor, PlaneFlowSensor
from twin_core.scenes import common
from twin_core.scenes.geometry import SceneGeometry, feeder, hopper_half_width

__all__ = ["build", "build_geometry", "feed_factor_curve", "run"]


def build_geometry(cfg: FeederScene) -> SceneGeometry:
    g = cfg.geometry
    geo = feeder(
        hopper_x=g.hopper_x,
        hopper_y=g.hopper_y,
        height=g.height,
        screw_radius=g.screw_radius,
        shaft_radius=g.shaft_radius,
        screw_pitch=g.screw_pitch,
        clearance=g.clearance,
        outlet_length=g.outlet_length,
        wedge_bottom_z=g.wedge_bottom_z,
        wedge_top_z=g.wedge_top_z,
        screw_rpm=cfg.screw_rpm,
        impeller_rpm=cfg.impeller_rpm,
        impeller_z=g.impeller_z,
    )
    geo.info["motion_start_s"] = cfg.settle_s
    lo = list(geo.info["domain_lo"])
    hi = list(geo.info["domain_hi"])
    lo[2] -= 0.03  # room below the outlet for the falling stream
    hi[0] += 0.03
    geo.info["domain_lo"], geo.info["domain_hi"] = lo, hi
    return geo


def _inside_hopper(
    p: np.ndarray, geo: SceneGeometry, r: float, z_min: float = -np.inf
) -> np.ndarray:
    info = geo.info
    c = info["trough_radius"]
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    in_x = (x > 1.1 * r) & (x < info["hopper_x"] - 1.1 * r)
    below = (np.minimum(np.hypot(y + c, z), np.hypot(y - c, z)) < c - 1.1 * r) & (z < 0)
    above = (z >= 0) & (np.abs(y) < hopper_half_width(z, info) - 1.2 * r)
    return in_x & (below | above) & (z < info["z_top"] - 1.1 * r) & (z > z_min)


def _fill_positions(
    cfg: FeederScene, geo: SceneGeometry, n: int, rng: np.random.Generator, z_min: float = -np.inf
) -> np.ndarray:
    lo = np.asarray(geo.info["domain_lo"], float)
    hi = np.asarray(geo.info["domain_hi"], float)
    hi[0] = geo.info["hopper_x"]
    avoid = [m for m, *_ in geo.rotating]
    return common.lattice_positions(
        n,
        lo,
        hi,
        cfg.radius,
        lambda p: _inside_hopper(p, geo, cfg.radius, z_min),
        rng,
        avoid=avoid,
    )


def build(cfg: FeederScene) -> tuple[Any, SceneGeometry]:
    geo = build_geometry(cfg)
    sim, pid, _ = common.make_simulation(cfg, geo, pad=2 * cfg.radius)
    pos = _fill_positions(cfg, geo, cfg.n_particles, np.random.default_rng(cfg.seed))
    sim.add_particles(pos, np.full(len(pos), cfg.radius), pid, 1)
    hi = geo.info["domain_hi"]
    lo = geo.info["domain_lo"]
    x_out = geo.info["outlet_x"]
    sim.add_outlet(
        [x_out + 3 * cfg.radius, lo[1] - 1, lo[2] - 1], [hi[0] + 1, hi[1] + 1, hi[2] + 1]
    )
    sim.add_outlet(
        [geo.info["hopper_x"], lo[1] - 1, lo[2] - 1],
        [hi[0] + 1, hi[1] + 1, -geo.info["trough_radius"] - 3 * cfg.radius],
    )
    return sim, geo


def _refill(sim: Any, cfg: FeederScene, geo: SceneGeometry, rng: np.random.Generator) -> int:
    n = cfg.refill_particles or cfg.n_particles
    inside = sim.pos[:, 0] < geo.info["hopper_x"]
    top = float(sim.pos[inside, 2].max()) if inside.any() else 0.0
    try:
        pos = _fill_positions(cfg, geo, n, rng, z_min=top + 2 * cfg.radius)
    except ValueError:
        # fewer sites than asked: take what fits above the bed
        for k in range(10):
            try:
                pos = _fill_positions(
                    cfg, geo, int(n * 0.8 ** (k + 1)), rng, z_min=top + 2 * cfg.radius
                )
                break
            except ValueError:
                continue
        else:
            return 0
    sim.add_particles(pos, cfg.radius, 0, 2)
    return len(pos)


def feed_factor_curve(
    t_flow: np.ndarray,
    flow_kg_s: np.ndarray,
    t_w: np.ndarray,
    w_kg: np.ndarray,
    screw_rpm: float,
    t_start: float,
) -> dict:
    """Feed factor FF = flow / screw speed (g/rev, seed Eq. 1) against the active feeder weight
    W (kg) at the same times, from the first bin after ``t_start`` where the flow reaches half
    its maximum; fit of seed Eq. (2) FF = FF_max - (FF_max - FF_min) exp(-beta W) with
    :func:`twin_core.feeder.feed_factor.fit_feed_factor` (SciPy ``curve_fit``, as the seed)."""
    from twin_core.feeder.feed_factor import fit_feed_factor

    rev_s = screw_rpm / 60.0
    ff = flow_kg_s * 1e3 / rev_s
    sel = t_flow >= t_start
    if sel.any() and flow_kg_s[sel].max() > 0:
        first = np.nonzero(sel & (flow_kg_s >= 0.5 * flow_kg_s[sel].max()))[0][0]
        sel &= np.arange(len(t_flow)) >= first
    w = np.interp(t_flow, t_w, w_kg)
    sel &= w > 0
    out = {"t_s": t_flow[sel], "ff_g_rev": ff[sel], "w_active_kg": w[sel]}
    try:
        fit = fit_feed_factor(w[sel], ff[sel])
        out["fit"] = fit.as_dict()
    except (ValueError, RuntimeError) as exc:
        out["fit"] = {"error": str(exc)}
    return out


def run(
    cfg: FeederScene,
    run_dir: Path,
    *,
    refill_level: float | None = None,
    resume: bool = False,
    progress: bool = True,
    pair_chunks: int | None = None,
) -> dict:
    """Run the feeder (optionally with one refill at ``refill_level``) into ``run_dir``;
    ``pair_chunks`` re-chunks a resumed run's pair scatter (``common.load_checkpoint``)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    geo = build_geometry(cfg)
    x_out = geo.info["outlet_x"]
    dens = cfg.material.density
    loaded = common.load_checkpoint(run_dir, pair_chunks) if resume else None
    if loaded is None:
        sim, geo = build(cfg)
        state = common.RunState()
        hi = geo.info["domain_hi"]
        lo = geo.info["domain_lo"]
        state.sensors = {
            "outlet": PlaneFlowSensor([x_out, 0, 0], [1, 0, 0], dens),
            "feeder": BoxFlowSensor(
                [-1, lo[1] - 1, -geo.info["trough_radius"] - 2 * cfg.radius],
                [x_out, hi[1] + 1, 10.0],
                dens,
            ),
            "contacts": ContactSensor(),
        }
        state.flags["rng"] = np.random.default_rng(cfg.seed + 7)
        state.flags["n_in"] = int(sim.n_particles)
        state.flags["ids_in"] = set(int(i) for i in sim.ids)
    else:
        sim, state = loaded
    frames = common.open_frames(
        run_dir, cfg, sim, resume=loaded is not None, scene="feeder", refill_level=refill_level
    )
    fi = cfg.output.frame_interval_s or cfg.frame_interval_s

    def on_sample(s: Any, st: common.RunState) -> None:
        st.sensors["outlet"].update(s)
        st.sensors["feeder"].update(s)
        if s.t >= st.flags.get("next_contact_t", 0.0) - 1e-9:
            st.sensors["contacts"].update(s)
            st.flags["next_contact_t"] = s.t + fi
        _, _, m = st.sensors["feeder"].content_series()
        if "w0" not in st.flags and s.t >= cfg.settle_s - 1e-9:
            st.flags["w0"] = float(m[-1])
        if (
            refill_level is not None
            and "w0" in st.flags
            and "refill_t" not in st.flags
            and m[-1] <= refill_level * st.flags["w0"]
        ):
            k = _refill(s, cfg, geo, st.flags["rng"])
            st.flags["refill_t"] = s.t
            st.flags["refill_n"] = k
            st.flags["n_in"] += k
            st.flags["ids_in"] |= set(int(i) for i in s.ids[s.type_id == 2])

    t_end = cfg.settle_s + cfg.run_s
    common.run_segments(
        sim,
        t_end,
        run_dir,
        state,
        sensor_interval_s=cfg.sensor_interval_s,
        on_sample=on_sample,
        frames=frames,
        frame_interval_s=fi,
        checkpoint_interval_s=cfg.output.checkpoint_interval_s,
        progress=progress,
        label="feeder" if refill_level is None else f"feeder refill {refill_level:g}",
    )
    frames.close()
    return analyze(cfg, sim, state, geo, run_dir, refill_level)


def analyze(
    cfg: FeederScene,
    sim: Any,
    state: common.RunState,
    geo: SceneGeometry,
    run_dir: Path,
    refill_level: float | None,
) -> dict:
    outlet: PlaneFlowSensor = state.sensors["outlet"]
    box: BoxFlowSensor = state.sensors["feeder"]
    t_end = cfg.settle_s + cfg.run_s
    tb, fr = outlet.flow(cfg.flow_bin_s, 0.0, t_end, types=[1, 2])
    tw, _, w = box.content_series()
    stagnant = float(w[-1])
    active = np.clip(w - stagnant, 0, None)
    ffc = feed_factor_curve(tb, fr[:, -1], tw, active, cfg.screw_rpm, cfg.settle_s)
    ev = outlet.events_
    crossed = set(int(i) for i in ev["id"][ev["n"] > 0])
    present = set(int(i) for i in sim.ids)
    ids_in = state.flags["ids_in"]
    unexplained = sorted(ids_in - present - crossed)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac1 = np.where(fr[:, -1] > 0, fr[:, 0] / fr[:, -1], np.nan)
        frac2 = np.where(fr[:, -1] > 0, fr[:, 1] / fr[:, -1], np.nan)
    contacts: ContactSensor = state.sensors["contacts"]
    res = {
        "scene": "feeder",
        "refill_level": refill_level,
        "refill_t_s": state.flags.get("refill_t"),
        "refill_particles": state.flags.get("refill_n", 0),
        "n_particles_in": state.flags["n_in"],
        "n_particles_end": int(sim.n_particles),
        "initial_mass_kg": state.flags.get("w0"),
        "stagnant_mass_kg": stagnant,
        "flow_t_s": tb,
        "flow_kg_s": fr[:, -1],
        "flow_type1_kg_s": fr[:, 0],
        "flow_type2_kg_s": fr[:, 1],
        "outlet_fraction_type1": frac1,
        "outlet_fraction_type2": frac2,
        "weight_t_s": tw,
        "weight_kg": w,
        "active_weight_kg": active,
        "feed_factor": ffc,
        "checks": {
            "max_overlap_rel_radius": float(max(contacts.max_overlap_, default=0.0)),
            "overlap_below_4pct": bool(max(contacts.max_overlap_, default=0.0) < 0.04),
            "discharged_particles": len(crossed),
            "unexplained_losses": len(unexplained),
            "mass_balance_ok": len(unexplained) == 0,
        },
        "wall_s": state.wall_s,
        "steps": state.steps,
        "sim_s": t_end,
    }
    common.write_json(run_dir / "results.json", res)
    return res
