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
    from twin_core.calibration import SEED_LEVELS
    from twin_core.calibration.studies import design_study

    if args.levels and args.factors:
        raise SystemExit("give --levels or --factors, not both")
    factors: Any = args.factors or (_read_mapping(args.levels) if args.levels else SEED_LEVELS)
    try:
        d, props = design_study(
            factors,
            args.out,
            extra_runs=not args.no_extra_runs,
            randomize=args.randomize,
            seed=args.seed,
        )
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    print(d.physical.to_string())
    print(
        f"{d.n_runs} runs, {len(d.coded.columns)} factors; max |r|: "
        + ", ".join(f"{k} {v:.3g}" for k, v in props.items())
    )
    print(f"wrote {args.out}/design_physical.csv, design_coded.csv, correlation_map.png")
    return 0


# --------------------------------------------------------------------------- fit
def _factor_list(args: argparse.Namespace, table: Any) -> list[str]:
    from twin_core.calibration import SEED_FACTORS

    factors = _list(args.factors) or SEED_FACTORS
    missing = [f for f in factors if f not in table.columns]
    if missing:
        raise SystemExit(f"table lacks factor column(s) {missing}; pass --factors")
    return factors


def _response_list(args: argparse.Namespace, table: Any, factors: list[str]) -> list[str]:
    """--responses, or every numeric column that is not a factor or bookkeeping."""
    import pandas as pd

    skip = {"run", "seed", "elapsed_s", "R2", *factors}
    responses = _list(args.responses) or [
        c
        for c in table.columns
        if c not in skip and not c.endswith("_used") and pd.api.types.is_numeric_dtype(table[c])
    ]
    if not responses:
        raise SystemExit("no response columns found; pass --responses")
    return responses


def _fit(args: argparse.Namespace) -> int:
    from twin_core.calibration.studies import fit_study

    table = _load_table(args.table)
    factors = _factor_list(args, table)
    try:
        study = fit_study(
            table,
            factors,
            _response_list(args, table, factors),
            args.out,
            terms=_list(args.terms),
            criterion=args.criterion,
            direction=args.direction,
            predict=_load_table(args.predict) if args.predict else None,
            figures=not args.no_figures,
        )
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    for m in study.models.values():
        print(m.report() + "\n")
    print(study.summary.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    if study.predictions is not None:
        print(study.predictions.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    if args.out:
        print(f"wrote {args.out}/summary.csv, models.json, report.txt, parity.png, profiler_*.png")
    return 0


# --------------------------------------------------------------------------- solve
def _solve(args: argparse.Namespace) -> int:
    from twin_core.calibration.studies import inverse_study

    table = _load_table(args.table)
    opts = {k: getattr(args, k) for k in ("criterion", "starts", "method", "rule", "seed")}
    try:
        study = inverse_study(
            table,
            _factor_list(args, table),
            _pairs(args.targets, "--targets"),
            _list(args.unknowns) or [],
            args.out,
            bounds=_bounds(args.bounds),
            fixed=_pairs(args.fixed, "--fixed"),
            contour=_list(args.contour) or [],
            **opts,
        )
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    res = study.result
    print(f"fixed: {study.fixed}")
    print(res.table().to_string(index=False, float_format=lambda v: f"{v:.5g}"))
    print(f"{res.diagnosis}\nrecommended ({res.rule}):")
    if res.recommended is not None:
        print("  " + ", ".join(f"{k} = {v:.5g}" for k, v in res.recommended.params.items()))
    if study.files:
        print(f"wrote {args.out}/" + ", ".join(study.files))
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
    from twin_core.calibration.studies import feeder_study

    data: dict[str, Any] = _read_mapping(args.config) if args.config else {}
    if args.overrides:
        for item in args.overrides.split(","):
            if "=" not in item:
                raise SystemExit(f"--set must look like FIELD=VALUE,...; got {item!r}")
            k, v = item.split("=", 1)
            data[k.strip()] = _coerce(v.strip())
    try:
        summary = feeder_study(data, args.duration, args.dt, args.seed, args.out)
    except ValueError as exc:
        raise SystemExit(f"invalid feeder configuration: {exc}") from None
    print(json.dumps({k: v for k, v in summary.items() if k != "config"}, indent=2))
    print(f"wrote {args.out}/trace.csv, feeder.png, summary.json")
    return 0


def _feeder_fit_ff(args: argparse.Namespace) -> int:
    import pandas as pd

    from twin_core.calibration.studies import feed_factor_study

    data = pd.read_csv(args.data)
    try:
        fit = feed_factor_study(data, args.weight_col, args.ff_col, args.out)
    except ValueError as exc:
        raise SystemExit(f"{args.data}: {exc}") from None
    print(json.dumps(fit.as_dict(), indent=2))
    if args.out:
        print(f"wrote {args.out}/fit.json, feed_factor_fit.png")
    return 0
