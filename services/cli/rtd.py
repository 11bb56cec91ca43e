"""``twin rtd``: analyze tracer profiles, funnel plots, lot boundaries, seed reproduction.

twin rtd analyze FILE [--fit MODEL|all|none] [preprocessing] --out DIR
twin rtd analyze FILE1 FILE2 [...] [--fit MODEL] [preprocessing] --out DIR   (repeat pulses)
twin rtd lots FILE [--fit MODEL] [--disturbance START END] [preprocessing] --out DIR
twin rtd funnel FILE [--compare FILE2] [--fit MODEL] [--limit 5] [preprocessing] --out DIR
twin rtd reproduce --out DIR [--seed 0] [--repeats 3]

Preprocessing (all three): --outliers/--no-outliers, --denoise METHOD|auto|none,
--truncate SPEC|none, --baseline auto|none|VALUE, or --raw for none of it. Files: blank rows and
missing values are skipped with a warning naming each line (--strict refuses them); units from
the header (``time [s]``, ``time (min)`` or the wire contract's suffixes ``time_s``,
``concentration_pct_w_w``) or --time-unit / --conc-unit. The analyses are
``twin_core.quality.analysis`` (analyze, lots, funnel_analysis), the reproduction
``twin_core.quality.reproduce.reproduce_chapter6``; the figures ``twin_core.{rtd,quality}.plots``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

#: the default of --time-limit as the help states it (a test holds it equal to
#: ``rtd.likelihood.TIME_LIMIT_S``, which the parser does not import)
_DEFAULT_TIME_LIMIT_HELP = "30"


def _profile_options(q: argparse.ArgumentParser, repeats: bool = False) -> None:
    if repeats:
        q.add_argument(
            "file",
            type=Path,
            nargs="+",
            help="CSV (or ; / tab separated) lab export; several: repeat pulses of one system, "
            "analysed jointly (lack of fit combined, estimates pooled)",
        )
    else:
        q.add_argument("file", type=Path, help="CSV (or ; / tab separated) lab export")
    q.add_argument("--time-col", default=None, help="time column: name or number (1 = first)")
    q.add_argument("--conc-col", default=None, help="concentration column: name or number")
    q.add_argument("--time-unit", default=None, help="s, ms, min or h, if not in the header")
    q.add_argument(
        "--conc-unit",
        default=None,
        help="%%, %% w/w, mg/g or fraction, if not in the header (converted to %% w/w)",
    )
    q.add_argument(
        "--strict",
        action="store_true",
        help="refuse blank rows and missing values (NaN, empty) naming line and column "
        "(default: skipped, each line named in a warning)",
    )


def _preprocess_options(q: argparse.ArgumentParser) -> None:
    g = q.add_argument_group("preprocessing (presentation and empirical results)")
    g.add_argument(
        "--outliers",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="Hampel outlier replacement (default on)",
    )
    g.add_argument(
        "--denoise", default="auto", help="sa | sa_centred | sg | fft | wavelet | auto | none"
    )
    g.add_argument(
        "--truncate",
        default="pat",
        help="pat[:K[@T]] (default pat: mu + 3 sd of the baseline after the tracer) | time:S | "
        "level:C | rel:F | none",
    )
    g.add_argument(
        "--baseline",
        default="auto",
        help="auto (estimated, fitted) | none (0) | VALUE in %% w/w",
    )
    g.add_argument("--raw", action="store_true", help="no preprocessing and a baseline of 0")


def _fit_options(q: argparse.ArgumentParser, default: str) -> None:
    # no twin_core import here: building the parser of every `twin` command stays free of scipy
    q.add_argument(
        "--fit",
        default=default,
        help="ad_open | ad_closed | tis | ... (an unknown name lists all models) | all (ranked "
        f"by BIC) | none (default {default})",
    )
    q.add_argument(
        "--time-limit",
        type=float,
        default=None,
        help=f"CPU seconds per fitted model (default {_DEFAULT_TIME_LIMIT_HELP})",
    )


def _time_limit(args: argparse.Namespace) -> float:
    """--time-limit, or the library's default (``rtd.likelihood.TIME_LIMIT_S``)."""
    from twin_core.rtd.likelihood import TIME_LIMIT_S

    return TIME_LIMIT_S if args.time_limit is None else args.time_limit


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "rtd", help="residence time distributions: analyze, funnel, lots, reproduce"
    )
    sub = p.add_subparsers(dest="rtd_command", metavar="SUBCOMMAND")
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])

    a = sub.add_parser(
        "analyze", help="preprocessing, fit with intervals and lack of fit -> JSON, CSV, figure"
    )
    _profile_options(a, repeats=True)
    _preprocess_options(a)
    _fit_options(a, "ad_open")
    a.add_argument("--out", type=Path, required=True)
    a.set_defaults(func=_analyze)

    f = sub.add_parser("funnel", help="funnel plot (max %% deviation over duration x intensity)")
    _profile_options(f)
    f.add_argument("--compare", type=Path, default=None, help="second profile: overlay, difference")
    f.add_argument("--limit", type=float, default=5.0, help="deviation limit in %% (default 5)")
    f.add_argument("--durations", default="0:60:200", help="start:stop:count in s")
    f.add_argument("--intensities", default="0:50:200", help="start:stop:count in %% of nominal")
    _preprocess_options(f)
    _fit_options(f, "none")
    f.add_argument("--out", type=Path, required=True)
    f.set_defaults(func=_funnel)

    lo = sub.add_parser("lots", help="lot boundaries (0.5 %% / 99.5 %% of F), diversion window")
    _profile_options(lo)
    lo.add_argument("--lower", type=float, default=0.005)
    lo.add_argument("--upper", type=float, default=0.995)
    lo.add_argument("--disturbance", type=float, nargs=2, metavar=("START", "END"), default=None)
    _preprocess_options(lo)
    _fit_options(lo, "none")
    lo.add_argument("--out", type=Path, required=True)
    lo.set_defaults(func=_lots)

    r = sub.add_parser("reproduce", help="the seed's chapter 6 analyses on the synthetic campaign")
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--repeats", type=int, default=3, help="repeats per tracer amount (seed: 3)")
    r.set_defaults(func=_reproduce)


# ------------------------------------------------------------------------------------------------


def _load(args: argparse.Namespace, path: Path | None = None):
    from twin_core.rtd.profiles import load_csv

    return load_csv(
        path or args.file,
        time_unit=args.time_unit,
        conc_unit=args.conc_unit,
        time_col=args.time_col,
        conc_col=args.conc_col,
        strict=args.strict,
    )


def _preprocessing(args: argparse.Namespace):
    from twin_core.rtd.pipeline import Preprocessing

    if args.raw:
        return Preprocessing.none()
    off = lambda v: None if v is None or v.strip().lower() == "none" else v  # noqa: E731
    return Preprocessing(args.outliers, off(args.denoise), off(args.truncate), args.baseline)


def _model(args: argparse.Namespace) -> str | None:
    return None if args.fit.strip().lower() == "none" else args.fit


def _range(spec: str, name: str) -> np.ndarray:
    try:
        a, b, n = spec.split(":")
        return np.linspace(float(a), float(b), int(n))
    except ValueError:
        raise ValueError(f"{name} must be start:stop:count, got {spec!r}") from None


def _finish(out: Path, name: str, report: dict, summary: dict) -> int:
    """Write ``name``.json; print the warnings and a one-line JSON summary on stdout."""
    from twin_core.quality.analysis import json_default

    (out / f"{name}.json").write_text(json.dumps(report, indent=2, default=json_default))
    for w in report.get("warnings", []):
        print(f"WARNING: {w}")
    print(json.dumps({"out": str(out), **summary}, default=json_default))
    return 0


def _fail(exc: Exception) -> int:
    print(f"error: {exc}", file=sys.stderr)
    return 2


def _analyze(args: argparse.Namespace) -> int:
    from twin_core.quality.analysis import analyze
    from twin_core.rtd.plots import plot_profile

    if len(args.file) > 1:
        return _analyze_repeats(args)
    try:
        res = analyze(
            _load(args, args.file[0]),
            _preprocessing(args),
            _model(args),
            time_limit_s=_time_limit(args),
        )
        args.out.mkdir(parents=True, exist_ok=True)
        p, s = res.processed, res.summary
        measured = p.profile.c if p.measured is None else np.where(p.measured, p.profile.c, np.nan)
        cols = {"t_s": p.t, "measured_pct_w_w": measured, "processed_pct_w_w": p.y}
        if s is not None:
            cols["fitted_pct_w_w"] = s.fit.fitted
        _write_csv(args.out / "profile.csv", cols)
        plot_profile(p, s, res.warnings).savefig(args.out / "profile.png", dpi=120)
        report = res.as_dict()
        summary = {k: report[k] for k in ("adequate", "warnings")}
        summary |= {"model": s.fit.model, "derived": report["derived"]} if s else {}
        return _finish(args.out, "report", report, summary)
    except (ValueError, OSError) as exc:
        return _fail(exc)


def _analyze_repeats(args: argparse.Namespace) -> int:
    """Several files: repeat pulses of one system (``quality.analysis.analyze_repeats``)."""
    from twin_core.quality.analysis import analyze_repeats
    from twin_core.quality.plots import plot_repeats

    try:
        model = _model(args)
        if model is None or model.strip().lower() == "all":
            raise ValueError(f"--fit must name one model for repeat pulses, got {args.fit!r}")
        res = analyze_repeats(
            [_load(args, f) for f in args.file],
            _preprocessing(args),
            model,
            time_limit_s=_time_limit(args),
        )
        args.out.mkdir(parents=True, exist_ok=True)
        rows = {"quantity": list(res.pooled)}
        for i in range(len(res.repeats)):
            rows[f"repeat_{i + 1}"] = [v.values[i] for v in res.pooled.values()]
            rows[f"repeat_{i + 1}_stderr"] = [v.stderrs[i] for v in res.pooled.values()]
        rows["pooled"] = [v.value for v in res.pooled.values()]
        rows["pooled_ci_low"] = [v.ci[0] for v in res.pooled.values()]
        rows["pooled_ci_high"] = [v.ci[1] for v in res.pooled.values()]
        rows["repeats_agree"] = [v.agree for v in res.pooled.values()]
        _write_csv(args.out / "repeats.csv", rows)
        plot_repeats(res).savefig(args.out / "repeats.png", dpi=120)
        report = res.as_dict()
        summary = {
            "adequate": res.adequate,
            "joint_lack_of_fit_p": res.joint.p_value,
            "model": model,
            "repeats": len(res.repeats),
            "pooled": {k: v.as_dict() for k, v in res.pooled.items() if k in _POOLED_SHOWN},
            "warnings": res.warnings,
        }
        return _finish(args.out, "report", report, summary)
    except (ValueError, OSError) as exc:
        return _fail(exc)


#: pooled quantities printed on stdout (all are in report.json and repeats.csv)
_POOLED_SHOWN = ("mean_residence_time_s", "variance_s2", "t_lo_s", "t_hi_s")


def _write_csv(path: Path, columns: dict) -> None:
    import pandas as pd

    pd.DataFrame(columns).to_csv(path, index=False)


def _funnel(args: argparse.Namespace) -> int:
    from twin_core.quality.analysis import funnel_analysis
    from twin_core.quality.plots import plot_funnel, plot_funnel_difference

    try:
        d = _range(args.durations, "durations")
        h = _range(args.intensities, "intensities")
        profiles = [_load(args)] + ([_load(args, args.compare)] if args.compare else [])
        res = funnel_analysis(
            profiles, _preprocessing(args), _model(args), d, h, args.limit, _time_limit(args)
        )
        args.out.mkdir(parents=True, exist_ok=True)
        cols = {"duration_s": d}
        for label, f, band in zip(res.labels, res.funnels, res.bands):
            cols[f"max_window_fraction[{label}]"] = f.m
            cols[f"critical_intensity_pct[{label}]"] = f.h_crit
            if band is not None:
                cols[f"model_critical_intensity_pct[{label}]"] = band.h_crit
                cols[f"model_ci_low[{label}]"] = band.lower
                cols[f"model_ci_high[{label}]"] = band.upper
        _write_csv(args.out / "funnel.csv", cols)
        plot_funnel(res).savefig(args.out / "funnel.png", dpi=120)
        if len(res.funnels) == 2:
            plot_funnel_difference(res).savefig(args.out / "funnel_difference.png", dpi=120)
        report = res.as_dict()
        return _finish(args.out, "funnel", report, report)
    except (ValueError, OSError) as exc:
        return _fail(exc)


def _lots(args: argparse.Namespace) -> int:
    from twin_core.quality.analysis import lots
    from twin_core.quality.plots import plot_lots

    try:
        res = lots(
            _load(args),
            _preprocessing(args),
            _model(args),
            args.lower,
            args.upper,
            tuple(args.disturbance) if args.disturbance else None,
            _time_limit(args),
        )
        args.out.mkdir(parents=True, exist_ok=True)
        _write_csv(args.out / "lots.csv", res.curves())
        plot_lots(res).savefig(args.out / "lots.png", dpi=120)
        report = res.as_dict()
        summary = {k: v for k, v in report.items() if k != "preprocessing"}
        return _finish(args.out, "lots", report, summary)
    except (ValueError, OSError) as exc:
        return _fail(exc)


def _reproduce(args: argparse.Namespace) -> int:
    from twin_core.quality.analysis import json_default
    from twin_core.quality.reproduce import reproduce_chapter6

    try:
        meta = reproduce_chapter6(args.out, args.seed, args.repeats, sys.stderr.isatty())
    except (ValueError, OSError) as exc:
        return _fail(exc)
    print(json.dumps(meta, default=json_default))
    return 0
