"""The seed's blender section at seed size, from DEM to the line: runs, models, tables.

    python benchmarks/blender_campaign.py --runs out/blender_seed            # all steps
    python benchmarks/blender_campaign.py --runs out/blender_seed --workers 3 --ship
    python benchmarks/blender_campaign.py --runs DIR --scheduler tcp://host:8786   # Dask

Steps (each resumable; a step whose inputs are missing says so and the rest go on):

1. **DEM campaign** (``--scene``, default the seed-size ``blender.yaml``: 6,000 particles of
   r = 1 mm, 20 s at each blade speed): one ``twin_core.scenes.blender.run`` per speed through
   ``twin_core.calibration.campaign.run_campaign`` (process pool or Dask; finished speeds are
   skipped, an interrupted one resumes from its checkpoint) into ``DIR/rpm_<speed>/``.
2. **Compartment models**: ``twin_core.compartment.build.build_blender_model`` on each run's
   fields, the other speeds' fields giving the rpm law, validated against the run's own
   particle transit times (mean, variance, KS; censored to the recording window) ->
   ``DIR/models/blender_section_<speed>rpm.json``; ``--ship`` copies them to the package
   (``--ship-dir``, default ``twin_core/compartment/data``: the live twin's default blender;
   docs/compartment.md says which models are kept for study in its subfolders).
3. **T95 of the fifteen indices** from the runs' frames (``blender_mixing``) beside the seed's
   Tables 8.2-8.4 -> ``DIR/t95_vs_seed.csv``.
4. **The whole blender at the line** (12 kg/h, 100 rpm) against the seed's measured RTD
   (Table 6.2 axial dispersion: mean 32.5 s): with the DEM runs' own time scale (nothing
   tuned) and with the holdup set from Table 6.2's mean (one parameter tuned, said so) ->
   ``DIR/line_vs_table_6_2.json``.

Everything lands in ``DIR/campaign_report.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from schemas.dem_scene import load_scene  # noqa: E402

#: the seed's measured RTD of the line (Table 6.2, untruncated 10 g pulse), 12 kg/h, 100 rpm
TABLE_6_2 = {"tau_d": 11.92, "tau": 16.37, "pe": 7.67}
LINE_POINT = (100.0, 12.0)


def run_speed(params: dict[str, float], seed: int, scene: str = "", runs: str = "") -> dict:
    """One blade speed of the campaign (resumes from its checkpoint)."""
    from twin_core.dem.threads import adaptive_threads
    from twin_core.scenes import blender

    cfg = load_scene(scene)
    rpm = float(params["rpm"])
    run_dir = Path(runs) / f"rpm_{rpm:g}"
    resume = (run_dir / "checkpoint.npz").exists()
    with adaptive_threads():  # two threads on a loaded machine run at a quarter of one
        res = blender.run(cfg, rpm, run_dir, resume=resume, progress=True)
    return {
        "net_axial_flow_kg_s": res["net_axial_flow_kg_s"],
        "transit_count": res["transit_count"],
        "transit_mean_s": res["transit_mean_s"],
        "lacey_final": res["lacey_final"],
        "wall_s": res["wall_s"],
    }


def step_campaign(args: argparse.Namespace) -> pd.DataFrame:
    from functools import partial

    from twin_core.calibration.campaign import run_campaign

    design = pd.DataFrame({"run": [f"rpm_{r:g}" for r in args.rpms], "rpm": args.rpms})
    return run_campaign(
        design,
        partial(run_speed, scene=str(args.scene), runs=str(args.runs)),
        args.runs / "campaign.csv",
        scheduler=args.scheduler,
        n_workers=args.workers,
    )


def _done(runs: Path, rpms: list[float]) -> list[float]:
    return [r for r in rpms if (runs / f"rpm_{r:g}" / "results.json").exists()]


def step_models(args: argparse.Namespace, speeds: list[float]) -> dict[float, dict]:
    """Build, validate and save one section model per finished speed."""
    from twin_core.compartment import load_fields
    from twin_core.compartment.build import BuildOptions, build_blender_model
    from twin_core.scenes.blender import add_transitions

    out = args.runs / "models"
    out.mkdir(parents=True, exist_ok=True)
    for r in speeds:  # runs made before the scene counted transitions
        run_dir = args.runs / f"rpm_{r:g}"
        if load_fields(run_dir / "fields.npz").transitions is None:
            add_transitions(run_dir)
    fields = {r: load_fields(args.runs / f"rpm_{r:g}" / "fields.npz") for r in speeds}
    cfg = load_scene(args.scene)
    window = cfg.mix_s
    reports = {}
    for r in speeds:
        transit = np.load(args.runs / f"rpm_{r:g}" / "transit_times.npz")["transit_s"]
        opts = BuildOptions(
            rpm=r,
            sections=args.sections,
            rpm_runs={o: f for o, f in fields.items() if o != r},
            transit_times=transit,
            transit_window_s=window,
        )
        try:
            result = build_blender_model(fields[r], opts, source=f"{cfg.name} {r:g} rpm")
        except ValueError as exc:  # e.g. blades that do not convey: no RTD, no model
            print(f"{r:g} rpm: no model: {exc}")
            continue
        path = result.blender.save(out / f"blender_section_{r:g}rpm.json")
        rep = result.report
        reports[r] = {
            "model": str(path.relative_to(args.runs)),
            "compartments": rep.get("n_compartments"),
            "section_mean_residence_s": rep.get("mean_residence_time_s"),
            "blender_mean_residence_time_s": rep.get("blender_mean_residence_time_s"),
            "rtd_validation": rep.get("rtd_validation"),
            "flow_source": rep.get("flow_source"),
            "flow_source_candidates": rep.get("flow_source_candidates"),
            "transits": int(len(transit)),
        }
        print(f"{r:g} rpm: {json.dumps(reports[r], default=float)}")
    if args.ship:
        from schemas.blender_model import BlenderModel

        dest = args.ship_dir
        dest.mkdir(parents=True, exist_ok=True)
        for old in dest.glob("*.json"):
            old.unlink()
        for r in speeds:  # compact JSON: package data stays small
            name = f"blender_section_{r:g}rpm.json"
            model = BlenderModel.load(out / name)
            (dest / name).write_text(model.model_dump_json())
        print(f"shipped {len(speeds)} models to {dest}")
    return reports


def step_t95(args: argparse.Namespace, speeds: list[float]) -> pd.DataFrame | None:
    """Our T95 of the fifteen indices beside the seed's Tables 8.2-8.4."""
    from twin_core.mixing.seed_tables import SEED_T95
    from twin_core.scenes.blender import blender_mixing

    cfg = load_scene(args.scene).model_copy(update={"rpms": speeds})
    ours = blender_mixing(cfg, args.runs, args.runs / "mixing")
    rows = {}
    for name in ours.index:
        row = {}
        for r in speeds:
            row[f"{r:g} rpm"] = ours.loc[name, f"{r:g} rpm"]
            seed = SEED_T95.get(r, {}).get(name)
            row[f"{r:g} rpm seed"] = seed[2] if seed else float("nan")
        rows[name] = row
    table = pd.DataFrame(rows).T
    table.to_csv(args.runs / "t95_vs_seed.csv")
    return table


def step_line(args: argparse.Namespace) -> dict:
    """The whole blender at the line vs Table 6.2 (module docstring, step 4)."""
    from twin_core.compartment.operating_point import (
        HoldupRule,
        ModelTable,
        OperatingPoint,
        load_models,
    )
    from twin_core.compartment.validation import compare_rtd
    from twin_core.rtd.models import model_e

    models = load_models(args.runs / "models")
    rpm, q = LINE_POINT
    point = OperatingPoint(rpm, q)
    t = np.arange(0.0, 600.0, 0.05)
    e_seed = model_e("axial_dispersion_open", TABLE_6_2, t)
    seed_mean = float(np.trapezoid(t * e_seed, t))
    out = {"point": {"rpm": rpm, "throughput_kg_h": q}, "n_sections": models[0].n_sections}
    cases = {
        "dem_time_scale": HoldupRule(),
        "holdup_from_table_6_2": HoldupRule(seed_mean * q / 3600.0, point),
    }
    for name, rule in cases.items():
        table = ModelTable(models, rule)
        e = table.rtd(point, t)
        cmp = compare_rtd(t, e, e_ref=e_seed)
        F, Fs = np.cumsum(e) * 0.05, np.cumsum(e_seed) * 0.05
        out[name] = {
            "holdup_kg": (rule.holdup_kg if rule.holdup_kg else None),
            "mean_s": cmp["model_mean"],
            "seed_mean_s": cmp["ref_mean"],
            "var_s2": cmp["model_var"],
            "seed_var_s2": cmp["ref_var"],
            "dimensionless_var": cmp["model_var"] / cmp["model_mean"] ** 2,
            "seed_dimensionless_var": cmp["ref_var"] / cmp["ref_mean"] ** 2,
            "q005_s": float(t[np.searchsorted(F, 0.005)]),
            "q995_s": float(t[min(np.searchsorted(F, 0.995), t.size - 1)]),
            "seed_q005_s": float(t[np.searchsorted(Fs, 0.005)]),
            "seed_q995_s": float(t[np.searchsorted(Fs, 0.995)]),
            "ks": cmp.get("ks"),
        }
    (args.runs / "line_vs_table_6_2.json").write_text(json.dumps(out, indent=1, default=float))
    return out


def _markdown(table: pd.DataFrame) -> str:
    """A small DataFrame as a markdown table."""
    head = "| | " + " | ".join(str(c) for c in table.columns) + " |"
    rule = "|---" * (len(table.columns) + 1) + "|"
    rows = [
        "| " + str(i) + " | " + " | ".join(f"{v:g}" for v in r) + " |" for i, r in table.iterrows()
    ]
    return "\n".join([head, rule, *rows])


def main() -> int:
    from twin_core.dem.threads import prefer_openmp

    prefer_openmp()  # before the first parallel region (twin_core.dem.threads)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--runs", type=Path, required=True, help="campaign directory")
    ap.add_argument(
        "--scene", type=Path, default=ROOT / "twin_core" / "scenes" / "configs" / "blender.yaml"
    )
    ap.add_argument("--rpms", type=float, nargs="+", default=[100.0, 75.0, 50.0])
    ap.add_argument("--workers", type=int, default=None, help="local processes (default: cores)")
    ap.add_argument("--scheduler", default=None, help="Dask scheduler address")
    ap.add_argument("--sections", type=int, default=8, help="sections of the whole blender")
    ap.add_argument("--skip-runs", action="store_true", help="only analyse finished runs")
    ap.add_argument("--no-t95", action="store_true", help="skip the mixing indices (slow)")
    ap.add_argument("--ship", action="store_true", help="copy the models into the package")
    ap.add_argument(
        "--ship-dir",
        type=Path,
        default=None,
        help="where --ship writes (default: the live twin's default models, "
        "twin_core/compartment/data; models kept for study go to its subfolders)",
    )
    args = ap.parse_args()
    if args.ship_dir is None:
        from twin_core.compartment.operating_point import SHIPPED_MODELS

        args.ship_dir = SHIPPED_MODELS

    args.runs.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    if not args.skip_runs:
        step_campaign(args)
    speeds = _done(args.runs, args.rpms)
    if not speeds:
        print("no finished run: nothing to analyse")
        return 1
    missing = sorted(set(args.rpms) - set(speeds))
    if missing:
        print(f"not finished: {missing} rpm (run again to resume)")
    reports = step_models(args, speeds)
    t95 = None if args.no_t95 else step_t95(args, speeds)
    line = step_line(args) if reports else {"skipped": "no section model"}
    report = ["# Blender campaign", "", f"speeds: {speeds}; not finished: {missing}", ""]
    report += ["## Section models vs their run's particle RTD", "", "```json"]
    report += [json.dumps(reports, indent=1, default=float), "```", ""]
    if t95 is not None:
        report += ["## T95 (s) beside the seed's Tables 8.2-8.4", "", _markdown(t95.round(2))]
    report += ["", "## Whole blender at 12 kg/h, 100 rpm vs Table 6.2", "", "```json"]
    report += [json.dumps(line, indent=1, default=float), "```"]
    (args.runs / "campaign_report.md").write_text("\n".join(report) + "\n")
    print(f"report: {args.runs / 'campaign_report.md'} ({time.time() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
