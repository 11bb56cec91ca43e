"""``twin rtd``: analyze tracer profiles, funnel plots, lot boundaries, seed reproduction.

twin rtd analyze FILE.csv [--outliers] [--denoise METHOD|auto] [--truncate SPEC]
                 [--fit MODEL] --out DIR
twin rtd funnel FILE.csv [--limit 5] --out DIR
twin rtd lots FILE.csv [--lower 0.005 --upper 0.995] [--disturbance START END]
twin rtd reproduce --out DIR [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

log = logging.getLogger("twin.rtd")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "rtd", help="residence time distributions: analyze, funnel, lots, reproduce"
    )
    sub = p.add_subparsers(dest="rtd_command", metavar="SUBCOMMAND")
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])

    def common(q: argparse.ArgumentParser) -> None:
        q.add_argument("file", type=Path, help="CSV with header 'time [s],concentration [% w/w]'")
        q.add_argument(
            "--time-unit", default=None, help="time unit if not in the header (s, ms, min, h)"
        )
        q.add_argument("--conc-unit", default=None, help="concentration unit if not in the header")

    a = sub.add_parser(
        "analyze", help="outliers, denoising, truncation, model fit -> JSON + figures"
    )
    common(a)
    a.add_argument("--outliers", action="store_true", help="Hampel outlier removal first")
    a.add_argument(
        "--denoise",
        default=None,
        help="sa | sa_centred | sg | fft | wavelet | auto (default: none)",
    )
    a.add_argument("--truncate", default=None, help="time:S | level:C | rel:F | pat:K[@T]")
    a.add_argument(
        "--fit",
        default=None,
        help="ad_open | ad_closed | tis | cstr_pfr | emg | zusatz | ad_open_dead | ad_open_bypass "
        "| tis_bypass | all",
    )
    a.add_argument(
        "--scale",
        choices=("free", "fixed"),
        default="free",
        help="fit E with a free amplitude (default; robust to a noisy area) or fixed to 1 (seed)",
    )
    a.add_argument(
        "--weighted",
        action="store_true",
        help="two-stage weighted fit with the variance model a + b y^2 (proportional noise)",
    )
    a.add_argument("--out", type=Path, required=True)
    a.set_defaults(func=_analyze)

    f = sub.add_parser("funnel", help="funnel plot (max %% deviation over duration x intensity)")
    common(f)
    f.add_argument("--limit", type=float, default=5.0, help="deviation limit in %% (default 5)")
    f.add_argument("--durations", default="0:60:200", help="start:stop:count in s")
    f.add_argument("--intensities", default="0:50:200", help="start:stop:count in %% of nominal")
    f.add_argument("--denoise", default=None, help="denoise first (method name or auto)")
    f.add_argument(
        "--compare",
        type=Path,
        default=None,
        help="second profile: overlay and difference of funnels",
    )
    f.add_argument("--out", type=Path, required=True)
    f.set_defaults(func=_funnel)

    lo = sub.add_parser("lots", help="lot boundaries (0.5 %% / 99.5 %% of F) and diversion window")
    common(lo)
    lo.add_argument("--lower", type=float, default=0.005)
    lo.add_argument("--upper", type=float, default=0.995)
    lo.add_argument("--disturbance", type=float, nargs=2, metavar=("START", "END"), default=None)
    lo.set_defaults(func=_lots)

    r = sub.add_parser(
        "reproduce", help="run the seed's chapter 6 analyses on the synthetic campaign"
    )
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--repeats", type=int, default=3, help="repeats per tracer amount (seed: 3)")
    r.set_defaults(func=_reproduce)


# ------------------------------------------------------------------------------------------------


def _load(args: argparse.Namespace):
    from twin_core.rtd.profiles import load_csv

    return load_csv(args.file, time_unit=args.time_unit, conc_unit=args.conc_unit)


def _range(spec: str, name: str) -> np.ndarray:
    try:
        a, b, n = spec.split(":")
        return np.linspace(float(a), float(b), int(n))
    except ValueError:
        raise ValueError(f"{name} must be start:stop:count, got {spec!r}") from None


def _dumps(obj: dict, **kw) -> str:
    from twin_core.quality.analysis import json_default

    return json.dumps(obj, default=json_default, **kw)


def _write_json(path: Path, obj: dict) -> None:
    path.write_text(_dumps(obj, indent=2))


def _fail(exc: Exception) -> int:
    print(f"error: {exc}", file=sys.stderr)
    return 2


def _analyze(args: argparse.Namespace) -> int:
    from twin_core.quality.analysis import analyze_profile
    from twin_core.rtd.plots import plot_profile

    try:
        prof = _load(args)
        opts = {k: getattr(args, k) for k in ("outliers", "denoise", "truncate", "fit", "scale")}
        a = analyze_profile(prof, weighted=args.weighted, **opts)
    except ValueError as exc:
        return _fail(exc)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    _write_json(out / "report.json", {"file": str(args.file), **a.report})
    fig = plot_profile(prof.t, prof.c, a.processed, a.e, prof.conc_unit, a.outliers, a.fits)
    fig.savefig(out / "profile.png", dpi=120)
    print(_dumps({"out": str(out), "moments": a.report["moments"]}))
    return 0


def _funnel(args: argparse.Namespace) -> int:
    from twin_core.quality.analysis import profile_funnels
    from twin_core.rtd.plots import plot_funnel_difference, plot_funnels
    from twin_core.rtd.profiles import load_csv

    try:
        durations = _range(args.durations, "durations")
        intensities = _range(args.intensities, "intensities")
        profiles = [_load(args)]
        if args.compare is not None:
            profiles.append(load_csv(args.compare, args.time_unit, args.conc_unit))
        funnels, res = profile_funnels(profiles, durations, intensities, args.limit, args.denoise)
    except ValueError as exc:
        return _fail(exc)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    cols, header = [durations], ["duration_s"]
    for k, v in funnels.items():
        cols += [v.m, v.h_crit]
        header += [f"max_window_fraction[{k}]", f"critical_intensity_pct[{k}]"]
    table = np.column_stack(cols)
    np.savetxt(out / "funnel.csv", table, delimiter=",", header=",".join(header), comments="")
    title = "funnel plot" if len(funnels) == 1 else "funnel overlay"
    plot_funnels(funnels, title).savefig(out / "funnel.png", dpi=120)
    if len(funnels) == 2:
        fig = plot_funnel_difference(*funnels.values())
        fig.savefig(out / "funnel_difference.png", dpi=120)
    _write_json(out / "funnel.json", res)
    print(_dumps(res))
    return 0


def _lots(args: argparse.Namespace) -> int:
    from twin_core.quality.lots import diversion_window, lot_boundaries

    try:
        prof = _load(args)
        c = np.clip(prof.c, 0, None)
        lo, hi = lot_boundaries(prof.t, c, args.lower, args.upper)
        res = {"t_lo_s": lo, "t_hi_s": hi, "lower": args.lower, "upper": args.upper}
        if args.disturbance:
            s, e = diversion_window(*args.disturbance, prof.t, c, args.lower, args.upper)
            res["diversion_window_s"] = [s, e]
        print(json.dumps(res))
        return 0
    except ValueError as exc:
        return _fail(exc)


def _reproduce(args: argparse.Namespace) -> int:
    from twin_core.quality.reproduce import reproduce_chapter6

    try:
        meta = reproduce_chapter6(args.out, args.seed, args.repeats, sys.stderr.isatty())
    except ValueError as exc:
        return _fail(exc)
    print(_dumps(meta))
    return 0
