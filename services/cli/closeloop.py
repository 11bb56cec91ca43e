"""``twin close-loop``: find, explain and fix where the declared line model is wrong.

    twin close-loop RECORDING.mcap --config LINE.yaml --report OUT.json [--figures DIR]

RECORDING is an MCAP log of the line (feeder flows, NIR concentration, events; checked by
``twin_core.closeloop.check.check_recording``); an incomplete one is refused unless
``--allow-partial``, and the report states what was lost (``diagnostics_before.input``). LINE.yaml is the line's configuration file
(``schemas.line.LineSpec``, e.g. ``services/configs/line1.yaml``); its declared line (feeders,
blender, sensor, tracers) is the model checked. The report is validated against
``schemas.closeloop.CloseLoopReport``; ``--figures`` writes PNGs of measured vs predicted and of
the residuals, before and after.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

log = logging.getLogger("twin.closeloop")


def load_line_config(path: str | Path) -> Any:
    """The ``schemas.line.LineSpec`` of a YAML/JSON line configuration file; a file that is not
    one raises ``ValueError`` with one line naming the fields and values rejected."""
    from pydantic import ValidationError

    from schemas.base import validation_summary
    from schemas.line import LineSpec

    try:
        return LineSpec.from_file(path)
    except ValidationError as exc:
        raise ValueError(f"{path} is not a valid line config: {validation_summary(exc)}") from None


def cmd_close_loop(args: argparse.Namespace) -> int:
    from schemas.closeloop import CloseLoopReport
    from services.cli.bus import check_output_file
    from services.recording import read_recording
    from twin_core.closeloop import IdentifyOptions
    from twin_core.closeloop.check import check_recording

    opts = IdentifyOptions(
        candidates=args.candidates.split(",") if args.candidates else None,
        max_effects=args.max_effects,
        alpha=args.alpha,
        min_improvement=args.min_improvement,
        split=args.split,
        train_fraction=args.train_fraction,
        skip_s=args.skip_s,
    )
    config = load_line_config(args.config)
    check_output_file(Path(args.report))
    rec = read_recording(args.recording)
    rec.require_complete(args.allow_partial)
    messages = ((m.key, m.decode()) for m in rec.messages)
    report = check_recording(
        messages,
        config,
        opts,
        noise="estimate" if args.noise == "estimate" else "declared",
        recording=str(args.recording),
        figures_dir=args.figures,
    )
    report["diagnostics_before"]["input"] = rec.loss_summary()
    rep = CloseLoopReport.model_validate(report)
    Path(args.report).write_text(rep.model_dump_json(indent=2))
    effects = [
        {"label": x["label"], **{p["name"]: p["value"] for p in x["params"]}}
        for x in report["effects"]
    ]
    summary = {
        "status": report["status"],
        "effects": effects,
        "errors": report["errors"],
        "input": rec.loss_report(),
    }
    print(json.dumps({**summary, "noise": report["noise"]["source"]}, indent=2))
    return 0


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "close-loop",
        help="find undeclared effects in a recording, fix the model, report before/after",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("recording", help="MCAP recording of the line")
    p.add_argument("--config", required=True, help="line configuration (YAML/JSON LineSpec)")
    p.add_argument("--report", required=True, help="JSON report to write")
    p.add_argument("--figures", default=None, help="directory for PNG figures")
    p.add_argument(
        "--allow-partial",
        action="store_true",
        help="accept an incomplete recording (cut short, corrupt chunks); the report says the loss",
    )
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
