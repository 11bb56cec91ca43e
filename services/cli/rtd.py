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


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _load(args: argparse.Namespace):
    from twin_core.rtd.profiles import load_csv

    return load_csv(args.file, time_unit=args.time_unit, conc_unit=args.conc_unit)


def _range(spec: str, name: str) -> np.ndarray:
    try:
        a, b, n = spec.split(":")
        return np.linspace(float(a), float(b), int(n))
    except ValueError:
        raise ValueError(f"{name} must be start:stop:count, got {spec!r}") from None


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(type(o))


def _write_json(path: Path, obj: dict) -> None:
    path.write_text(json.dumps(obj, indent=2, default=_json_default))


def _fail(exc: Exception) -> int:
    print(f"error: {exc}", file=sys.stderr)
    return 2


def _analyze(args: argparse.Namespace) -> int:
    from twin_core.quality.lots import lot_boundaries
    from twin_core.rtd import denoise as D
    from twin_core.rtd.fitting import compare_models, fit
    from twin_core.rtd.metrics import denoise_metrics, fwhm
    from twin_core.rtd.models import MODELS
    from twin_core.rtd.noise import characterize
    from twin_core.rtd.outliers import hampel
    from twin_core.rtd.profiles import e_curve, moments
    from twin_core.rtd.truncation import parse_spec

    try:
        prof = _load(args)
        out: Path = args.out
        out.mkdir(parents=True, exist_ok=True)
        t, y0 = prof.t, prof.c
        report: dict = {"file": str(args.file), "n": int(t.size), "conc_unit": prof.conc_unit}
        report["moments_raw"] = moments(t, y0).__dict__
        y = y0.copy()
        if args.outliers:
            r = hampel(y, t=t)
            y = r.y
            report["outliers"] = {
                "count": r.count,
                "indices": r.indices,
                "times": t[r.indices],
                "original": r.original,
            }
        y_clean = y.copy()
        if args.denoise:
            steps = np.diff(t)
            if np.ptp(steps) > 0.01 * np.median(steps):
                raise ValueError("denoise needs uniformly sampled t (steps vary by more than 1 %)")
            d = D.denoise(y, args.denoise)
            y = d.y
            report["denoise"] = {
                "method": d.method,
                "params": d.params,
                "risk": d.risk,
                "metrics": denoise_metrics(t, y_clean, y),
            }
        if args.truncate:
            spec = parse_spec(args.truncate)
            y = spec.apply(t, y)
            report["truncate"] = {
                "kind": spec.kind,
                "value": spec.value,
                "zeroed": int(np.sum(y == 0)),
            }
        e = e_curve(t, y)
        report["moments"] = moments(t, y).__dict__
        if not report["moments"]["variance"] > 0 or np.min(y) < -0.01 * np.max(y):
            report["moments_note"] = (
                "negative values (baseline noise/offset) distort the moments and the area; "
                "consider --truncate pat:3"
            )
        report["height"] = float(np.max(y))
        report["fwhm_s"] = fwhm(t, y)
        lo, hi = lot_boundaries(t, np.clip(y, 0, None))
        report["lot_boundaries_s"] = [lo, hi]
        fits = []
        if args.fit:
            names = list(MODELS) if args.fit == "all" else [args.fit]
            sig = "auto" if args.weighted else None
            fits = (
                compare_models(t, e, names, scale=args.scale, sigma=sig)
                if len(names) > 1
                else [fit(t, e, names[0], scale=args.scale, sigma=sig)]
            )
            report["fits"] = [f.as_dict() for f in fits]
            if fits:
                best = fits[0]
                resid_fit = best.fitted * np.trapezoid(y, t)  # back to concentration units
                report["noise"] = characterize(t, y_clean, resid_fit).as_dict()
        _write_json(out / "report.json", report)
        plt = _plt()
        fig, ax = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
        ax[0].plot(t, y0, ".", ms=3, color="0.6", label="measured")
        if args.outliers and report["outliers"]["count"]:
            idx = report["outliers"]["indices"]
            ax[0].plot(t[idx], y0[idx], "rx", label="outliers")
        ax[0].plot(t, y, "C0", lw=1.5, label="processed")
        ax[0].set_ylabel(f"C ({prof.conc_unit})")
        ax[0].legend()
        ax[1].plot(t, e, "C0", label="E(t) processed")
        for f in fits[:3]:
            ax[1].plot(t, f.fitted, "--", label=f"{f.model} (AIC {f.aic:.0f})")
        ax[1].set_xlabel("t (s)")
        ax[1].set_ylabel("E (1/s)")
        ax[1].legend()
        fig.tight_layout()
        fig.savefig(out / "profile.png", dpi=120)
        plt.close(fig)
        print(json.dumps({"out": str(out), "moments": report["moments"]}, default=_json_default))
        return 0
    except ValueError as exc:
        return _fail(exc)


def _plot_funnel(path: Path, funnels: dict, title: str) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 5))
    first = next(iter(funnels.values()))
    if len(funnels) == 1:
        cs = ax.contourf(
            first.durations, first.intensities, first.max_dev.T, levels=20, cmap="viridis"
        )
        fig.colorbar(cs, ax=ax, label="max deviation (%)")
    for i, (label, f) in enumerate(funnels.items()):
        ax.plot(
            f.durations,
            np.clip(f.h_crit, 0, f.intensities.max()),
            color=f"C{i + 1}",
            lw=2,
            label=f"{label}",
        )
    ax.set_xlabel("disturbance duration (s)")
    ax.set_ylabel("disturbance intensity (% of nominal)")
    ax.set_ylim(first.intensities.min(), first.intensities.max())
    ax.set_title(title)
    ax.legend(title=f"limit {first.limit:g} %", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _funnel(args: argparse.Namespace) -> int:
    from twin_core.quality.funnel import compare_funnels, funnel
    from twin_core.rtd import denoise as D
    from twin_core.rtd.profiles import e_curve, load_csv

    try:
        durations = _range(args.durations, "durations")
        intensities = _range(args.intensities, "intensities")
        profiles = [_load(args)]
        if args.compare is not None:
            profiles.append(
                load_csv(args.compare, time_unit=args.time_unit, conc_unit=args.conc_unit)
            )
        funnels = {}
        for i, prof in enumerate(profiles):
            y = prof.c if not args.denoise else D.denoise(prof.c, args.denoise).y
            label = prof.name or f"profile {i + 1}"
            if label in funnels:
                label = f"{label} ({i + 1})"
            funnels[label] = funnel(prof.t, e_curve(prof.t, y), durations, intensities, args.limit)
        out: Path = args.out
        out.mkdir(parents=True, exist_ok=True)
        f = next(iter(funnels.values()))
        res = {"funnels": {k: v.as_dict() for k, v in funnels.items()}}
        cols = [f.durations]
        header = ["duration_s"]
        for k, v in funnels.items():
            cols += [v.m, v.h_crit]
            header += [f"max_window_fraction[{k}]", f"critical_intensity_pct[{k}]"]
        np.savetxt(
            out / "funnel.csv",
            np.column_stack(cols),
            delimiter=",",
            header=",".join(header),
            comments="",
        )
        _plot_funnel(
            out / "funnel.png", funnels, "funnel plot" if len(funnels) == 1 else "funnel overlay"
        )
        if len(funnels) == 2:
            a, b = funnels.values()
            res["comparison"] = compare_funnels(a, b)
            plt = _plt()
            fig, ax = plt.subplots(figsize=(6.5, 5))
            diff = (b.max_dev - a.max_dev).T
            lim = float(np.max(np.abs(diff))) or 1.0
            cs = ax.pcolormesh(a.durations, a.intensities, diff, cmap="RdBu_r", vmin=-lim, vmax=lim)
            fig.colorbar(cs, ax=ax, label="max deviation, second - first (%)")
            ax.set_xlabel("disturbance duration (s)")
            ax.set_ylabel("disturbance intensity (% of nominal)")
            ax.set_title("funnel difference")
            fig.tight_layout()
            fig.savefig(out / "funnel_difference.png", dpi=120)
            plt.close(fig)
        _write_json(out / "funnel.json", res)
        print(json.dumps(res, default=_json_default))
        return 0
    except ValueError as exc:
        return _fail(exc)


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
    from tqdm import tqdm

    from twin_core.rtd import reproduce as R
    from twin_core.rtd.synthetic import generate_campaign

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    from twin_core.rtd.synthetic import CampaignConfig

    if args.repeats < 2:
        print(f"error: repeats must be >= 2, got {args.repeats}", file=sys.stderr)
        return 2
    runs = generate_campaign(args.seed, CampaignConfig(repeats=args.repeats))
    ten = [r for r in runs if r.amount_g == 10.0]  # the seed's truncation runs
    plt = _plt()
    steps = tqdm(total=6, desc="reproduce", disable=not sys.stderr.isatty())

    # Table 6.1
    long, summ = R.denoise_table(runs)
    long.to_csv(out / "table_6_1_runs.csv", index=False)
    summ.to_csv(out / "table_6_1.csv", index=False)
    fig, axs = plt.subplots(1, 2, figsize=(12, 4.5))
    run = runs[0]
    y = R.clean(run)
    axs[0].plot(run.t, run.c, ".", color="0.7", ms=3, label="measured")
    axs[0].plot(run.t, run.c_true + run.baseline_offset, "k", lw=1, label="truth")
    for name in ("SA", "WT", "SV", "FFT"):
        axs[0].plot(run.t, R.apply_method(y, R.SEED_METHODS[name]), lw=1, label=name)
    axs[0].set_xlim(0, 100)
    axs[0].set_xlabel("t (s)")
    axs[0].set_ylabel("C (% w/w)")
    axs[0].legend()
    axs[0].set_title(f"run {run.name} (Fig. 6.10)")
    piv = summ.pivot(index="method", columns="amount_g", values="rmse_truth")
    piv.plot.bar(ax=axs[1])
    axs[1].set_ylabel("RMSE to truth (% w/w)")
    axs[1].set_title("denoising error against the known truth")
    fig.tight_layout()
    fig.savefig(out / "table_6_1.png", dpi=120)
    plt.close(fig)
    steps.update()

    # Table 6.2 / 6.3
    l2, s2 = R.truncation_table(ten)
    l2.to_csv(out / "table_6_2_runs.csv", index=False)
    s2.to_csv(out / "table_6_2.csv", index=False)
    fig, axs = plt.subplots(1, 3, figsize=(13, 4))
    sub = s2[s2.level != "PAT"]
    x = sub.level.astype(float) * 100
    for ax, par in zip(axs, ("tau_d", "tau", "pe")):
        ax.errorbar(
            x, sub[f"{par}_mean"], yerr=sub[f"{par}_std"], fmt="o-", label="noisy fits (n=3)"
        )
        ax.plot(x, sub[f"{par}_truthfit_mean"], "s--", label="fit of truncated truth")
        ax.axhline(sub[f"{par}_true_mean"].iloc[0], color="k", lw=0.8, label="true")
        for xi, yi, g in zip(x, sub[f"{par}_mean"], sub[f"{par}_group"]):
            ax.annotate(g, (xi, yi), textcoords="offset points", xytext=(4, 6), fontsize=8)
        ax.set_xlabel("truncation level (% of peak)")
        ax.set_title(par)
    axs[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "table_6_2.png", dpi=120)
    plt.close(fig)
    steps.update()

    # Fig. 6.16
    cases = R.funnel_cases(ten[0])
    R.funnel_summary(cases).to_csv(out / "fig_6_16_funnels.csv", index=False)
    rows = {"duration_s": R.DURATIONS}
    for case, fs in cases.items():
        for label, f in fs.items():
            rows[f"{case}:{label}"] = f.h_crit
    import pandas as pd

    pd.DataFrame(rows).to_csv(out / "fig_6_16_boundaries.csv", index=False)
    fig, axs = plt.subplots(2, 2, figsize=(11, 9))
    for ax, (case, fs) in zip(axs.ravel(), list(cases.items())[:4]):
        for i, (label, f) in enumerate(fs.items()):
            ax.plot(
                f.durations, np.clip(f.h_crit, 0, f.intensities.max()), color=f"C{i}", label=label
            )
        ax.set_title(case.replace("_", " "))
        ax.set_xlabel("duration (s)")
        ax.set_ylabel("intensity (% of nominal)")
        ax.legend(fontsize=8, title="feasible below the line")
    fig.tight_layout()
    fig.savefig(out / "fig_6_16.png", dpi=120)
    plt.close(fig)
    steps.update()

    # Fig. 6.17
    l3, s3 = R.oos_curve(ten)
    l3.to_csv(out / "fig_6_17_runs.csv", index=False)
    s3.to_csv(out / "fig_6_17.csv", index=False)
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for col, lab in (
        ("oos_increase_pct", "seed workflow (measured)"),
        ("oos_increase_pct_baseline_corrected", "baseline-corrected"),
        ("oos_increase_pct_truth", "noise-free truth"),
    ):
        ax.errorbar(s3.level * 100, s3[f"{col}_mean"], yerr=s3[f"{col}_std"], fmt="o-", label=lab)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("truncation level (% of peak height)")
    ax.set_ylabel("increase of OOS tablets (percentage points)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "fig_6_17.png", dpi=120)
    plt.close(fig)
    steps.update()

    # lots and noise
    R.lot_table(runs).to_csv(out / "lots.csv", index=False)
    steps.update()
    R.noise_table(runs).to_csv(out / "noise.csv", index=False)
    steps.update()
    steps.close()
    meta = {
        "seed": args.seed,
        "runs": [r.name for r in runs],
        "anova_p": s2.attrs.get("anova_p", {}),
        "files": sorted(p.name for p in out.iterdir()),
    }
    _write_json(out / "reproduce.json", meta)
    print(json.dumps(meta))
    return 0
