"""``twin close-loop``: find, explain and fix where the declared line model is wrong.

    twin close-loop RECORDING.mcap --config LINE.yaml --report OUT.json [--figures DIR]

RECORDING is an MCAP log of the line (feeder flows, NIR concentration, events; read with
``services.recording.load_line_data``). LINE.yaml is either a plain declared-line config
(``twin_core.plant.line_config_from_dict`` keys: name, feeders, blender, sensor, tracers) or a
live-twin ``schemas.line.LineSpec`` file. The report is validated against
``schemas.closeloop.CloseLoopReport``; ``--figures`` writes PNGs of measured vs predicted and of
the residuals, before and after.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("twin.closeloop")


def load_line_config(path: str | Path) -> Any:
    """A ``twin_core.plant.LineConfig`` from a YAML/JSON file (plain form or LineSpec)."""
    from schemas.base import read_mapping
    from twin_core.plant import line_config_from_dict

    data = read_mapping(path)
    if {"spec", "oos", "bus", "services", "dt_s"} & set(data):
        from schemas.line import LineSpec

        return LineSpec.model_validate(data).plant_config()
    return line_config_from_dict(data)


def run_data_from_line_data(line_data: Any, config: Any, name: str = "recording") -> Any:
    """``RunData`` on a uniform grid (the sensor period) from ``load_line_data``'s output.

    Flows are interpolated linearly between samples, refill flags taken from the nearest
    earlier sample, NIR readings matched to the nearest grid time within dt / 2 (else NaN);
    tracer pulses come from the ``tracer_pulse`` events (mass, component, duration; the
    config's tracers if the recording has none).
    """
    import pandas as pd

    from twin_core.closeloop import RunData
    from twin_core.plant import LineInputs, TracerPulse

    sig: pd.DataFrame = line_data.signals
    ev: pd.DataFrame = line_data.events
    comp = config.sensor.component
    conc_cols = [c for c in sig.columns if c.startswith("conc_") and c.endswith(f"_{comp}_pct_w_w")]
    if not conc_cols:
        raise ValueError(
            f"recording has no measured concentration of {comp!r} (conc_*_{comp}_pct_w_w)"
        )
    meas = sig[conc_cols[0]].dropna()
    dt = float(config.sensor.sample_period_s)
    t = np.arange(float(meas.index.min()), float(meas.index.max()) + 0.5 * dt, dt)
    idx = np.searchsorted(t, meas.index.values - 0.5 * dt)
    idx = np.clip(idx, 0, t.size - 1)
    ok = np.abs(t[idx] - meas.index.values) <= 0.5 * dt + 1e-9
    y = np.full(t.size, np.nan)
    y[idx[ok]] = meas.values[ok]
    flows, comps, refill, rpm = {}, {}, {}, {}
    for f in config.feeders:
        col = f"flow_{f.component}_kg_h"
        if col not in sig:
            raise ValueError(f"recording has no flow of feeder component {f.component!r} ({col})")
        s = sig[col].dropna()
        flows[f.name] = np.maximum(np.interp(t, s.index.values, s.values), 0.0)
        comps[f.name] = f.component
        rcol = f"refilling_{f.component}"
        if rcol in sig:
            r = sig[rcol].dropna()
            j = np.clip(np.searchsorted(r.index.values, t, side="right") - 1, 0, len(r) - 1)
            refill[f.name] = r.values[j] > 0.5
        scol = f"screw_speed_{f.component}_rpm"
        if scol in sig and sig[scol].notna().sum() >= 2:
            sp = sig[scol].dropna()
            rpm[f.name] = np.interp(t, sp.index.values, sp.values)
    tracers = []
    events = []
    for row in ev.to_dict("records") if len(ev) else []:
        events.append(
            {"t_s": float(row["t_s"]), "kind": str(row["kind"]), "source": str(row["source"])}
        )
        if row["kind"] == "tracer_pulse":
            mass = row.get("mass_kg")
            if mass is None or not math.isfinite(float(mass)):
                continue
            dur = row.get("duration_s")
            dur = float(dur) if dur is not None and math.isfinite(float(dur)) and dur > 0 else dt
            tracers.append(
                TracerPulse(float(row["t_s"]), float(mass), str(row.get("component") or comp), dur)
            )
    if not tracers:
        tracers = list(config.tracers)
    inputs = LineInputs(
        t_s=t,
        flows_kg_h=flows,
        components=comps,
        refilling=refill,
        tracers=tracers,
        screw_speed_rpm=rpm,
    )
    return RunData(t, y, inputs, events, name=name)


def write_figures(result: Any, out_dir: str | Path) -> list[str]:
    """PNG figures: measured vs predicted before/after, residuals before/after with ACF."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from twin_core.closeloop.diagnostics import _acf

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t = result.data.t_s
    y = result.ident.measured
    sp = result.ident.split
    pb, pa = result.predicted_before, result.predicted_after
    found = (
        "augmented: " + ", ".join(result.effects_found)
        if result.effects_found
        else f"no effect claimed ({result.status})"
    )
    paths = []

    def shade(ax):
        ho = t[sp.heldout]
        if ho.size:
            ax.axvspan(ho.min(), ho.max(), color="0.9", zorder=0, label="held out")

    fig, axes = plt.subplots(2, 1, figsize=(11, 6.5), sharex=True)
    for ax, p, title, color in (
        (axes[0], pb, "declared model (before)", "C3"),
        (axes[1], pa, f"{found} (after)", "C2"),
    ):
        shade(ax)
        ax.plot(t, y, ".", ms=2, color="0.4", label="measured")
        ax.plot(t, p, "-", lw=1.2, color=color, label="predicted")
        ax.set_ylabel(f"{result.model.config.sensor.component} (% w/w)")
        ax.set_title(title)
        ax.legend(loc="upper right", fontsize=8)
    axes[1].set_xlabel("t (s)")
    fig.tight_layout()
    p1 = out / "closeloop_measured_vs_predicted.png"
    fig.savefig(p1, dpi=110)
    plt.close(fig)
    paths.append(str(p1))

    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), gridspec_kw={"width_ratios": [3, 1]})
    for row, (p, lab) in enumerate(((pb, "before"), (pa, "after"))):
        r = y - p
        ax = axes[row, 0]
        shade(ax)
        ax.plot(t, r, lw=0.6, color="C0")
        ax.axhline(0, color="k", lw=0.8)
        rmse_ho = float(np.sqrt(np.nanmean(r[sp.heldout] ** 2)))
        ax.set_title(f"residual {lab}: held-out RMSE {rmse_ho:.3f} % w/w")
        ax.set_ylabel("measured - predicted")
        ax2 = axes[row, 1]
        rr = r[(sp.train | sp.heldout) & np.isfinite(r)]
        a = _acf(rr, 60)
        ax2.bar(np.arange(1, 61), a[1:], width=1.0, color="C1")
        ax2.axhline(1.96 / np.sqrt(rr.size), color="k", ls="--", lw=0.7)
        ax2.axhline(-1.96 / np.sqrt(rr.size), color="k", ls="--", lw=0.7)
        ax2.set_title(f"ACF {lab}")
        ax2.set_xlabel("lag (s)")
    axes[1, 0].set_xlabel("t (s)")
    fig.tight_layout()
    p2 = out / "closeloop_residuals.png"
    fig.savefig(p2, dpi=110)
    plt.close(fig)
    paths.append(str(p2))

    if result.ident.steps:
        rows = sorted(result.ident.steps[0], key=lambda f: -f.rel_improvement)
        fig, ax = plt.subplots(figsize=(8, 0.35 * len(rows) + 1.5))
        vals = [max(f.rel_improvement, -0.1) for f in rows]
        cols = ["C2" if f.claimable else "0.6" for f in rows]
        ax.barh([f.labels[-1] for f in rows], vals, color=cols)
        ax.axvline(result.ident.options.min_improvement, color="k", ls="--", lw=0.8, label="margin")
        ax.invert_yaxis()
        ax.set_xlabel("held-out relative MSE improvement, step 1 (green: passes the claim test)")
        ax.legend(fontsize=8)
        fig.tight_layout()
        p3 = out / "closeloop_candidates.png"
        fig.savefig(p3, dpi=110)
        plt.close(fig)
        paths.append(str(p3))
    return paths


def cmd_close_loop(args: argparse.Namespace) -> int:
    from schemas.closeloop import CloseLoopReport
    from twin_core.closeloop import IdentifyOptions, close_loop
    from twin_core.plant import LineModel

    try:
        from services.recording import load_line_data
    except ImportError as exc:  # pragma: no cover - depends on the services package
        log.error("cannot read recordings: %s", exc)
        return 2
    config = load_line_config(args.config)
    ld = load_line_data(args.recording)
    data = run_data_from_line_data(ld, config, name=Path(args.recording).name)
    opts = IdentifyOptions(
        candidates=args.candidates.split(",") if args.candidates else None,
        max_effects=args.max_effects,
        alpha=args.alpha,
        min_improvement=args.min_improvement,
        split=args.split,
        train_fraction=args.train_fraction,
        skip_s=args.skip_s,
    )
    model = LineModel(config)
    if args.noise == "estimate":
        from twin_core.closeloop.noise import with_estimated_noise

        model, est = with_estimated_noise(data, model)
        noise = {"source": "estimated", **est.to_dict()}
        log.info(
            "noise estimated on %d quiet samples: white x%.2f, pink_sd %.3f %% w/w",
            est.n_quiet,
            est.white_factor,
            est.pink_sd,
        )
    else:
        n = config.sensor.noise
        noise = {
            "source": "declared",
            "white_sd": n.white_sd,
            "pink_sd": n.pink_sd,
            "proportional_rel": n.proportional_rel,
        }
    result = close_loop(data, model, opts, recording=str(args.recording))
    report = result.to_dict()
    report["noise"] = noise
    if args.figures:
        report["figures"] = write_figures(result, args.figures)
    rep = CloseLoopReport.model_validate(report)
    Path(args.report).parent.mkdir(parents=True, exist_ok=True)
    Path(args.report).write_text(rep.model_dump_json(indent=2))
    e = report["errors"]
    log.info(
        "status %s; effects %s; held-out RMSE %.4f -> %.4f %% w/w",
        report["status"],
        [x["label"] for x in report["effects"]] or "none",
        e["before"]["heldout"]["rmse"],
        e["after"]["heldout"]["rmse"],
    )
    print(
        json.dumps(
            {
                "status": report["status"],
                "effects": [
                    {"label": x["label"], **{p["name"]: p["value"] for p in x["params"]}}
                    for x in report["effects"]
                ],
                "errors": e,
            },
            indent=2,
        )
    )
    return 0


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "close-loop",
        help="find undeclared effects in a recording, fix the model, report before/after",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("recording", help="MCAP recording of the line")
    p.add_argument("--config", required=True, help="declared line config (YAML/JSON)")
    p.add_argument("--report", required=True, help="JSON report to write")
    p.add_argument("--figures", default=None, help="directory for PNG figures")
    p.add_argument("--candidates", default=None, help="comma-separated effect names (default all)")
    p.add_argument("--max-effects", type=int, default=2)
    p.add_argument("--alpha", type=float, default=0.05)
    p.add_argument("--min-improvement", type=float, default=0.03)
    p.add_argument("--split", choices=("tail", "blocks"), default="tail")
    p.add_argument("--train-fraction", type=float, default=0.6)
    p.add_argument("--skip-s", type=float, default=0.0, help="ignore the first seconds (start-up)")
    p.add_argument(
        "--noise",
        choices=("declared", "estimate"),
        default="declared",
        help="NIR noise levels for the decisions: as declared in the config, or estimated from "
        "the recording's quiet samples (twin_core.closeloop.noise)",
    )
    p.set_defaults(func=cmd_close_loop)
