"""`twin calibrate design|fit|solve|campaign` and `twin feeder simulate` (seed ch. 3, 8.1)."""

from __future__ import annotations

import argparse
import importlib
import json
import logging
from pathlib import Path
from typing import Any

log = logging.getLogger("twin.calibrate")

_SEED_TABLES = {
    "seed:bulk": "bulk",
    "seed:feed_factor": "feed_factor",
    "seed:dsd": "dsd",
    "seed:verification": "verification",
}


def _pairs(text: str | None, name: str) -> dict[str, float]:
    """'a=1,b=2.5' -> {'a': 1.0, 'b': 2.5}."""
    out: dict[str, float] = {}
    if not text:
        return out
    for item in text.split(","):
        if "=" not in item:
            raise SystemExit(f"{name} must look like NAME=VALUE,NAME=VALUE; got {item!r}")
        k, v = item.split("=", 1)
        try:
            out[k.strip()] = float(v)
        except ValueError:
            raise SystemExit(f"{name}: value of {k.strip()!r} is not a number: {v!r}") from None
    return out


def _bounds(text: str | None) -> dict[str, tuple[float, float]]:
    """'a=0.1:0.6,b=0:1' -> {'a': (0.1, 0.6), 'b': (0.0, 1.0)}."""
    out: dict[str, tuple[float, float]] = {}
    if not text:
        return out
    for item in text.split(","):
        try:
            k, v = item.split("=", 1)
            lo, hi = (float(x) for x in v.split(":"))
        except ValueError:
            raise SystemExit(f"--bounds must look like NAME=LO:HI,...; got {item!r}") from None
        out[k.strip()] = (lo, hi)
    return out


def _list(text: str | None) -> list[str] | None:
    return [s.strip() for s in text.split(",") if s.strip()] if text else None


def _load_table(spec: str):
    import pandas as pd

    from twin_core.calibration import load_seed_table

    if spec in _SEED_TABLES:
        return load_seed_table(_SEED_TABLES[spec])
    path = Path(spec)
    if not path.exists():
        raise SystemExit(f"table {spec!r} not found (or use one of {sorted(_SEED_TABLES)})")
    if path.suffix == ".parquet":
        return pd.read_parquet(path)
    return pd.read_csv(path)


def _out(path: str) -> Path:
    p = Path(path)
    p.mkdir(parents=True, exist_ok=True)
    return p


def _save(fig: Any, path: Path) -> None:
    fig.savefig(path, dpi=130)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="DEM bulk calibration: DSD, response surfaces, inverse")
    csub = p.add_subparsers(dest="calibrate_command", metavar="ACTION")

    d = csub.add_parser("design", help="definitive screening design + correlation map")
    d.add_argument(
        "--levels", help="JSON/YAML file: factor -> [lower, middle, upper] (default: seed)"
    )
    d.add_argument("--factors", type=int, help="number of coded factors instead of --levels")
    d.add_argument("--no-extra-runs", action="store_true", help="2011 design (no 4 extra runs)")
    d.add_argument("--randomize", action="store_true", help="randomise the run order")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--out", required=True, help="output directory")
    d.set_defaults(func=_design)

    f = csub.add_parser("fit", help="two-step stepwise response surfaces of a results table")
    f.add_argument("table", help="CSV/Parquet table, or seed:bulk / seed:feed_factor")
    f.add_argument("--factors", help="comma list (default: the seed's 8 DEM factors)")
    f.add_argument("--responses", help="comma list (default: every other numeric column)")
    f.add_argument("--criterion", default="aicc", choices=["aic", "aicc", "bic", "p"])
    f.add_argument("--direction", default="both", choices=["forward", "backward", "both"])
    f.add_argument("--terms", help="fit these terms instead of stepwise, e.g. 'A,B,A*B,A*A'")
    f.add_argument(
        "--predict",
        help="table of new runs to predict (95 %% prediction intervals), e.g. seed:verification",
    )
    f.add_argument("--out", help="output directory (models.json, parity.png, summary.csv)")
    f.add_argument("--no-figures", action="store_true", help="tables only")
    f.set_defaults(func=_fit)

    s = csub.add_parser("solve", help="inverse calibration: parameters from bulk measurements")
    s.add_argument("--targets", required=True, help="RESPONSE=VALUE,... (measured responses)")
    s.add_argument("--table", default="seed:bulk", help="table the surfaces are fitted to")
    s.add_argument("--factors", help="comma list of design factors (default: seed's 8)")
    s.add_argument("--unknowns", default="PP_SF,PP_RF,PP_COR,PW_SF", help="parameters to solve")
    s.add_argument("--bounds", help="NAME=LO:HI,... (default: the design range)")
    s.add_argument("--fixed", help="NAME=VALUE,... for the other factors (default: design mean)")
    s.add_argument("--criterion", default="aicc", choices=["aic", "aicc", "bic", "p"])
    s.add_argument("--starts", type=int, default=64)
    s.add_argument("--method", default="both", choices=["multistart", "de", "both"])
    s.add_argument(
        "--rule",
        default="min_variance",
        choices=["min_variance", "nearest_prior", "best_conditioned"],
    )
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--contour", default="PP_SF,PP_RF", help="two unknowns for the contour plot")
    s.add_argument("--profile-points", type=int, default=15, help="profile grid (0: no profiles)")
    s.add_argument("--out", help="output directory (solutions.csv, contours.png, profiles.png)")
    s.set_defaults(func=_solve)

    c = csub.add_parser("campaign", help="run a design's simulations in parallel (resumable)")
    c.add_argument("design", help="design CSV (physical units), e.g. from `twin calibrate design`")
    c.add_argument(
        "--runner",
        default="surrogate",
        help="'surrogate', 'drawdown' (DEM drawdown test, seed 3.2.2) or module:function",
    )
    c.add_argument("--scene", help="drawdown runner: DrawdownScene YAML/JSON (default: seed scene)")
    c.add_argument("--run-root", default="drawdown_runs", help="drawdown runner: run directories")
    c.add_argument("--results", required=True, help="results CSV (resumed if it exists)")
    c.add_argument("--scheduler", help="Dask scheduler address (default: local process pool)")
    c.add_argument("--workers", type=int, default=None)
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--fresh", action="store_true", help="discard previous results")
    c.set_defaults(func=_campaign)

    fp = sub.add_parser("feeder", help="loss-in-weight feeder model")
    fsub = fp.add_subparsers(dest="feeder_command", metavar="ACTION")
    fs = fsub.add_parser("simulate", help="simulate a LIW feeder (PID, refills) and plot it")
    fs.add_argument("config", nargs="?", help="YAML/JSON FeederConfig (default: defaults)")
    fs.add_argument("--duration", type=float, default=3600.0, help="seconds")
    fs.add_argument("--dt", type=float, default=0.1, help="time step (s)")
    fs.add_argument("--seed", type=int, default=0)
    fs.add_argument("--set", dest="overrides", help="FIELD=VALUE,... overrides of the config")
    fs.add_argument("--out", required=True, help="output directory (trace.csv, feeder.png)")
    fs.set_defaults(func=_feeder_simulate)
    ff = fsub.add_parser("fit-ff", help="fit seed Eq. (2) to feed factor vs hopper mass data")
    ff.add_argument("data", help="CSV with hopper mass and feed factor columns")
    ff.add_argument("--weight-col", default="hopper_mass_kg")
    ff.add_argument("--ff-col", default="feed_factor_g_rev")
    ff.add_argument("--out", help="output directory (fit.json, feed_factor_fit.png)")
    ff.set_defaults(func=_feeder_fit_ff)


# --------------------------------------------------------------------------- design
def _read_mapping(path: str) -> dict[str, Any]:
    from schemas.base import read_mapping

    return read_mapping(path)


def _design(args: argparse.Namespace) -> int:
    from twin_core.calibration import (
        SEED_LEVELS,
        correlation_map,
        definitive_screening_design,
        dsd_properties,
    )
    from twin_core.calibration.plots import plot_correlation_map

    if args.levels and args.factors:
        raise SystemExit("give --levels or --factors, not both")
    factors: Any = args.factors or (_read_mapping(args.levels) if args.levels else SEED_LEVELS)
    try:
        d = definitive_screening_design(
            factors, extra_runs=not args.no_extra_runs, randomize=args.randomize, seed=args.seed
        )
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    out = _out(args.out)
    d.coded.to_csv(out / "design_coded.csv")
    d.physical.to_csv(out / "design_physical.csv")
    corr = correlation_map(d.coded)
    corr.to_csv(out / "correlation_map.csv")
    _save(plot_correlation_map(corr), out / "correlation_map.png")
    props = dsd_properties(d.coded)
    (out / "design.json").write_text(
        json.dumps(
            {
                "runs": d.n_runs,
                "conference_order": d.conference_order,
                "fake_factors": d.n_fake,
                "max_abs_r": props,
            },
            indent=2,
        )
    )
    print(d.physical.to_string())
    print(
        f"{d.n_runs} runs, {len(d.coded.columns)} factors; max |r|: "
        + ", ".join(f"{k} {v:.3g}" for k, v in props.items())
    )
    print(f"wrote {out}/design_physical.csv, design_coded.csv, correlation_map.png")
    return 0


# --------------------------------------------------------------------------- fit
def _factor_list(args: argparse.Namespace, table: Any) -> list[str]:
    from twin_core.calibration import SEED_FACTORS

    factors = _list(args.factors) or SEED_FACTORS
    missing = [f for f in factors if f not in table.columns]
    if missing:
        raise SystemExit(f"table lacks factor column(s) {missing}; pass --factors")
    return factors


def _fit_models(
    table: Any, factors: list[str], responses: list[str], args: argparse.Namespace
) -> dict[str, Any]:
    from twin_core.calibration import ResponseSurface, TwoStepRSM

    models: dict[str, Any] = {}
    for r in responses:
        try:
            if getattr(args, "terms", None):
                models[r] = ResponseSurface(terms=_list(args.terms)).fit(table, r)
            else:
                models[r] = (
                    TwoStepRSM(
                        factors,
                        criterion=args.criterion,
                        direction=getattr(args, "direction", "both"),
                    )
                    .fit(table, r)
                    .model_
                )
        except ValueError as exc:
            raise SystemExit(f"{r}: {exc}") from None
    return models


def _fit(args: argparse.Namespace) -> int:
    import pandas as pd

    from twin_core.calibration.plots import plot_parity, plot_prediction_profiles

    table = _load_table(args.table)
    factors = _factor_list(args, table)
    responses = _list(args.responses) or [
        c
        for c in table.columns
        if c not in factors
        and c not in ("run", "seed", "elapsed_s", "R2")
        and not c.endswith("_used")
        and pd.api.types.is_numeric_dtype(table[c])
    ]
    if not responses:
        raise SystemExit("no response columns found; pass --responses")
    models = _fit_models(table, factors, responses, args)
    for m in models.values():
        print(m.report())
        print()
    summary = pd.DataFrame(
        [
            {
                "response": k,
                "terms": " + ".join("*".join(t) for t in m.terms_),
                "r2": m.r2_,
                "r2_adj": m.r2_adj_,
                "rmse": m.rmse_,
                "sse": m.sse_,
            }
            for k, m in models.items()
        ]
    )
    print(summary.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    pred = None
    if args.predict:
        new = _load_table(args.predict)
        parts = [new[["run"]] if "run" in new.columns else pd.DataFrame(index=new.index)]
        for k, m in models.items():
            try:
                iv = m.predict_interval(new)
            except ValueError as exc:
                raise SystemExit(f"--predict: {exc}") from None
            parts.append(iv.add_prefix(f"{k}:").set_index(new.index))
        pred = pd.concat(parts, axis=1)
        print(pred.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    if args.out:
        out = _out(args.out)
        summary.to_csv(out / "summary.csv", index=False)
        (out / "models.json").write_text(
            json.dumps({k: m.to_dict() for k, m in models.items()}, indent=2)
        )
        (out / "report.txt").write_text("\n\n".join(m.report() for m in models.values()))
        if not args.no_figures:
            _save(plot_parity(models), out / "parity.png")
            ranges = {f: (float(table[f].min()), float(table[f].max())) for f in factors}
            for k, m in models.items():
                if m.factors_:
                    _save(plot_prediction_profiles(m, ranges), out / f"profiler_{k}.png")
        effects = pd.concat(
            [m.effect_summary().reset_index().assign(response=k) for k, m in models.items()],
            ignore_index=True,
        )
        effects.to_csv(out / "effect_summary.csv", index=False)
        if pred is not None:
            pred.to_csv(out / "predictions.csv", index=False)
        print(
            f"wrote {out}/summary.csv, models.json, report.txt, parity.png, profiler_*.png, "
            "effect_summary.csv"
        )
    return 0


# --------------------------------------------------------------------------- solve
def _solve(args: argparse.Namespace) -> int:
    from twin_core.calibration import InverseCalibration
    from twin_core.calibration.plots import plot_contours, plot_profiles

    table = _load_table(args.table)
    factors = _factor_list(args, table)
    targets = _pairs(args.targets, "--targets")
    models = _fit_models(table, factors, list(targets), args)
    unknowns = _list(args.unknowns) or []
    bounds = _bounds(args.bounds)
    for u in unknowns:
        if u not in table.columns:
            raise SystemExit(f"unknown {u!r} is not a column of the table")
        bounds.setdefault(u, (float(table[u].min()), float(table[u].max())))
    used = {f for m in models.values() for f in m.factors_}
    fixed = _pairs(args.fixed, "--fixed")
    for f in used - set(unknowns) - set(fixed):
        fixed[f] = float(table[f].mean())
    try:
        ic = InverseCalibration(models, {u: bounds[u] for u in unknowns}, fixed=fixed)
        res = ic.solve(
            targets, n_starts=args.starts, method=args.method, seed=args.seed, rule=args.rule
        )
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    tab = res.table()
    print(f"fixed: {fixed}")
    print(tab.to_string(index=False, float_format=lambda v: f"{v:.5g}"))
    print(res.diagnosis)
    print(f"recommended ({res.rule}):")
    if res.recommended is not None:
        print("  " + ", ".join(f"{k} = {v:.5g}" for k, v in res.recommended.params.items()))
    if args.out:
        out = _out(args.out)
        tab.to_csv(out / "solutions.csv", index=False)
        (out / "diagnosis.txt").write_text(res.diagnosis + "\n" + res.rule + "\n")
        written = ["solutions.csv", "diagnosis.txt"]
        if res.recommended is not None:
            cx = _list(args.contour) or []
            if len(cx) == 2 and all(c in unknowns for c in cx):
                sols = [s.params for s in res.solutions]
                _save(
                    plot_contours(ic, cx[0], cx[1], res.recommended.params, targets, sols),
                    out / "contours.png",
                )
                written.append("contours.png")
            profiles = {
                u: ic.profile(targets, u, n_points=15, n_starts=2, seed=args.seed) for u in unknowns
            }
            _save(plot_profiles(profiles), out / "profiles.png")
            written.append("profiles.png")
        print(f"wrote {out}/" + ", ".join(written))
    return 0 if res.recommended is not None else 1


# --------------------------------------------------------------------------- campaign
def _runner(spec: str, scene: str | None = None, run_root: str = "drawdown_runs"):
    if spec == "surrogate":
        from twin_core.calibration.campaign import surrogate_drawdown

        return surrogate_drawdown
    if spec == "drawdown":
        from twin_core.calibration.scenes import DrawdownRunner

        base = _read_mapping(scene) if scene else None
        if base is not None:
            base.pop("scene", None)
        try:
            return DrawdownRunner(base, run_root=run_root)
        except ValueError as exc:
            raise SystemExit(f"invalid drawdown scene: {exc}") from None
    if ":" not in spec:
        raise SystemExit(f"--runner must be 'surrogate' or module:function, got {spec!r}")
    mod, fn = spec.split(":", 1)
    try:
        return getattr(importlib.import_module(mod), fn)
    except (ImportError, AttributeError) as exc:
        raise SystemExit(f"cannot load runner {spec!r}: {exc}") from None


def _campaign(args: argparse.Namespace) -> int:
    import pandas as pd

    from twin_core.calibration.campaign import run_campaign

    design = pd.read_csv(args.design)
    try:
        out = run_campaign(
            design,
            _runner(args.runner, args.scene, args.run_root),
            args.results,
            seed=args.seed,
            scheduler=args.scheduler,
            n_workers=args.workers,
            resume=not args.fresh,
        )
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    n_ok = int((out["status"] == "ok").sum())
    print(out.to_string(index=False, float_format=lambda v: f"{v:.5g}"))
    print(f"{n_ok}/{len(out)} runs ok; results in {args.results}")
    return 0 if n_ok == len(out) else 1


# --------------------------------------------------------------------------- feeder
def _coerce(v: str) -> Any:
    low = v.lower()
    if low in ("true", "false"):
        return low == "true"
    try:
        return float(v)
    except ValueError:
        return v


def _feeder_simulate(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from schemas.feeder import FeederConfig
    from twin_core.calibration.plots import plot_feeder_trace
    from twin_core.feeder import LossInWeightFeeder

    data: dict[str, Any] = _read_mapping(args.config) if args.config else {}
    if args.overrides:
        for item in args.overrides.split(","):
            if "=" not in item:
                raise SystemExit(f"--set must look like FIELD=VALUE,...; got {item!r}")
            k, v = item.split("=", 1)
            data[k.strip()] = _coerce(v.strip())
    try:
        cfg = FeederConfig(**data)
        trace = LossInWeightFeeder(cfg).simulate(args.duration, args.dt, seed=args.seed)
    except (ValidationError, ValueError) as exc:
        raise SystemExit(f"invalid feeder configuration: {exc}") from None
    out = _out(args.out)
    trace.to_frame().to_csv(out / "trace.csv", index=False)
    _save(plot_feeder_trace(trace), out / "feeder.png")
    grav = ~trace.volumetric
    summary = {
        "config": cfg.model_dump(),
        "refills": trace.refills,
        "mean_flow_kg_h_gravimetric": float(trace.mass_flow_kg_h[grav].mean())
        if grav.any()
        else None,
        "std_flow_kg_h_gravimetric": float(trace.mass_flow_kg_h[grav].std())
        if grav.any()
        else None,
        "max_flow_kg_h": float(trace.mass_flow_kg_h.max()),
        "dispensed_kg": trace.dispensed_kg(),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps({k: v for k, v in summary.items() if k != "config"}, indent=2))
    print(f"wrote {out}/trace.csv, feeder.png, summary.json")
    return 0


def _feeder_fit_ff(args: argparse.Namespace) -> int:
    import numpy as np
    import pandas as pd
    from matplotlib.figure import Figure

    from twin_core.feeder import fit_feed_factor

    data = pd.read_csv(args.data)
    for c in (args.weight_col, args.ff_col):
        if c not in data.columns:
            raise SystemExit(f"{args.data} lacks column {c!r}; it has {list(data.columns)}")
    try:
        fit = fit_feed_factor(data[args.weight_col], data[args.ff_col])
    except (ValueError, RuntimeError) as exc:
        raise SystemExit(f"fit failed: {exc}") from None
    print(json.dumps(fit.as_dict(), indent=2))
    if args.out:
        out = _out(args.out)
        (out / "fit.json").write_text(json.dumps(fit.as_dict(), indent=2))
        fig = Figure(figsize=(6, 4), layout="constrained")
        ax = fig.subplots()
        ax.plot(data[args.weight_col], data[args.ff_col], ".", ms=3, label="data")
        w = np.linspace(0, float(data[args.weight_col].max()), 200)
        ax.plot(w, fit.predict(w), "r-", label=f"Eq. (2), R$^2$ = {fit.r2:.3f}")
        ax.set_xlabel(args.weight_col)
        ax.set_ylabel(args.ff_col)
        ax.legend()
        _save(fig, out / "feed_factor_fit.png")
        print(f"wrote {out}/fit.json, feed_factor_fit.png")
    return 0
