"""`twin compartment`: build a blender compartment model from DEM grid fields and run it.

twin compartment build FIELDS.npz --out MODEL.json [--figures DIR]
twin compartment simulate MODEL.json [--duration 3600 --dt 0.1 ...] [--out CSV]
twin compartment synthetic OUT.npz      (synthetic fields with known flows)
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

log = logging.getLogger("twin.compartment")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("compartment", help="multi-zonal compartment model of the blender")
    sub = p.add_subparsers(dest="compartment_command", metavar="SUBCOMMAND")

    b = sub.add_parser("build", help="fields npz -> blender model JSON")
    b.add_argument("fields", type=Path, help="grid fields .npz (format in docs/compartment.md)")
    b.add_argument("--out", type=Path, required=True, help="model JSON to write")
    b.add_argument("--figures", type=Path, default=None, help="directory for PNG figures")
    b.add_argument("--variables", default="vx,vy,vz", help="zoning variables, comma separated")
    b.add_argument("--tol", type=float, default=0.1, help="sign-zone tolerance (fraction of max)")
    b.add_argument("--min-cells", type=int, default=3, help="merge compartments below this size")
    b.add_argument(
        "--flow-source",
        default="auto",
        choices=("auto", "crossings", "velocity"),
        help="cell-face flows from crossing counts or upwinded velocities",
    )
    b.add_argument("--sections", type=int, default=8, help="periodic sections in series")
    b.add_argument(
        "--section-form",
        default="transit",
        choices=("transit", "closed"),
        help="section RTD: record-passage transit law (DEM definition) or closed-closed cut",
    )
    b.add_argument(
        "--n-upstream",
        type=int,
        default=None,
        help="upstream copies of the transit form (default: the fewest with < 1e-4 dropped "
        "backward crossings per transit)",
    )
    b.add_argument("--rpm", type=float, default=None, help="blade speed basis of the fields")
    b.add_argument(
        "--rpm-run",
        nargs=2,
        action="append",
        default=[],
        metavar=("RPM", "FIELDS"),
        help="fields of a DEM run at another blade speed: its net axial flow calibrates the "
        "rpm law of dynamic runs (repeatable; needs --rpm)",
    )
    b.add_argument("--split-axis", type=int, default=1, help="axis of the two-type RSD split")
    b.add_argument(
        "--rsd-source",
        default="cells",
        choices=("cells", "compartments"),
        help="network whose RSD(t) gives the Eq. (10) parameters: every cell a compartment "
        "(sampled on --rsd-grid with the particle sampling floor, like the DEM grid RSD) or "
        "the compartments (Eq. 2; lumping mixes too fast)",
    )
    b.add_argument(
        "--rsd-grid",
        type=int,
        nargs=3,
        default=(10, 6, 6),
        metavar=("NX", "NY", "NZ"),
        help="sampling cells of the grid RSD (seed B.1: 10 x 6 x 6)",
    )
    b.add_argument(
        "--transit-times",
        type=Path,
        default=None,
        help="DEM particle transit times of the section (.npy, s) for the RTD comparison",
    )
    b.add_argument(
        "--transit-window",
        type=float,
        default=None,
        help="recording window (s) of the DEM transit times (default: 'window_s' of the npz "
        "if present): the model RTD is censored to the transits that fit in it",
    )
    b.add_argument(
        "--surrogate",
        type=int,
        default=20000,
        help="particles of the random-walk surrogate when crossings exist (0: none)",
    )
    b.add_argument("--seed", type=int, default=0, help="seed of the surrogate walk")
    b.set_defaults(func=cmd_build)

    s = sub.add_parser("simulate", help="predict the blender outlet from an inlet signal")
    s.add_argument("model", type=Path, help="model JSON from `twin compartment build`")
    s.add_argument("--duration", type=float, default=3600.0, help="s")
    s.add_argument("--dt", type=float, default=0.1, help="output step (s)")
    s.add_argument("--inlet", type=float, default=3.0, help="baseline inlet concentration")
    s.add_argument("--step-at", type=float, default=None, help="time of an inlet step (s)")
    s.add_argument("--step-to", type=float, default=None, help="inlet concentration after it")
    s.add_argument("--pulse-at", type=float, default=None, help="time of a tracer pulse (s)")
    s.add_argument("--pulse-width", type=float, default=1.0, help="pulse width (s)")
    s.add_argument("--pulse-height", type=float, default=10.0, help="added concentration")
    s.add_argument("--scale-at", type=float, default=None, help="time of a flow change (s)")
    s.add_argument(
        "--scale-to",
        type=float,
        default=1.0,
        help="flows relative to the basis after --scale-at (rpm or throughput ratio)",
    )
    s.add_argument(
        "--rpm-to",
        type=float,
        default=None,
        help="blade speed after --scale-at (the flow scale from the model's rpm law)",
    )
    s.add_argument("--out", type=Path, default=None, help="CSV of t, inlet, outlet")
    s.add_argument("--figures", type=Path, default=None, help="directory for PNG figures")
    s.set_defaults(func=cmd_simulate)

    y = sub.add_parser("synthetic", help="write synthetic fields with known flows")
    y.add_argument("out", type=Path)
    y.add_argument("--shape", type=int, nargs=3, default=(10, 20, 20), metavar=("NX", "NY", "NZ"))
    y.add_argument("--counts", default="expected", choices=("expected", "poisson"))
    y.add_argument("--seed", type=int, default=0)
    y.set_defaults(func=cmd_synthetic)

    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def cmd_synthetic(args: argparse.Namespace) -> int:
    from twin_core.compartment import save_fields, synthetic_blender_fields

    case = synthetic_blender_fields(*args.shape, counts=args.counts, seed=args.seed)
    save_fields(args.out, case.fields)
    print(json.dumps({"fields": str(args.out), "throughput_kg_s": case.throughput_kg_s}))
    return 0


def cmd_build(args: argparse.Namespace) -> int:
    from twin_core.compartment import (
        CompartmentModel,
        fit_rsd_decay,
        load_fields,
        section_rsd,
        split_initial,
        to_blender_model,
    )
    from twin_core.compartment.fields import mirror_axis

    try:
        fields = load_fields(args.fields)
        dem_samples, dem_window = (
            _load_transit_times(args.transit_times)
            if args.transit_times is not None
            else (None, None)
        )
        if args.transit_window is None:
            args.transit_window = dem_window
        variables = tuple(v.strip() for v in args.variables.split(",") if v.strip())
        t0 = time.perf_counter()
        model = CompartmentModel(
            variables=variables,
            tol_fraction=args.tol,
            min_cells=args.min_cells,
            flow_source=args.flow_source,
            section_form=args.section_form,
            n_upstream=args.n_upstream,
        ).fit(fields)
        t_build = time.perf_counter() - t0
        if model.section_ is None:
            raise ValueError(
                f"{args.fields}: no net axial flow through the periodic face "
                f"({model.throughput_kg_s_:.3g} kg/s): no RTD, no blender model"
            )
        if model.mirrored_:  # net flow towards -x: work in the model's orientation
            fields = mirror_axis(fields, model.axial_axis)
        # every cell its own compartment (same orientation): radial mixing and the surrogate
        cells = None
        if args.rsd_source == "cells" or (
            args.transit_times is None and fields.has_crossings and args.surrogate > 0
        ):
            cells = CompartmentModel(
                resolution="cells", flow_source=model.flow_source_, axial_direction="+"
            ).fit(fields)
        # radial mixing of the closed section: RSD(t) and the Eq. (10) parameters
        c0 = split_initial(fields, model.labels_, axis=args.split_axis)
        t_mix = _mixing_grid(model)
        rsd_t = section_rsd(model.periodic_, c0, t_mix)
        fit_comp = fit_rsd_decay(t_mix, rsd_t)
        rsd_grid = None
        if args.rsd_source == "cells":
            rsd_grid = _cell_grid_rsd(fields, cells, args, t_mix)
            fit = fit_rsd_decay(t_mix, rsd_grid)
        else:
            fit = fit_comp
        rpm_runs = {
            float(r): CompartmentModel(
                variables=variables,
                tol_fraction=args.tol,
                min_cells=args.min_cells,
                flow_source=args.flow_source,
            ).fit(load_fields(Path(p)))
            for r, p in args.rpm_run
        }
        bm = to_blender_model(
            model,
            rpm_runs=rpm_runs or None,
            n_sections=args.sections,
            rpm_basis=args.rpm,
            rsd_fit=fit,
            source=f"{args.fields.name} ({model.flow_source_})",
        )
    except ValueError as exc:
        log.error("%s", exc)
        return 2
    bm.save(args.out)
    report = {
        **model.summary(),
        "build_s": t_build,
        "rsd_source": args.rsd_source,
        "rsd_fit": fit,
        "rsd_fit_compartments_eq2": fit_comp,
        "blender_mean_residence_time_s": bm.mean_residence_time_s,
        "model": str(args.out),
    }
    validation = None
    samples = None
    if args.transit_times is not None:
        samples = dem_samples
        validation = "DEM transit times"
    elif cells is not None and fields.has_crossings and args.surrogate > 0:
        from twin_core.compartment.surrogate import walk_transit_times

        # the walk runs on the cell flows made conserving (raw counts of a short DEM run
        # leave cells that are entered but never left)
        samples = walk_transit_times(cells.periodic_, args.surrogate, seed=args.seed)
        validation = "random-walk surrogate"
    t_rtd = np.linspace(0.0, 8.0 * model.mean_residence_time_s_, 2001)
    e_sec = model.section_.impulse_response(t_rtd)
    e_cmp = None
    if samples is not None:
        from twin_core.compartment import compare_rtd

        e_cmp = e_sec
        if args.transit_window is not None and validation == "DEM transit times":
            from twin_core.compartment.validation import window_censored

            e_cmp = window_censored(t_rtd, e_sec, args.transit_window)
            validation = f"DEM transit times (window {args.transit_window} s)"
        report["rtd_validation"] = {
            "against": validation,
            **compare_rtd(t_rtd, e_cmp, samples=samples),
        }
    print(json.dumps(report, indent=1, default=float))
    if args.figures is not None:
        write_build_figures(
            args.figures,
            fields,
            model,
            t_rtd,
            e_sec,
            samples,
            validation,
            t_mix,
            rsd_t,
            fit,
            bm,
            rsd_grid,
            e_cmp if e_cmp is not e_sec else None,
        )
    return 0


def _load_transit_times(path: Path) -> tuple[np.ndarray, float | None]:
    """Transit times (s) from a .npy array or an .npz holding ``transit_s`` (and optionally
    ``window_s``, the length of the recording window)."""
    if not path.exists():
        raise ValueError(f"transit-times file {str(path)!r} does not exist")
    data = np.load(path, allow_pickle=False)
    if isinstance(data, np.lib.npyio.NpzFile):
        with data:
            if "transit_s" not in data.files:
                raise ValueError(f"{path}: key 'transit_s' missing (keys: {data.files})")
            window = float(data["window_s"]) if "window_s" in data.files else None
            return np.asarray(data["transit_s"], dtype=float), window
    return np.asarray(data, dtype=float), None


def _cell_grid_rsd(fields, cells, args, t_mix: np.ndarray) -> np.ndarray:
    """Grid RSD (seed Eq. B.1) of the cell-level network sampled like the DEM's particles
    (Poisson counts per cell, binomial types; right also for sparse runs): the radial-mixing
    curve a DEM grid RSD would show."""
    from twin_core.compartment.radial import (
        flowing,
        grid_rsd_sampled,
        section_concentrations,
        split_initial,
    )
    from twin_core.compartment.surrogate import coarse_index

    c0 = split_initial(fields, cells.labels_, axis=args.split_axis)
    c = section_concentrations(cells.periodic_, c0, t_mix)
    bins = tuple(args.rsd_grid)
    coarse = coarse_index(fields, cells.mask_, bins)
    return grid_rsd_sampled(
        c,
        cells.labels_,
        fields.occupancy,
        coarse,
        int(np.prod(bins)),
        seed=args.seed,
        n_samples=10,
        active=flowing(cells.periodic_),
    )


def _mixing_grid(model) -> np.ndarray:
    """Times for the radial-mixing RSD: up to 3 x the section residence time."""
    return np.linspace(0.0, 3.0 * model.mean_residence_time_s_, 121)


def write_build_figures(
    out,
    fields,
    model,
    t_rtd,
    e_sec,
    samples,
    validation,
    t_mix,
    rsd_t,
    fit,
    bm,
    rsd_grid=None,
    e_censored=None,
) -> list[Path]:
    """Zone maps, compartment maps, network graph, RTD comparison and RSD (PNG files)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.colors import BoundaryNorm, ListedColormap

    from twin_core.compartment import rsd_decay

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    ext = [fields.y_edges[0], fields.y_edges[-1], fields.z_edges[0], fields.z_edges[-1]]

    nv = len(model.zones_)
    zmin = min(int(z.min()) for z in model.zones_.values())
    zmax = max(int(z.max()) for z in model.zones_.values())
    levels = np.arange(zmin, zmax + 1)
    if zmin == -2 and zmax <= 1:  # sign zones: empty, -1, 0, +1
        cmap = ListedColormap(["white", "#3b4cc0", "#a1d99b", "#b40426"][: levels.size])
    else:
        cmap = ListedColormap(
            ["white"] + list(plt.get_cmap("viridis")(np.linspace(0, 1, max(levels.size - 1, 1))))
        )
    norm = BoundaryNorm(np.arange(zmin - 0.5, zmax + 1.5), cmap.N)
    fig, axes = plt.subplots(
        1, nv, figsize=(3.8 * nv + 1, 3.6), squeeze=False, layout="constrained"
    )
    for ax, (name, zmap) in zip(axes[0], model.zones_.items()):
        im = ax.imshow(zmap[0].T, origin="lower", extent=ext, cmap=cmap, norm=norm)
        ax.set_title(f"zones of {name}, slice x=0")
        ax.set_xlabel("y (m)")
    axes[0][0].set_ylabel("z (m)")
    fig.colorbar(im, ax=axes[0].tolist(), ticks=levels, label="zone (-2 empty)")
    files.append(out / "zone_maps.png")
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)

    maps = dict(model.maps_)
    maps["overlay (compartments)"] = model.labels_
    fig, axes = plt.subplots(
        1, len(maps), figsize=(3.8 * len(maps), 3.6), squeeze=False, layout="constrained"
    )
    for ax, (name, lab) in zip(axes[0], maps.items()):
        sl = lab[0].astype(float)
        sl[sl < 0] = np.nan
        ax.imshow(sl.T, origin="lower", extent=ext, cmap="tab20", interpolation="nearest")
        ax.set_title(f"{name}: {len(np.unique(lab[0][lab[0] >= 0]))} in slice 0")
        ax.set_xlabel("y (m)")
    files.append(out / "compartment_maps.png")
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)

    net = model.periodic_
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    cen = net.centroid
    rmax = float(net.rate.max())
    for ax, (i, j, lab_i, lab_j) in zip(axes, ((1, 2, "y", "z"), (0, 2, "x", "z"))):
        sel = (
            (net.slice_index[net.src] == 0) & (net.slice_index[net.dst] == 0)
            if i == 1
            else (~net.wrap)
        )
        seg = np.stack([cen[net.src[sel]][:, [i, j]], cen[net.dst[sel]][:, [i, j]]], axis=1)
        ax.add_collection(
            LineCollection(
                seg, colors="0.5", linewidths=0.3 + 2.5 * net.rate[sel] / rmax, alpha=0.6
            )
        )
        pts = net.slice_index == 0 if i == 1 else np.ones(net.n, bool)
        sc = ax.scatter(
            cen[pts, i],
            cen[pts, j],
            s=8 + 200 * net.holdup[pts] / net.holdup.max(),
            c=net.slice_index[pts],
            cmap="viridis",
            zorder=3,
        )
        ax.set_xlabel(f"{lab_i} (m)")
        ax.set_ylabel(f"{lab_j} (m)")
    axes[0].set_title("network, slice 0 (size: holdup, width: flow)")
    axes[1].set_title(f"network, all {net.n} compartments")
    fig.colorbar(sc, ax=axes[1], label="slice")
    files.append(out / "network_graph.png")
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    ax = axes[0]
    if samples is not None:
        fin = np.asarray(samples)[np.isfinite(samples)]
        ax.hist(
            fin,
            bins=80,
            range=(0, t_rtd[-1]),
            density=True,
            alpha=0.4,
            label=f"{validation} (n={fin.size})",
        )
    ax.plot(t_rtd, e_sec, "k-", label=f"compartment model ({model.section_form} form)")
    if e_censored is not None:
        ax.plot(t_rtd, e_censored, "r--", label="model censored to the recording window")
    ax.axvline(model.mean_residence_time_s_, color="k", ls=":", label="V/Q")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("E(t) (1/s)")
    ax.set_title("section RTD")
    ax.legend(fontsize=8)
    tb = np.linspace(0.0, 3.0 * bm.mean_residence_time_s, 1501)
    for k in sorted({1, 2, 4, bm.n_sections}):
        axes[1].plot(tb, bm.impulse_response(tb, n_sections=k), label=f"{k} sections")
    axes[1].set_xlabel("t (s)")
    axes[1].set_title("sections in series (Eq. 8-9)")
    axes[1].legend(fontsize=8)
    files.append(out / "rtd_comparison.png")
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    axes[0].plot(t_mix, rsd_t, "k.", ms=3, label="compartments (Eq. 2)")
    if rsd_grid is not None:
        axes[0].plot(t_mix, rsd_grid, "b.", ms=3, label="cell network: grid RSD, sampled")
    axes[0].plot(
        t_mix,
        rsd_decay(t_mix, fit["rsd_ss"], fit["rsd_0"], fit["k_b"]),
        "r-",
        label=f"Eq. 10 fit, k_b={fit['k_b']:.3g}/s",
    )
    axes[0].set_xlabel("t (s)")
    axes[0].set_ylabel("RSD")
    axes[0].set_title("radial mixing, closed section")
    axes[0].legend(fontsize=8)
    x = np.linspace(0.0, bm.n_sections * bm.section_length_m, 200)
    axes[1].plot(x, bm.rsd_profile(x), "r-")
    axes[1].set_xlabel("x along the blender (m)")
    axes[1].set_ylabel("RSD")
    axes[1].set_title("RSD along the blender (Eq. 10)")
    files.append(out / "rsd.png")
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)
    return files


def cmd_simulate(args: argparse.Namespace) -> int:
    from schemas.blender_model import BlenderModel

    try:
        bm = BlenderModel.load(args.model)
        if args.dt <= 0 or args.duration <= args.dt:
            raise ValueError(f"need 0 < dt < duration, got dt={args.dt}, duration={args.duration}")
        t = np.arange(0.0, args.duration, args.dt)
        u = np.full(t.size, args.inlet)
        if args.step_at is not None:
            if args.step_to is None:
                raise ValueError("--step-at needs --step-to")
            u[t >= args.step_at] = args.step_to
        if args.pulse_at is not None:
            u[(t >= args.pulse_at) & (t < args.pulse_at + args.pulse_width)] += args.pulse_height
        scale = None
        if args.scale_at is not None:
            to = args.scale_to
            if args.rpm_to is not None:
                to = float(bm.flow_scale_for_rpm(np.array([args.rpm_to]))[0])
            if to < 0:
                raise ValueError(f"--scale-to must be >= 0, got {to}")
            scale = np.where(t >= args.scale_at, to, 1.0)
        t0 = time.perf_counter()
        y = bm.predict(t, u, flow_scale=scale)
        elapsed = time.perf_counter() - t0
    except ValueError as exc:
        log.error("%s", exc)
        return 2
    print(
        json.dumps(
            {
                "points": int(t.size),
                "simulate_s": elapsed,
                "mean_residence_time_s": bm.mean_residence_time_s,
                "outlet_min": float(y.min()),
                "outlet_max": float(y.max()),
                "outlet_final": float(y[-1]),
            },
            indent=1,
        )
    )
    if args.out is not None:
        np.savetxt(
            args.out,
            np.column_stack([t, u, y]),
            delimiter=",",
            header="t_s,inlet,outlet",
            comments="",
        )
    if args.figures is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        args.figures.mkdir(parents=True, exist_ok=True)
        fig, ax = plt.subplots(figsize=(9, 4))
        ax.plot(t, u, color="0.6", label="inlet")
        ax.plot(t, y, "k-", label="outlet (compartment model)")
        ax.set_xlabel("t (s)")
        ax.set_ylabel("concentration")
        ax.legend()
        fig.savefig(args.figures / "simulation.png", dpi=110)
        plt.close(fig)
    return 0
