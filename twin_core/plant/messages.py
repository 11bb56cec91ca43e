"""The virtual plant's bus messages: a simulated line as the messages a real line would publish.

- :func:`run_messages` turns a :class:`~twin_core.plant.simulate.LineRun` into time-ordered
  ``(key, message)`` pairs: one :class:`~schemas.messages.FeederFlow` per feeder per tick on
  ``twin/<line>/feeder/<id>/flow`` (its ``refilling`` flag is the refill state), one
  :class:`~schemas.messages.MeasuredConcentration` per NIR sample on
  ``twin/<line>/pat/<sensor>/concentration``, the plant's :class:`~schemas.messages.Event` s
  (refills, tracer pulses, disturbances) on ``twin/<line>/feeder/<id>/event`` or
  ``twin/<line>/plant/<source>/event``.
- :func:`simulate_messages` runs :func:`~twin_core.plant.simulate.simulate_line` for a line
  configuration (disturbances and hidden effects injectable).
- :func:`feeder_flow_messages` simulates the feeders alone (the feeder service in
  ``feeder_mode: simulate``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from schemas import keys
from schemas.line import LineSpec
from schemas.messages import BlenderDrive, FeederFlow, MeasuredConcentration
from twin_core.plant.simulate import FeederRecord, LineRun, simulate_feeder, simulate_line

__all__ = ["feeder_flow_messages", "run_messages", "simulate_messages"]

#: tie-break order of messages of one plant time: flows (by feeder), NIR, events
_ORDER_NIR = 100
_ORDER_EVENT = 200


def _nz(x: float) -> float:
    return float(x) if math.isfinite(x) and x >= 0 else 0.0


def _flows(
    t: np.ndarray, feeders: Mapping[str, FeederRecord], spec: LineSpec
) -> list[tuple[float, int, str, Any]]:
    """One FeederFlow per feeder per tick (NaN or negative readings sent as 0)."""
    out: list[tuple[float, int, str, Any]] = []
    for j, (name, rec) in enumerate(feeders.items()):
        k = keys.feeder_flow(spec.name, name)
        sp = spec.feeders[j].setpoint_kg_h if j < len(spec.feeders) else None
        for i in range(t.size):
            msg = FeederFlow(
                t=float(t[i]),
                seq=i,
                component=rec.component,
                mass_flow_kg_h=_nz(rec.flow_kg_h[i]),
                setpoint_kg_h=sp,
                screw_speed_rpm=_nz(rec.screw_speed_rpm[i]),
                hopper_mass_kg=_nz(rec.hopper_mass_kg[i]),
                feed_factor_g_rev=_nz(rec.feed_factor_g_rev[i]),
                refilling=bool(rec.refilling[i]),
            )
            out.append((t[i], j, k, msg))
    return out


def _ordered(rows: list[tuple[float, int, str, Any]]) -> list[tuple[str, Any]]:
    rows.sort(key=lambda x: (x[0], x[1]))
    return [(k, msg) for _, _, k, msg in rows]


def run_messages(run: LineRun, spec: LineSpec) -> list[tuple[str, Any]]:
    """Bus messages of a ``LineRun`` in plant-time order, as (key, message) pairs (module
    docstring)."""
    line = spec.name
    t = np.asarray(run.t_s, float)
    out = _flows(t, run.feeders, spec)
    nk = keys.measured_concentration(line, spec.sensor.id)
    m = np.asarray(run.measured_pct_w_w, float)
    for seq, i in enumerate(np.nonzero(np.isfinite(m))[0]):
        msg = MeasuredConcentration(
            t=float(t[i]),
            seq=seq,
            sensor=spec.sensor.id,
            component=run.sensor_component,
            concentration_pct_w_w=float(m[i]),
        )
        out.append((t[i], _ORDER_NIR, nk, msg))
    feeders = {f.id for f in spec.feeders}
    for ev in run.events:  # the simulator's events are the wire messages
        unit = "feeder" if ev.source in feeders else "plant"
        out.append((ev.t, _ORDER_EVENT, keys.event(line, unit, ev.source), ev))
    return _ordered(out)


def simulate_messages(
    spec: LineSpec,
    duration_s: float,
    seed: int | None = 0,
    disturbances: Sequence[Mapping[str, Any]] = (),
    effects: Sequence[Mapping[str, Any]] = (),
    blade_speeds: Sequence[tuple[float, float]] = (),
    lot_assays: Sequence[Any] = (),
) -> tuple[LineRun, list[tuple[str, Any]]]:
    """Simulate the line of ``spec`` (``simulate_line``); return (run, messages).
    ``blade_speeds``: (plant time, rpm) reports of the blender's drive (``BlenderDrive``) put in
    the messages; the simulated blender itself does not change with them (its E(t) is the
    declared one). ``lot_assays``: lots of other API content in the truth
    (``twin_core.tracking.assay.LotAssay``; the hopper law of ``spec.tracking``)."""
    from twin_core.tracking.hopper import mixed_fraction

    run = simulate_line(
        spec,
        duration_s,
        dt_s=spec.dt_s,
        seed=seed,
        effects=list(effects),
        disturbances=list(disturbances),
        lot_assays=list(lot_assays),
        hopper_mixing=mixed_fraction(spec.tracking.hopper, spec.tracking.mixed_fraction),
    )
    msgs = run_messages(run, spec)
    if not blade_speeds:
        return run, msgs
    key = keys.blender_drive(spec.name)
    drives = [
        (key, BlenderDrive(t=float(t), seq=i, blade_speed_rpm=float(rpm)))
        for i, (t, rpm) in enumerate(sorted(blade_speeds))
    ]
    # a drive report comes before the other messages of its plant time (the blender switches
    # from that tick on; coming after the tick's flows it would apply one tick late)
    return run, sorted([*drives, *msgs], key=lambda km: km[1].t)


def feeder_flow_messages(spec: LineSpec, duration_s: float) -> list[tuple[str, FeederFlow]]:
    """The feeders of ``spec`` alone (``simulate_feeder``, feeder i seeded with i) on the ticks
    0 .. ``duration_s``: their FeederFlow messages in plant-time order."""
    dt = spec.dt_s
    n = int(duration_s / dt) + 1
    records = {
        f.id: simulate_feeder(f, duration_s, dt, n, seed=i) for i, f in enumerate(spec.feeders)
    }
    return _ordered(_flows(np.arange(n) * dt, records, spec))
