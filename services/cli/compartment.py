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
        choices=("auto", "transitions", "crossings", "velocity"),
        help="flows from particle transitions at a lag (kinetic zoning), face crossing counts "
        "or upwinded velocities; auto: with transit times, the one closer to them",
    )
    b.add_argument(
        "--mobility-classes",
        type=int,
        default=8,
        help="classes of the cells' escape rate in the kinetic zoning (transitions)",
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


def _save_figures(figures: dict, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name, fig in figures.items():
        fig.savefig(out / name, dpi=110)


def cmd_build(args: argparse.Namespace) -> int:
    from services.cli.bus import check_output_file
    from twin_core.compartment import load_fields
    from twin_core.compartment.build import BuildOptions, build_blender_model, load_transit_times

    check_output_file(args.out)
    try:
        samples, window = None, None
        if args.transit_times is not None:
            samples, window = load_transit_times(args.transit_times)
        opts = BuildOptions(
            variables=tuple(v.strip() for v in args.variables.split(",") if v.strip()),
            **{
                k: getattr(args, k)
                for k in ("tol", "min_cells", "flow_source", "sections", "mobility_classes")
            },
            **{k: getattr(args, k) for k in ("section_form", "n_upstream", "rpm", "split_axis")},
            **{k: getattr(args, k) for k in ("rsd_source", "surrogate", "seed")},
            rsd_grid=tuple(args.rsd_grid),
            rpm_runs={float(r): load_fields(Path(f)) for r, f in args.rpm_run},
            transit_times=samples,
            transit_window_s=args.transit_window if args.transit_window is not None else window,
        )
        result = build_blender_model(load_fields(args.fields), opts, source=args.fields.name)
    except ValueError as exc:
        raise ValueError(f"{exc}") from None
    result.blender.save(args.out)
    print(json.dumps({**result.report, "model": str(args.out)}, indent=1, default=float))
    if args.figures is not None:
        from twin_core.compartment.plots import build_figures

        _save_figures(build_figures(result), args.figures)
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    from schemas.blender_model import BlenderModel
    from twin_core.compartment.simulation import InletScenario, simulate_blender

    keys = ("inlet", "step_at", "step_to", "pulse_at", "pulse_width", "pulse_height")
    scenario = InletScenario(
        duration_s=args.duration,
        dt_s=args.dt,
        **{k: getattr(args, k) for k in (*keys, "scale_at", "scale_to", "rpm_to")},
    )
    try:
        bm = BlenderModel.load(args.model)
        t0 = time.perf_counter()
        t, u, y = simulate_blender(bm, scenario)
        elapsed = time.perf_counter() - t0
    except ValueError as exc:
        raise ValueError(f"{exc}") from None
    summary = {"points": int(t.size), "simulate_s": elapsed}
    summary |= {"mean_residence_time_s": bm.mean_residence_time_s}
    summary |= {"outlet_min": float(y.min()), "outlet_max": float(y.max())}
    print(json.dumps({**summary, "outlet_final": float(y[-1])}, indent=1))
    if args.out is not None:
        table = np.column_stack([t, u, y])
        np.savetxt(args.out, table, delimiter=",", header="t_s,inlet,outlet", comments="")
    if args.figures is not None:
        from twin_core.compartment.plots import plot_simulation

        _save_figures({"simulation.png": plot_simulation(t, u, y)}, args.figures)
    return 0
