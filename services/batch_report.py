"""The batch record of a recording: one JSON and one HTML file per batch (``twin batch
report``; ICH Q13 sections 3.1 and 3.3).

Each record: the batch's time span, product and diverted mass, every divert window in it with
its command, alert and reason, the raw-material lots with mass and fraction per component
(``twin_core.tracking.batches``), the OOS episodes, the blender models in use and their
changes, the close-loop findings, and the SHA-256 of the recording. Alerts, divert commands,
models in use and findings are the recording's own (the live twin records them); a recording
of the plant alone has none, and the record says it shows plant data only. The HTML is written
with the standard library (``html.escape``), one self-contained page per batch.
"""

from __future__ import annotations

import html
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from schemas.line import LineSpec
from services.trace import TraceInputs
from twin_core.tracking import LotTrace
from twin_core.tracking.batches import batch_summaries

__all__ = ["batch_records", "batches_markdown", "batches_of_recording", "write_batch_report"]


def _divert_windows(inputs: TraceInputs) -> list[dict[str, Any]]:
    """The gate's divert windows in force (``DashboardState.divert_windows``: a later command
    of an alert replaces its earlier window; an accept cancels), each with its command and
    alert."""
    from schemas import keys
    from twin_core.online.dashboard_state import DashboardState

    state = DashboardState()
    for c in inputs.diverts:
        state.add(keys.divert_command("line"), c)
    commands = {c.command_id: c for c in inputs.diverts}
    alerts = {a.alert_id: a for a in inputs.alerts}
    out = []
    for w in state.divert_windows():
        cmd = commands.get(w.ident)
        alert = alerts.get(cmd.alert_id) if cmd is not None and cmd.alert_id else None
        out.append(
            {
                "t_start_s": w.t_start_s,
                "t_end_s": w.t_end_s,
                "command_id": w.ident,
                "decided_at_s": cmd.t if cmd is not None else None,
                "reason": w.text,
                "alert_id": cmd.alert_id if cmd is not None else None,
                "alert_cause": alert.cause if alert is not None else None,
                # the blender model the decision was taken with (contract: absent before)
                "model_version": getattr(cmd, "model_version", None) if cmd is not None else None,
            }
        )
    return out


def batch_records(
    spec: LineSpec,
    inputs: TraceInputs,
    trace: LotTrace,
    bounds: Sequence[tuple[int, int, bool]],
) -> list[dict[str, Any]]:
    """The batch records as JSON-able dicts (module docstring)."""
    windows = _divert_windows(inputs)
    batches = batch_summaries(trace, bounds, [(w["t_start_s"], w["t_end_s"]) for w in windows])
    dt = float(trace.t_s[1] - trace.t_s[0])
    total = trace.outlet_kg_s.sum(axis=1)
    decisions = bool(inputs.alerts or inputs.diverts or inputs.findings or inputs.models_in_use)
    out = []
    for b in batches:
        a, e = b.t_start_s, b.t_end_s

        def inside(t0: float, t1: float, a: float = a, e: float = e) -> bool:
            return t0 < e and t1 >= a

        wins = []
        for w in windows:
            if inside(w["t_start_s"], w["t_end_s"]):
                m = (trace.t_s >= max(a, w["t_start_s"])) & (trace.t_s <= min(e, w["t_end_s"]))
                m &= trace.t_s < e
                wins.append({**w, "diverted_kg_in_batch": float(total[m].sum() * dt)})
        segments = [
            {"applies_from_s": t0, "reason": r}
            for (t0, _), r in zip(inputs.kernels, inputs.kernel_reasons)
            if t0 < e
        ]
        out.append(
            {
                "batch": b.index,
                "line": spec.name,
                "definition": spec.batch.model_dump() if spec.batch else {"by": "whole record"},
                "complete": b.complete,
                "t_start_s": a,
                "t_end_s": e,
                "product_kg": b.product_kg,
                "diverted_kg": b.diverted_kg,
                "accepted_kg": b.product_kg - b.diverted_kg,
                "divert_windows": wins,
                "lots": b.lots,
                "oos_episodes": [
                    x.model_dump(mode="json")
                    for x in inputs.alerts
                    if inside(x.t_start_s, x.t_end_s)
                ],
                "models_in_use": [
                    x.model_dump(mode="json") for x in inputs.models_in_use if x.applies_from_s < e
                ][-20:],
                "tracking_kernels": segments,
                "closeloop_findings": [
                    {
                        "finding_id": f.finding_id,
                        "t_start_s": f.t_start_s,
                        "t_end_s": f.t_end_s,
                        "status": f.status,
                        "effects": [x.model_dump(mode="json") for x in f.model_effects],
                    }
                    for f in inputs.findings
                    if inside(f.t_start_s, f.t_end_s)
                ],
                "data_quality_periods": sorted(
                    (
                        {"finding_id": f.finding_id, **q.model_dump(mode="json")}
                        for f in inputs.findings
                        for q in f.data_quality
                        if inside(q.t_start_s, q.t_end_s)
                    ),
                    key=lambda q: (q["t_start_s"], q["series"]),
                ),
                "tracking": spec.tracking.model_dump(),
                "recording": {"path": Path(inputs.path).name, "sha256": inputs.sha256},
                "decisions_recorded": decisions,
                "note": ""
                if decisions
                else "the recording holds plant data only (no alert, divert command, model in "
                "use or finding of the twin was recorded): divert windows and OOS episodes are "
                "not shown",
            }
        )
    return out


def _table(rows: list[dict[str, Any]], cols: list[tuple[str, str]]) -> str:
    if not rows:
        return "<p>none</p>"
    head = "".join(f"<th>{html.escape(t)}</th>" for _, t in cols)
    body = []
    for r in rows:
        cells = []
        for k, _ in cols:
            v = r.get(k)
            if isinstance(v, float):
                v = f"{v:.6g}"
            cells.append(f"<td>{html.escape('' if v is None else str(v))}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def _html(rec: dict[str, Any]) -> str:
    """One batch record as a self-contained HTML page."""
    esc = html.escape
    lots = [
        {
            **r,
            "pct_batch": 100 * r["fraction_of_batch"],
            "pct_comp": 100 * r["fraction_of_component"],
        }
        for r in rec["lots"]
    ]
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>Batch {rec['batch']} of {esc(rec['line'])}</title>",
        "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}"
        "td,th{border:1px solid #999;padding:2px 6px;text-align:left}</style></head><body>",
        f"<h1>Batch record: batch {rec['batch']} of line {esc(rec['line'])}</h1>",
        f"<p>Plant time {rec['t_start_s']:.0f} - {rec['t_end_s']:.0f} s"
        f" ({'complete' if rec['complete'] else 'partial'}); definition: "
        f"{esc(json.dumps(rec['definition']))}</p>",
        f"<p>Product {rec['product_kg']:.3f} kg, diverted {rec['diverted_kg']:.3f} kg, accepted "
        f"{rec['accepted_kg']:.3f} kg.</p>",
        f"<p>Recording {esc(rec['recording']['path'])}, SHA-256 "
        f"<code>{esc(rec['recording']['sha256'])}</code></p>",
    ]
    if rec["note"]:
        parts.append(f"<p><b>{esc(rec['note'])}</b></p>")
    parts += [
        "<h2>Raw-material lots</h2>",
        _table(
            lots,
            [
                ("lot", "lot"),
                ("component", "component"),
                ("feeder", "feeder"),
                ("mass_kg", "mass, kg"),
                ("pct_batch", "% of batch"),
                ("pct_comp", "% of component"),
            ],
        ),
        f"<p>Tracking model: hopper {esc(rec['tracking']['hopper'])}; blender E(t) in use "
        "per time segment (below).</p>",
        "<h2>Divert windows</h2>",
        _table(
            rec["divert_windows"],
            [
                ("t_start_s", "from, s"),
                ("t_end_s", "to, s"),
                ("diverted_kg_in_batch", "diverted, kg"),
                ("command_id", "command"),
                ("decided_at_s", "decided at, s"),
                ("alert_id", "alert"),
                ("alert_cause", "alert cause"),
                ("reason", "reason"),
                ("model_version", "model version"),
            ],
        ),
        "<h2>State of control</h2><h3>OOS episodes</h3>",
        _table(
            rec["oos_episodes"],
            [
                ("alert_id", "alert"),
                ("t_start_s", "from, s"),
                ("t_end_s", "to, s"),
                ("peak_deviation_pct_w_w", "peak deviation, % w/w"),
                ("cause", "cause"),
            ],
        ),
        "<h3>Data-quality periods (close-loop)</h3>",
        _table(
            rec["data_quality_periods"],
            [
                ("t_start_s", "from, s"),
                ("t_end_s", "to, s"),
                ("series", "series"),
                ("kind", "kind"),
                ("action", "action"),
                ("n_samples", "samples"),
            ],
        ),
        "<h3>Blender models in use</h3>",
        _table(
            rec["models_in_use"],
            [
                ("applies_from_s", "from, s"),
                ("kind", "kind"),
                ("name", "model"),
                ("reason", "why"),
                ("model_version", "version"),
            ],
        ),
        "<h3>Close-loop findings</h3>",
        _table(
            rec["closeloop_findings"],
            [
                ("finding_id", "finding"),
                ("t_start_s", "from, s"),
                ("t_end_s", "to, s"),
                ("status", "status"),
            ],
        ),
        "</body></html>",
    ]
    return "\n".join(parts)


def write_batch_report(
    spec: LineSpec,
    inputs: TraceInputs,
    trace: LotTrace,
    bounds: Sequence[tuple[int, int, bool]],
    out: Path,
) -> list[Path]:
    """Write ``batch_<k>.json`` and ``batch_<k>.html`` per batch and ``batches.json`` (the
    list) into ``out``; returns the JSON paths."""
    return [p for p, _ in _write(spec, inputs, trace, bounds, out)]


def _write(
    spec: LineSpec,
    inputs: TraceInputs,
    trace: LotTrace,
    bounds: Sequence[tuple[int, int, bool]],
    out: Path,
) -> list[tuple[Path, dict[str, Any]]]:
    out.mkdir(parents=True, exist_ok=True)
    records = batch_records(spec, inputs, trace, bounds)
    paths = []
    for rec in records:
        p = out / f"batch_{rec['batch']:03d}.json"
        p.write_text(json.dumps(rec, indent=1))
        (out / f"batch_{rec['batch']:03d}.html").write_text(_html(rec))
        paths.append((p, rec))
    index = [
        {
            k: r[k]
            for k in ("batch", "t_start_s", "t_end_s", "complete", "product_kg", "diverted_kg")
        }
        for r in records
    ]
    (out / "batches.json").write_text(json.dumps(index, indent=1))
    return paths


def batches_of_recording(path: str | Path, spec: LineSpec, out: Path) -> list[dict[str, Any]]:
    """The batch records of a recording written to ``out`` (:func:`write_batch_report`), and
    their summary for a run report: span, product and diverted mass, the lots with their mass
    and fraction of their component (e.g. ``twin demo`` on the live twin's own recording)."""
    from services.trace import trace_recording
    from twin_core.tracking.batches import batch_bounds

    inputs, trace = trace_recording(path, spec, allow_partial=True)
    b = spec.batch
    bounds = (
        [(0, trace.t_s.size, False)]
        if b is None
        else batch_bounds(trace, b.by, b.size, b.start_s, b.api_component)
    )
    out_rows = []
    for p, rec in _write(spec, inputs, trace, bounds, out):
        out_rows.append(
            {
                "batch": rec["batch"],
                "t_start_s": rec["t_start_s"],
                "t_end_s": rec["t_end_s"],
                "complete": rec["complete"],
                "product_kg": rec["product_kg"],
                "diverted_kg": rec["diverted_kg"],
                "divert_windows": len(rec["divert_windows"]),
                "lots": [
                    {k: x[k] for k in ("lot", "component", "mass_kg", "fraction_of_component")}
                    for x in rec["lots"]
                    if x["fraction_of_component"] >= 1e-4
                ],
                "record": p.name,
            }
        )
    return out_rows


def batches_markdown(rows: list[dict[str, Any]]) -> list[str]:
    """The batches of a run report as Markdown lines (a table: each batch with its lots)."""
    if not rows:
        return []
    lines = [
        "",
        "## Batches (lots from the material tracking; records in `batches/`)",
        "",
        "| batch | plant time, s | product, kg | diverted, kg | lots (kg, share of component) |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lots = "; ".join(
            f"{x['lot']} {x['mass_kg']:.3f} ({100 * x['fraction_of_component']:.1f} %)"
            for x in r["lots"]
        )
        span = f"{r['t_start_s']:.0f} - {r['t_end_s']:.0f}{'' if r['complete'] else ' (partial)'}"
        lines.append(
            f"| {r['batch']} | {span} | {r['product_kg']:.3f} | {r['diverted_kg']:.3f} | {lots} |"
        )
    return lines
