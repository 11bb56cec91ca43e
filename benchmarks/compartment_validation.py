"""Validation numbers of the compartment model against the particle-walk surrogate of DEM.

Prints the tables of docs/compartment.md:

1. section RTD of the compartment model vs the exact transit-time law of the cell-level
   particle walk (and a 40,000-particle stochastic sample of it) for several zoning
   settings; mean, variance, KS and W1 distances;
2. the same with Poisson crossing counts (a 20 s DEM-like sample) and with upwinded
   velocities instead of crossings;
3. radial mixing: RSD across coarse 10 x 6 x 6 sampling cells (seed Eq. B.1) of the walkers
   (two types split along y) vs the model's, with the binomial sampling floor; and the
   plateau left by the seed's Eq. (1) flows;
4. Eq. (10) parameters and the whole blender (8 sections).

Usage: python benchmarks/compartment_validation.py [--fields FIELDS.npz]
(the DEM fields from twin_core.scenes when given; the synthetic field otherwise).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from twin_core.compartment import (  # noqa: E402
    CompartmentModel,
    CompartmentNetwork,
    blender_model_rtd,
    blender_rtd,
    compare_rtd,
    first_passage_network,
    fit_rsd_decay,
    load_fields,
    open_section,
    rtd_moments,
    section_rsd,
    split_initial,
    synthetic_blender_fields,
    to_blender_model,
)
from twin_core.compartment.fields import mirror_axis  # noqa: E402
from twin_core.compartment.network import chain_periodic  # noqa: E402
from twin_core.compartment.radial import (  # noqa: E402
    flowing,
    grid_rsd_from_compartments,
    grid_rsd_sampled,
    section_concentrations,
)
from twin_core.compartment.surrogate import (  # noqa: E402
    coarse_index,
    grid_rsd_from_particles,
    walk_snapshots,
    walk_transit_times,
)
from twin_core.compartment.validation import window_censored  # noqa: E402


def row(name: str, r: dict) -> str:
    return (
        f"| {name} | {r['model_mean']:.3f} | {r['ref_mean']:.3f} | {100 * r['mean_rel_err']:+.1f} % "
        f"| {r['model_var']:.2f} | {r['ref_var']:.2f} | {100 * r['var_rel_err']:+.1f} % "
        f"| {r['ks']:.3f} | {100 * r['w1_rel']:.1f} % |"
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--fields", default=None)
    ap.add_argument("--particles", type=int, default=40000)
    ap.add_argument("--transit-times", default=None, help="DEM transit times (.npz 'transit_s')")
    ap.add_argument("--frames", default=None, help="DEM frame directory for the grid RSD")
    ap.add_argument("--transit-window", type=float, default=None, help="DEM recording window (s)")
    args = ap.parse_args()
    if args.fields:
        fields = load_fields(args.fields)
        noisy = None
        label = args.fields
    else:
        fields = synthetic_blender_fields(10, 20, 20).fields
        noisy = synthetic_blender_fields(10, 20, 20, counts="poisson", seed=1).fields
        label = "synthetic 10 x 20 x 20 (expected counts)"
    base = CompartmentModel().fit(fields)
    if base.mirrored_:  # net flow towards -x: work in the model's (mirrored) orientation
        fields = mirror_axis(fields, 0)
        print("fields mirrored along x (net axial flow towards -x)")
    if args.transit_times:
        with np.load(args.transit_times) as z:
            dem = np.asarray(z["transit_s"], dtype=float)
        td = np.linspace(0.0, 30.0 * base.mean_residence_time_s_, 6001)
        print("## DEM transit times")
        print("| model | mean | ref | err | var | ref | err | KS | W1/mean |")
        print("|---|---|---|---|---|---|---|---|---|")
        for name, sec in (("transit form", base.section_), ("closed-closed", base.closed_section_)):
            e = sec.impulse_response(td)
            print(row(f"{name} vs {dem.size} DEM transits", compare_rtd(td, e, samples=dem)))
            if args.transit_window:
                ew = window_censored(td, e, args.transit_window)
                name_w = f"{name}, censored to the {args.transit_window} s window"
                print(row(name_w, compare_rtd(td, ew, samples=dem)))
    if not fields.has_crossings:
        print(f"fields: {label}: no crossing counts, so no particle-walk surrogate; model:")
        print(base.summary())
        return
    # every cell its own compartment, flows made conserving (raw counts of a short DEM run
    # leave cells that are entered but never left)
    cells = CompartmentModel(resolution="cells", axial_direction="+").fit(fields).periodic_
    tau = base.mean_residence_time_s_
    t = np.linspace(0.0, 30.0 * tau, 6001)
    t0 = time.perf_counter()
    e_ref = first_passage_network(cells, 2).impulse_response(t)
    t_exact = time.perf_counter() - t0
    t0 = time.perf_counter()
    samples = walk_transit_times(cells, args.particles, seed=1)
    t_walk = time.perf_counter() - t0
    print(f"fields: {label}; {cells.n} occupied cells; V/Q = {tau:.3f} s")
    a, m_ref, v_ref = rtd_moments(t, e_ref)
    print(
        f"surrogate exact law: mean {m_ref:.3f} s, var {v_ref:.2f} s^2 ({t_exact:.1f} s); "
        f"walk of {samples.size} particles: mean {samples.mean():.3f} "
        f"+/- {samples.std() / np.sqrt(samples.size):.3f} s, var {samples.var():.2f} ({t_walk:.1f} s)"
    )
    print("\n## 1. section RTD vs the surrogate (exact law)")
    print("| model | mean | ref | err | var | ref | err | KS | W1/mean |")
    print("|---|---|---|---|---|---|---|---|---|")
    for variables in (("vx", "vy", "vz"), ("vy", "vz"), ("vx",)):
        for tol in (0.0, 0.1, 0.3):
            for mc in (1, 3):
                m = CompartmentModel(variables=variables, tol_fraction=tol, min_cells=mc).fit(
                    fields
                )
                r = compare_rtd(t, m.section_.impulse_response(t), e_ref=e_ref)
                name = f"{'+'.join(variables)}, tol {tol}, min {mc}: {m.n_compartments_} comp."
                print(row(name, r))
    cc = base.closed_section_.impulse_response(t)
    print(row("default, closed-closed cut (not the product)", compare_rtd(t, cc, e_ref=e_ref)))
    print(
        row(
            "every cell a compartment, closed-closed cut (the cut's own error)",
            compare_rtd(t, open_section(cells).impulse_response(t), e_ref=e_ref),
        )
    )
    r = compare_rtd(t, base.section_.impulse_response(t), samples=samples)
    print(row(f"default vs {samples.size} walk samples", r))

    print("\n## 2. flow sources")
    if noisy is not None:
        m = CompartmentModel().fit(noisy)
        print(
            row(
                "Poisson counts (20 s sample)",
                compare_rtd(t, m.section_.impulse_response(t), e_ref=e_ref),
            )
        )
        print(
            f"   raw imbalance of Poisson counts {m.raw_imbalance_['max_rel']:.3e} (max rel), "
            f"projection correction {m.correction_rel_:.3e}"
        )
    m = CompartmentModel(flow_source="velocity").fit(fields)
    print(row("upwinded velocities", compare_rtd(t, m.section_.impulse_response(t), e_ref=e_ref)))
    print(
        f"   seed Eq. (1) imbalance: max {base.seed_imbalance_['max_rel']:.2f}, "
        f"rms {base.seed_imbalance_['rms_rel']:.2f} (relative to mean compartment outflow)"
    )

    print("\n## 3. radial mixing (two types split along y)")
    rng = np.random.default_rng(2)
    n_part = int(round(fields.occupancy[base.mask_].sum()))
    p = cells.holdup / cells.holdup.sum()
    start = rng.choice(cells.n, size=n_part, p=p)
    y_mid = 0.5 * (fields.y_edges[0] + fields.y_edges[-1])
    is_tracer = cells.centroid[start, 1] < y_mid
    tm = np.linspace(0.0, 3.0 * tau, 61)
    snaps = walk_snapshots(cells, start, tm, seed=3)
    coarse = coarse_index(fields, base.mask_, (10, 6, 6))
    ppk = 1.0 / fields.particle_mass_kg
    r_dem = grid_rsd_from_particles(snaps, is_tracer, coarse, 360)
    c0 = split_initial(fields, base.labels_, axis=1)
    c = section_concentrations(base.periodic_, c0, tm)
    _, r_cm_s = grid_rsd_from_compartments(
        c,
        base.labels_,
        fields.holdup_kg,
        coarse,
        360,
        particles_per_kg=ppk,
        active=flowing(base.periodic_),
    )
    lab_cells = np.full(fields.shape, -1, dtype=np.int64)
    lab_cells[base.mask_] = np.arange(cells.n)
    c_cells = section_concentrations(cells, (cells.centroid[:, 1] < y_mid).astype(float), tm)
    _, r_cells_s = grid_rsd_from_compartments(
        c_cells,
        lab_cells,
        fields.holdup_kg,
        coarse,
        360,
        particles_per_kg=ppk,
        active=flowing(cells),
    )
    occ_cells = fields.occupancy
    r_cells_mc = grid_rsd_sampled(
        c_cells, lab_cells, occ_cells, coarse, 360, seed=7, active=flowing(cells)
    )
    seed = base.seed_flows_
    seed_net = CompartmentNetwork(base.holdup_kg_, seed.src, seed.dst, seed.rate)
    r_seed = section_rsd(seed_net, c0, tm)
    r_comp = section_rsd(base.periodic_, c0, tm)
    print(f"{n_part} walkers; 10 x 6 x 6 sampling cells; '+ floor': binomial sampling variance")
    print(
        "| t (s) | surrogate grid RSD | model grid RSD + floor | cell network grid RSD + floor "
        "| cell network sampled | model Eq. 2 | seed flows Eq. 2 |"
    )
    print("|---|---|---|---|---|---|---|")
    for k in range(0, tm.size, 6):
        print(
            f"| {tm[k]:.2f} | {r_dem[k]:.3f} | {r_cm_s[k]:.3f} | {r_cells_s[k]:.3f} "
            f"| {r_cells_mc[k]:.3f} "
            f"| {r_comp[k]:.3f} | {r_seed[k]:.3f} |"
        )
    late = tm > 2 * tau
    print(
        f"RMS(surrogate - model+floor) = {np.sqrt(np.mean((r_dem - r_cm_s) ** 2)):.3f}, "
        f"RMS(surrogate - cell network+floor) = {np.sqrt(np.mean((r_dem - r_cells_s) ** 2)):.3f}; "
        f"plateau t > 2 tau: surrogate {r_dem[late].mean():.3f}, model+floor "
        f"{r_cm_s[late].mean():.3f}, seed flows (Eq. 2) {r_seed[late].mean():.3f}"
    )

    if args.frames:
        from twin_core.compartment.radial import grid_rsd_from_positions, initial_from_particles
        from twin_core.dem.frames import FrameReader

        reader = FrameReader(args.frames)
        frames = list(reader)
        t_avg0 = frames[-1].t - float(np.load(args.fields)["duration_s"])
        k0 = int(np.argmin([abs(fr.t - t_avg0) for fr in frames]))
        f0 = frames[k0]
        pos0 = f0.positions.copy()
        if base.mirrored_:
            pos0[:, 0] = fields.x_edges[0] + fields.x_edges[-1] - pos0[:, 0]
        c0_dem = initial_from_particles(pos0, f0.types == 1, fields, lab_cells)
        tf = np.array([fr.t - f0.t for fr in frames[k0:]])
        tu = np.linspace(0.0, max(tf[-1], 1e-3), 41)
        c_dem_model = section_concentrations(cells, c0_dem, tu)
        r_model = np.interp(
            tf,
            tu,
            grid_rsd_sampled(
                c_dem_model, lab_cells, fields.occupancy, coarse, 360, seed=9, active=flowing(cells)
            ),
        )
        print(
            f"\n## DEM grid RSD (10 x 6 x 6, tracer = type 1) from the frame at t = {f0.t:.2f} s "
            "(start of the field averaging); cell network started from that frame"
        )
        print("| t - t0 (s) | DEM | cell network, sampled like the DEM |")
        print("|---|---|---|")
        r_d = []
        for fr, ti, rm in zip(frames[k0:], tf, r_model):
            r = grid_rsd_from_positions(fr.positions, fr.types == 1, fields)
            r_d.append(r)
            print(f"| {ti:.2f} | {r:.3f} | {rm:.3f} |")
        r_d = np.asarray(r_d)
        print(f"RMS difference {np.sqrt(np.mean((r_d - r_model) ** 2)):.3f}")

    print("\n## 4. Eq. (10) and the whole blender")
    for name, y in (
        ("model, Eq. 2", r_comp),
        ("surrogate grid RSD", r_dem),
        ("cell network grid RSD + floor", r_cells_s),
    ):
        fit = fit_rsd_decay(tm, y)
        print(
            f"Eq. 10 fit ({name}): RSD_ss {fit['rsd_ss']:.3g} +/- {fit['rsd_ss_se']:.1g}, "
            f"RSD_0 {fit['rsd_0']:.3g} +/- {fit['rsd_0_se']:.1g}, "
            f"k_b {fit['k_b']:.3g} +/- {fit['k_b_se']:.1g} 1/s"
        )
    fit = fit_rsd_decay(tm, r_comp)
    bm = to_blender_model(base, n_sections=8, rsd_fit=fit)
    tb = np.linspace(0.0, 4.0 * bm.mean_residence_time_s, 4001)
    a, mb, vb = rtd_moments(tb, blender_model_rtd(bm, tb))
    print(
        f"8 sections (product): area {a:.6f}, mean {mb:.3f} s (8 V/Q = "
        f"{bm.mean_residence_time_s:.3f}), var {vb:.2f} s^2; 8 x surrogate section var = "
        f"{8 * v_ref:.2f} s^2; mean axial velocity v_x = {base.axial_velocity_m_s_:.4f} m/s"
    )
    if args.fields:
        return  # the face-coupled cell-level reference is affordable on the synthetic field only
    small = synthetic_blender_fields(6, 10, 10).fields
    ms = CompartmentModel().fit(small)
    cs = CompartmentModel(resolution="cells").fit(small).periodic_
    n = 8
    tb = np.linspace(0.0, 4.0 * n * ms.mean_residence_time_s_, 2001)
    t0 = time.perf_counter()
    truth = chain_periodic(cs, n).impulse_response(tb)
    t_truth = time.perf_counter() - t0
    print(
        f"\nwhole blender, {n} sections, reference = cell-level surrogate joined face to face "
        f"({cs.n * n} states, {t_truth:.1f} s); model {ms.n_compartments_} compartments/section"
    )
    print("| whole-blender model | mean | ref | err | var | ref | err | KS | W1/mean |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, e in (
        ("product: transit section, convolution", blender_rtd(ms.section_, n, tb)),
        ("closed-closed sections, convolution", blender_rtd(ms.closed_section_, n, tb)),
        ("compartments joined face to face", chain_periodic(ms.periodic_, n).impulse_response(tb)),
    ):
        print(row(name, compare_rtd(tb, e, e_ref=truth)))


if __name__ == "__main__":
    main()
