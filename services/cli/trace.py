"""``twin trace`` and ``twin batch report``: raw-material lots in the product of a recording
(``twin_core.tracking``; docs/traceability.md).

twin trace REC.mcap --config LINE.yaml --lot LOT [--threshold F] [--json]
twin trace REC.mcap --config LINE.yaml --at T [--json]
twin batch report REC.mcap --config LINE.yaml --out DIR
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from services.cli.live import DEFAULT_CONFIG


def _spec(args: argparse.Namespace) -> Any:
    from schemas.line import LineSpec

    return LineSpec.from_file(args.config or DEFAULT_CONFIG)


def _assays(texts: list[str] | None) -> dict[str, float]:
    """``LOT:ASSAY`` -> {lot: assay}."""
    out: dict[str, float] = {}
    for text in texts or []:
        lot, _, value = text.rpartition(":")
        try:
            a = float(value)
        except ValueError:
            a = math.nan
        if not lot or not (math.isfinite(a) and 0 <= a <= 2):
            raise ValueError(f"--assay must be LOT:ASSAY with ASSAY in [0, 2], got {text!r}")
        out[lot] = a
    return out


def cmd_trace(args: argparse.Namespace) -> int:
    from services.trace import trace_recording
    from twin_core.tracking.assay import content_deviation
    from twin_core.tracking.recall import (
        composition_at,
        lot_intervals,
        recall_coverage,
        threshold_for_coverage,
    )

    if (args.lot is None) == (args.at is None):
        raise ValueError("give one of --lot LOT or --at T")
    spec = _spec(args)
    threshold = spec.tracking.threshold if args.threshold is None else args.threshold
    if not 0 < threshold < 1:
        raise ValueError(f"--threshold must be in (0, 1), got {threshold!r}")
    if args.coverage is not None and not 0 < args.coverage < 1:
        raise ValueError(f"--coverage must be in (0, 1), got {args.coverage!r}")
    if args.coverage is not None and args.threshold is not None:
        raise ValueError("give --threshold or --coverage, not both")
    assays = _assays(args.assay)
    inputs, trace = trace_recording(args.recording, spec, args.allow_partial)
    if args.coverage is not None and args.lot is not None:
        threshold = threshold_for_coverage(trace, args.lot, args.coverage)
    for lot in assays:
        trace.column(lot)
    if args.at is not None:
        shares = composition_at(trace, args.at, min_fraction=1e-6)
        dev = content_deviation(trace.fractions(), trace.lots, assays) if assays else None
        i = int(
            min(
                max(0, (args.at - trace.t_s[0]) // (trace.t_s[1] - trace.t_s[0])),
                trace.t_s.size - 1,
            )
        )
        batch = next(
            (k for k, (a, e, _) in enumerate(_bounds(spec, trace), start=1) if a <= i < e), None
        )
        result: dict[str, Any] = {
            "t_s": args.at,
            "batch": batch,
            "lots": [s.to_dict() for s in shares],
            "content_deviation_pct_w_w": None if dev is None else float(dev[i]),
        }
        if args.json:
            print(json.dumps(result))
            return 0
        print(f"product leaving at {args.at:g} s (batch {batch}):")
        for s in shares:
            print(
                f"  {s.lot:24s} {s.component:12s} {100 * s.fraction:8.4f} % of product "
                f"{100 * s.component_fraction:8.3f} % of {s.component}"
            )
        if dev is not None:
            print(f"  predicted content deviation from the lots' assays: {dev[i]:+.3f} % w/w")
        return 0
    intervals = lot_intervals(trace, args.lot, threshold)
    bounds = _bounds(spec, trace)
    rows = []
    for iv in intervals:
        batches = [
            k
            for k, (a, e, _) in enumerate(bounds, start=1)
            if trace.t_s[a] <= iv.t_end_s and iv.t_start_s < trace.t_s[e - 1] + 1e-9
        ]
        rows.append({**iv.to_dict(), "batches": batches})
    j = trace.column(args.lot)
    result = {
        "lot": args.lot,
        "threshold": threshold,
        "recording_sha256": inputs.sha256,
        "lot_mass_in_kg": float(trace.mass_in_kg[j]),
        "lot_mass_out_kg": float(trace.outlet_kg_s[:, j].sum() * (trace.t_s[1] - trace.t_s[0])),
        "coverage": recall_coverage(trace, args.lot, intervals),
        "intervals": rows,
        "hopper_model": spec.tracking.hopper,
    }
    if assays.get(args.lot) is not None:
        dev = content_deviation(trace.fractions(), trace.lots, assays)
        k = int(abs(dev).argmax())
        result["content_deviation_pct_w_w"] = {"max": float(dev[k]), "t_s": float(trace.t_s[k])}
    if args.json:
        print(json.dumps(result))
        return 0
    print(
        f"lot {args.lot}: {result['lot_mass_out_kg']:.4g} kg left the blender in the record; "
        f"product holding > {threshold:g} of it ({100 * result['coverage']:.3f} % of the lot):"
    )
    if not rows:
        print("  none")
    for r in rows:
        print(
            f"  {r['t_start_s']:10.0f} - {r['t_end_s']:10.0f} s  product {r['product_kg']:9.3f} kg"
            f"  lot {r['lot_kg']:9.3f} kg  max {100 * r['max_fraction']:.3f} %"
            f"  batch {', '.join(map(str, r['batches'])) or '-'}"
        )
    if "content_deviation_pct_w_w" in result:
        d = result["content_deviation_pct_w_w"]
        print(f"  predicted content deviation: {d['max']:+.3f} % w/w at {d['t_s']:.0f} s")
    return 0


def _bounds(spec: Any, trace: Any) -> list[tuple[int, int, bool]]:
    from twin_core.tracking.batches import batch_bounds

    b = spec.batch
    if b is None:
        return [(0, trace.t_s.size, False)]
    return batch_bounds(trace, b.by, b.size, b.start_s, b.api_component)


def cmd_batch_report(args: argparse.Namespace) -> int:
    from services.batch_report import write_batch_report
    from services.trace import trace_recording

    spec = _spec(args)
    out = Path(args.out)
    inputs, trace = trace_recording(args.recording, spec, args.allow_partial)
    paths = write_batch_report(spec, inputs, trace, _bounds(spec, trace), out)
    print(f"wrote {len(paths)} batch record(s) to {out}", file=sys.stdout)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument("recording", help="MCAP recording of the line")
        p.add_argument("--config", help=f"line YAML/JSON (default {DEFAULT_CONFIG.name})")
        p.add_argument("--allow-partial", action="store_true", help="accept a cut recording")

    p = subparsers.add_parser("trace", help="raw-material lots in the product (recall questions)")
    common(p)
    p.add_argument("--lot", help="the lot to recall: product intervals holding it")
    p.add_argument("--at", type=float, help="plant time: lot composition of the product then")
    p.add_argument(
        "--threshold", type=float, help="mass fraction of the lot in the product (default: config)"
    )
    p.add_argument(
        "--coverage",
        type=float,
        help="instead of --threshold: the largest threshold whose intervals hold this share "
        "of the lot by the model (e.g. 0.9995 for 99.9 %% of it, docs/traceability.md)",
    )
    p.add_argument(
        "--assay",
        action="append",
        help="LOT:ASSAY a lot's content as a fraction of label (repeatable): the predicted "
        "content deviation where it leaves",
    )
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_trace)

    p = subparsers.add_parser("batch", help="batches of a recording and their batch records")
    sub = p.add_subparsers(dest="batch_command", metavar="ACTION")
    r = sub.add_parser("report", help="one JSON and one HTML batch record per batch")
    common(r)
    r.add_argument("--out", required=True, help="output directory")
    r.set_defaults(func=cmd_batch_report)
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])
