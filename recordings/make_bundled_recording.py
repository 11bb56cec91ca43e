"""Make the bundled recording ``recordings/line1_30min.mcap`` (reproducible, seeded).

A 30-minute synthetic run of the line, simulated by ``twin_core.plant.simulate_line``:
API and excipient loss-in-weight feeders at 12 kg/h in total (5 % API), one excipient refill,
an NIR probe at the blender outlet sampling at 1 Hz with the seed's noise (white, pink,
proportional to the signal, outliers, baseline offset; docs/seed.md), and three API tracer pulses
(10 / 7.5 / 5 g, the seed's pulse masses) at 300 / 900 / 1500 s.

Channels (line ``line1``)::

    twin/line1/feeder/api/flow, twin/line1/feeder/excipient/flow   FeederFlow, 1 Hz
    twin/line1/pat/nir1/concentration                              MeasuredConcentration, 1 Hz
    twin/line1/feeder/excipient/event                              Event refill_start/stop
    twin/line1/tracer/api/event                                    Event tracer_pulse

The MCAP metadata record ``provenance`` holds the generator, the seed and the line
configuration; ``ground_truth`` holds the injected outliers' times and the hidden effects (none).
Values are rounded to instrument resolution (flows 1e-4 kg/h, concentration 1e-4 % w/w, hopper
mass 1e-4 kg, screw speed 1e-3 rpm, feed factor 1e-5 g/rev).

Run: ``python recordings/make_bundled_recording.py [OUT]``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from schemas import keys
from schemas.messages import Event, FeederFlow, MeasuredConcentration
from services.recording import McapRecorder
from twin_core.plant import seed_line, simulate_line

LINE = "line1"
SEED = 2026
DURATION_S = 1800.0
DT_S = 1.0
TRACER_G = (10.0, 7.5, 5.0)
TRACER_T_S = (300.0, 900.0, 1500.0)
API_FRACTION = 0.05
#: a small API feeder (low feed factor, 1 kg hopper); the excipient feeder uses the defaults
API_LIW = dict(
    ff_max_g_rev=1.0,
    ff_min_g_rev=0.6,
    initial_mass_kg=1.0,
    refill_low_kg=0.3,
    refill_high_kg=1.0,
    refill_rate_kg_s=0.1,
)
OUT = Path(__file__).with_name("line1_30min.mcap")


def build_messages(seed: int = SEED) -> tuple[list[tuple[str, object]], dict, dict]:
    """Simulate the run and return ``[(key, message)]`` in plant-time order, the provenance
    and the ground truth."""
    cfg = seed_line(
        api_fraction=API_FRACTION,
        total_kg_h=12.0,
        tracer_g=TRACER_G,
        tracer_times_s=TRACER_T_S,
        api_liw=API_LIW,
    )
    run = simulate_line(cfg, DURATION_S, DT_S, seed=seed)
    rows: list[tuple[float, int, str, object]] = []
    seqs: dict[str, int] = {}

    def add(t: float, order: int, key: str, model, **fields) -> None:
        seq = seqs.get(key, 0)
        seqs[key] = seq + 1
        rows.append((t, order, key, model(t=t, seq=seq, **fields)))

    specs = {f.id: f for f in cfg.feeders}
    for i, t_grid in enumerate(run.t_s):
        t = float(round(t_grid, 6))
        for j, (name, rec) in enumerate(run.feeders.items()):
            add(
                t,
                j,
                keys.feeder_flow(LINE, name),
                FeederFlow,
                component=rec.component,
                mass_flow_kg_h=round(float(rec.flow_kg_h[i]), 4),
                setpoint_kg_h=round(float(specs[name].setpoint_kg_h), 4),
                screw_speed_rpm=round(float(rec.screw_speed_rpm[i]), 3),
                hopper_mass_kg=round(max(float(rec.hopper_mass_kg[i]), 0.0), 4),
                feed_factor_g_rev=round(float(rec.feed_factor_g_rev[i]), 5),
                refilling=bool(rec.refilling[i]),
            )
        value = run.measured_pct_w_w[i]
        if np.isfinite(value):
            add(
                t,
                10,
                keys.measured_concentration(LINE, "nir1"),
                MeasuredConcentration,
                sensor="nir1",
                component=run.sensor_component,
                concentration_pct_w_w=round(float(value), 4),
                quality="good",
            )
    for ev in run.events:
        unit = "tracer" if ev.kind == "tracer_pulse" else "feeder"
        fields = ev.model_dump(exclude={"t", "seq"})
        add(float(round(ev.t, 6)), 5, keys.event(LINE, unit, ev.source), Event, **fields)
    rows.sort(key=lambda r: (r[0], r[1]))
    provenance = {
        "generator": "recordings/make_bundled_recording.py (twin_core.plant.simulate_line)",
        "seed": str(seed),
        "duration_s": str(DURATION_S),
        "dt_s": str(DT_S),
        "line_config": json.dumps(cfg.line_dict()),
    }
    truth = {
        "effects": json.dumps(run.effects),
        "outlier_times_s": json.dumps([float(x) for x in run.t_s[run.outliers]]),
        "events": json.dumps([e.model_dump(mode="json") for e in run.events]),
    }
    return [(k, m) for _, _, k, m in rows], provenance, truth


def make(out: Path = OUT, seed: int = SEED) -> Path:
    messages, provenance, truth = build_messages(seed)
    with McapRecorder(out, flush_period_s=None) as rec:
        rec.add_metadata("provenance", provenance)
        rec.add_metadata("ground_truth", truth)
        for key, msg in messages:
            rec.write_message(key, msg, publish_time_ns=int(round(msg.t * 1e9)))
    return out


if __name__ == "__main__":
    path = make(Path(sys.argv[1]) if len(sys.argv) > 1 else OUT)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.3f} MB)")
