"""A recording as the material-tracking model's inputs (``twin_core.tracking``), and the
records the batch report quotes.

:func:`load_trace_inputs` reads a recording (``services.recording.read_recording``) into the
tick grid of the line (``spec.dt_s``): each feeder's measured flow and hopper mass (a tick
without a message holds the last value), the refills with their lots (``Event.lot_id``; a
feeder without refill events, e.g. fed by the OPC UA bridge or ``twin import``, has its
refills from its ``refilling`` flag, lots unnamed: ``<feeder>-L<k>``), and
the E(t) in use per time segment: the blender's own kernel (``BlenderKernel``) with the
updates the live blender adopts from the recording (``RtdEstimate`` with
``blender.adopt_rtd_estimates``, ``ModelFinding`` effects with ``blender.adopt_findings``, from
their ``applies_from_s``). Blade-speed or throughput switches of a compartment-model blender are
not followed (the configured operating point throughout). It also keeps the recording's own
decisions for the batch record: alerts, divert commands, close-loop findings, models in use.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from schemas import keys
from schemas.line import LineSpec
from twin_core.tracking import LotTrace, Refill, mixed_fraction, track_lots

__all__ = ["TraceInputs", "load_trace_inputs", "sha256_file", "trace_recording"]


def sha256_file(path: str | Path) -> str:
    """SHA-256 of a file, hex."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass
class TraceInputs:
    """What :func:`track_lots` needs from a recording, and the decisions it recorded."""

    t_s: np.ndarray
    flows_kg_h: dict[str, np.ndarray]
    hopper_kg: dict[str, np.ndarray]
    refills: list[Refill]
    kernels: list[tuple[float, np.ndarray]]
    kernel_reasons: list[str]
    alerts: list[Any] = field(default_factory=list)
    diverts: list[Any] = field(default_factory=list)
    findings: list[Any] = field(default_factory=list)
    models_in_use: list[Any] = field(default_factory=list)
    measured: list[tuple[float, str, float]] = field(default_factory=list)
    sha256: str = ""
    path: str = ""


def load_trace_inputs(path: str | Path, spec: LineSpec, allow_partial: bool = False) -> TraceInputs:
    """Read the recording at ``path`` for line ``spec`` (module docstring). A recording without
    feeder flows of the line's feeders is an error naming the feeders."""
    from schemas.closeloop import ModelFinding
    from schemas.messages import (
        BlenderModelInUse,
        DivertCommand,
        Event,
        FeederFlow,
        MeasuredConcentration,
        OosAlert,
        RtdEstimate,
    )
    from services.common import applies_from
    from services.recording import read_recording
    from twin_core.online.blender import BlenderKernel

    rec = read_recording(path)
    rec.require_complete(allow_partial)
    feeders = [f.id for f in spec.feeders]
    dt = spec.dt_s
    flows: dict[str, dict[int, float]] = {f: {} for f in feeders}
    hopper: dict[str, dict[int, float]] = {f: {} for f in feeders}
    refilling: dict[str, dict[int, float]] = {f: {} for f in feeders}
    events: list[Event] = []
    out = TraceInputs(np.zeros(0), {}, {}, [], [], [])
    updates: list[tuple[float, str, Any]] = []
    t0: float | None = None
    by_key: dict[str, tuple[Any, str | None]] = {}  # key -> (model, id): parsed once per channel
    for m in rec.messages:
        info = by_key.get(m.key)
        if info is None:
            model = keys.model_for_key(m.key)
            info = by_key[m.key] = (model, keys.parse_key(m.key).id if model else None)
        model, fid = info
        if model is None:
            continue
        if model is FeederFlow:
            if fid not in flows:
                continue
            msg = model.model_validate_json(m.payload)
            t0 = msg.t if t0 is None else t0
            i = int(round((msg.t - t0) / dt))
            flows[fid][i] = msg.mass_flow_kg_h
            hopper[fid][i] = msg.hopper_mass_kg
            refilling[fid][i] = 1.0 if msg.refilling else 0.0
        elif model in (Event, OosAlert, DivertCommand, RtdEstimate, BlenderModelInUse):
            msg = model.model_validate_json(m.payload)
            if isinstance(msg, Event):
                events.append(msg)
            elif isinstance(msg, OosAlert):
                out.alerts.append(msg)
            elif isinstance(msg, DivertCommand):
                out.diverts.append(msg)
            elif isinstance(msg, BlenderModelInUse):
                out.models_in_use.append(msg)
            elif spec.blender.adopt_rtd_estimates:
                updates.append((applies_from(msg, spec), "estimate", (msg.model, msg.params)))
        elif model is ModelFinding:
            msg = model.model_validate_json(m.payload)
            out.findings.append(msg)
            if spec.blender.adopt_findings:
                effs = [e.model_dump() for e in msg.model_effects]
                updates.append((applies_from(msg, spec), "effects", effs))
        elif model is MeasuredConcentration:
            msg = model.model_validate_json(m.payload)
            if msg.quality != "bad":
                out.measured.append((msg.t, msg.component, msg.concentration_pct_w_w))
    missing = [f for f in feeders if not flows[f]]
    if missing or t0 is None:
        raise ValueError(f"recording has no feeder flows of feeders {missing}, {path}")
    n = max(max(v) for v in flows.values()) + 1
    out.t_s = t0 + np.arange(n) * dt
    for f in feeders:
        out.flows_kg_h[f] = _held(flows[f], n)
        out.hopper_kg[f] = _held(hopper[f], n)
    from twin_core.tracking.assay import refills_from_events

    out.refills = refills_from_events([e for e in events if e.source in feeders])
    with_events = {r.feeder for r in out.refills}
    for f in feeders:  # no refill events (e.g. an OPC UA or historian feed): the refill flag
        if f not in with_events:
            out.refills += _refills_from_flag(f, out.t_s, _held(refilling[f], n) > 0.5)
    kernel = BlenderKernel(spec)
    out.kernels, out.kernel_reasons = [(float(out.t_s[0]), kernel.e.copy())], ["start"]
    last_effects: list[dict] = []
    for t_from, kind, payload in sorted(updates, key=lambda u: u[0]):
        if kind == "effects":
            if payload == last_effects:
                continue
            last_effects = payload
        kernel.schedule(t_from, kind, payload)
        # applied before the first tick at or after t_from
        i = int(np.searchsorted(out.t_s, t_from - 1e-9))
        t_tick = float(out.t_s[min(i, n - 1)]) if i < n else float("inf")
        if kernel.apply_due(t_from):
            if i >= n:
                break
            if out.kernels[-1][0] == t_tick:
                out.kernels[-1] = (t_tick, kernel.e.copy())
                out.kernel_reasons[-1] = kind
            else:
                out.kernels.append((t_tick, kernel.e.copy()))
                out.kernel_reasons.append(kind)
    out.sha256 = sha256_file(path)
    out.path = str(path)
    return out


def _refills_from_flag(feeder: str, t: np.ndarray, flag: np.ndarray) -> list[Refill]:
    """Refills of a feeder from its ``refilling`` flag: each run of raised ticks, stopping at
    the first tick after it (an unnamed lot: ``<feeder>-L<k>`` for the k-th)."""
    edges = np.diff(np.concatenate([[0], flag.astype(np.int8), [0]]))
    starts, stops = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    return [
        Refill(feeder, float(t[a]), float(t[min(b, t.size - 1)]), None, None)
        for a, b in zip(starts, stops)
    ]


def _held(values: dict[int, float], n: int) -> np.ndarray:
    """Values on ticks 0..n-1, a tick without one holding the previous (the first: the next)."""
    arr = np.full(n, np.nan)
    idx = np.fromiter(values.keys(), dtype=int, count=len(values))
    arr[idx] = np.fromiter(values.values(), dtype=float, count=len(values))
    ok = np.isfinite(arr)
    if not ok.all():
        first = int(np.argmax(ok))
        arr[:first] = arr[first]
        pos = np.where(np.isfinite(arr), np.arange(n), 0)
        arr = arr[np.maximum.accumulate(pos)]
    return arr


def trace_recording(
    path: str | Path, spec: LineSpec, allow_partial: bool = False
) -> tuple[TraceInputs, LotTrace]:
    """The recording's inputs and the lot trace of the line's tracking model
    (``spec.tracking``)."""
    inputs = load_trace_inputs(path, spec, allow_partial)
    alpha = mixed_fraction(spec.tracking.hopper, spec.tracking.mixed_fraction)
    trace = track_lots(
        inputs.t_s,
        inputs.flows_kg_h,
        spec.components,
        inputs.kernels,
        inputs.refills,
        inputs.hopper_kg,
        alpha,
        {f.id: f.initial_lot for f in spec.feeders},
    )
    return inputs, trace
