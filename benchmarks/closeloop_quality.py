"""Calibration of the close-loop's data-quality check (``twin_core.closeloop.quality``).

Clean 2-hour, 1 Hz records of the plant simulator (standard scenario: tracer pulses, refills,
flow dips; the seed's NIR noise, white + 1/f + proportional + isolated outliers, at 1x and 2x)
must give no flag in >= 99 % of the windows; the same records with one stuck stretch of
``--stuck-s`` seconds (the NIR, or the API feeder's reported flow, frozen at its value) must be
flagged ``stuck`` over that stretch. Prints the rates with their 95 % (Clopper-Pearson)
intervals and the CPU time of the check.

    python benchmarks/closeloop_quality.py --windows 50
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import stats

from twin_core.closeloop import RunData
from twin_core.closeloop.quality import check_data_quality
from twin_core.closeloop.scenarios import standard_scenario
from twin_core.plant import LineModel, simulate_line
from twin_core.plant.model import LineInputs


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Exact binomial interval of a rate k / n (Clopper & Pearson 1934)."""
    a = 1.0 - level
    lo = stats.beta.ppf(a / 2, k, n - k + 1) if k > 0 else 0.0
    hi = stats.beta.ppf(1 - a / 2, k + 1, n - k) if k < n else 1.0
    return float(lo), float(hi)


def scaled_scenario(duration_s: float, scale: float):
    """The standard scenario with the NIR noise scaled by ``scale``."""
    cfg, dist = standard_scenario(duration_s)
    n = cfg.sensor.noise
    cfg.sensor.noise = n.model_copy(
        update={
            "white_sd": n.white_sd * scale,
            "pink_sd": n.pink_sd * scale,
            "proportional_rel": n.proportional_rel * scale,
        }
    )
    return cfg, dist


def stuck_nir(data: RunData, a: int, n: int) -> RunData:
    y = data.measured.copy()
    y[a : a + n] = y[a]
    return RunData(data.t_s, y, data.inputs, data.events)


def stuck_flow(data: RunData, feeder: str, a: int, n: int) -> RunData:
    inp = data.inputs
    flows = {k: v.copy() for k, v in inp.flows_kg_h.items()}
    flows[feeder][a : a + n] = flows[feeder][a]
    new = LineInputs(inp.t_s, flows, inp.components, inp.refilling, inp.tracers)
    return RunData(data.t_s, data.measured, new, data.events)


def found_stuck(q, series: str, t0: float, t1: float) -> bool:
    return any(
        f.kind == "stuck" and f.series == series and f.t_start_s <= t1 and f.t_end_s >= t0
        for f in q.flags
    )


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--windows", type=int, default=50, help="windows per noise scale")
    ap.add_argument("--noise", default="1,2")
    ap.add_argument("--duration", type=float, default=7200.0)
    ap.add_argument("--stuck-s", type=int, default=30)
    args = ap.parse_args()
    rng = np.random.default_rng(2026)
    for scale in [float(x) for x in args.noise.split(",")]:
        cfg, dist = scaled_scenario(args.duration, scale)
        model = LineModel(cfg)
        flagged, nir_found, flow_found, cpu = 0, 0, 0, []
        kinds: dict[str, int] = {}
        for w in range(args.windows):
            run = simulate_line(cfg, args.duration, seed=50_000 + w, disturbances=dist)
            data = RunData.from_line_run(run)
            c0 = time.process_time()
            q = check_data_quality(data, model)
            cpu.append(time.process_time() - c0)
            flagged += bool(q.flags)
            for f in q.flags:
                kinds[f"{f.series}:{f.kind}"] = kinds.get(f"{f.series}:{f.kind}", 0) + 1
            a = int(rng.integers(200, data.t_s.size - 200))
            t0, t1 = data.t_s[a], data.t_s[a + args.stuck_s - 1]
            q = check_data_quality(stuck_nir(data, a, args.stuck_s), model)
            nir_found += found_stuck(q, "nir", t0, t1)
            q = check_data_quality(stuck_flow(data, "api", a, args.stuck_s), model)
            flow_found += found_stuck(q, "api:flow", t0, t1)
        n = args.windows
        clean = n - flagged
        lo, hi = clopper_pearson(clean, n)
        print(
            f"noise x{scale:g}: clean windows without a flag {clean}/{n} = {clean / n:.3f} "
            f"(95 % CI {lo:.3f}..{hi:.3f}); flags {kinds or 'none'}; "
            f"stuck {args.stuck_s} s found: NIR {nir_found}/{n}, API flow {flow_found}/{n}; "
            f"check CPU median {np.median(cpu) * 1000:.0f} ms"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
