"""Evidence for the material-tracking model (docs/traceability.md): the recall against an
independent parcel simulation for each hopper model, the hopper model's effect on a recall,
and the effect of RTD uncertainty on the recall intervals.

    python benchmarks/trace_evidence.py [--parcel-g 0.1] [--out out/trace_evidence.json]

Line: API 1.2 kg/h from a hopper refilled from 0.4 to 1.0 kg (a lot every 30 min), 6 h at
1 Hz, excipient 10.8 kg/h; blender tanks in series (tau_d 5 s, tau 25 s, n 3). The recalled lot
is api-L0004 (refilled at 2 h). The parcel simulation is ``twin_core.tracking.parcels`` (no code
shared with the model).
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

from twin_core.rtd.models import model_e
from twin_core.tracking import Refill, mixed_fraction, track_lots
from twin_core.tracking.parcels import simulate_parcels
from twin_core.tracking.recall import lot_intervals, recall_coverage, threshold_for_coverage

DT = 1.0
T = np.arange(int(6 * 3600 / DT)) * DT
Q, M0, LOW, HIGH = 1.2, 1.0, 0.4, 1.0
TIS = (5.0, 25.0, 3.0)
LOT = "api-L0004"
COMPONENTS = {"api": "api", "exc": "excipient"}


def refills() -> list[tuple[float, str, float]]:
    first = (M0 - LOW) / Q * 3600.0
    period = (HIGH - LOW) / Q * 3600.0
    times = [first + k * period for k in range(50) if first + k * period < T[-1]]
    return [(x, f"api-L{k + 1:04d}", HIGH - LOW) for k, x in enumerate(times)]


def kernel(tis: tuple[float, float, float]) -> np.ndarray:
    return model_e("tanks_in_series", dict(zip(("tau_d", "tau", "n"), tis)), np.arange(400) * DT)


def trace(alpha: float, tis: tuple[float, float, float] = TIS):
    n = T.size
    return track_lots(
        T,
        {"api": np.full(n, Q), "exc": np.full(n, 10.8)},
        COMPONENTS,
        [(0.0, kernel(tis))],
        [Refill("api", x, x, lot, m) for x, lot, m in refills()],
        {"api": np.r_[M0, np.full(n - 1, np.nan)]},
        alpha,
    )


def parcel_times(alpha: float, parcel_kg: float, tis=TIS, seed: int = 1) -> np.ndarray:
    runs = simulate_parcels(T, Q, ("api-L0000", M0), refills(), alpha, tis, parcel_kg, seed)
    to = runs.t_out_s[runs.lot == runs.lots.index(LOT)]
    return np.sort(to[to < T[-1] + DT])


def score(tr, intervals, to: np.ndarray) -> dict[str, float]:
    """Parcel coverage of the intervals and their extra product over the shortest product
    window holding 99.9 % of the parcels."""
    inside = np.zeros(to.size, dtype=bool)
    for iv in intervals:
        inside |= (to >= iv.t_start_s) & (to < iv.t_end_s + DT)
    total = tr.outlet_kg_s.sum(axis=1)
    cum = np.concatenate([[0.0], np.cumsum(total) * DT])
    grid = np.concatenate([T, [T[-1] + DT]])
    k = int(np.ceil(0.999 * to.size))
    shortest = (
        np.interp(to[k - 1 :], grid, cum) - np.interp(to[: to.size - k + 1], grid, cum)
    ).min()
    product = sum(iv.product_kg for iv in intervals)
    return {
        "parcel_coverage": float(inside.mean()),
        "n_parcels": int(to.size),
        "product_kg": float(product),
        "shortest_999_kg": float(shortest),
        "extra_product": float(product / shortest - 1.0),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parcel-g", type=float, default=0.1)
    ap.add_argument("--out", default="out/trace_evidence.json")
    args = ap.parse_args()
    pk = args.parcel_g / 1000.0
    result: dict[str, object] = {"lot": LOT, "parcel_g": args.parcel_g, "hopper": {}}
    for hopper in ("fifo", "mixture", "mixed"):
        alpha = mixed_fraction(hopper, 0.5)
        tr = trace(alpha)
        to = parcel_times(alpha, pk)
        rows = {}
        for cov in (0.999, 0.9995):
            f = threshold_for_coverage(tr, LOT, cov)
            ivs = lot_intervals(tr, LOT, f)
            rows[str(cov)] = {
                "threshold": f,
                "model_coverage": recall_coverage(tr, LOT, ivs),
                "intervals": [[iv.t_start_s, iv.t_end_s] for iv in ivs],
                **score(tr, ivs, to),
            }
        result["hopper"][hopper] = rows  # type: ignore[index]
        print(hopper, json.dumps(rows))
    # RTD uncertainty: the recall (fifo, 99.95 % model coverage) under each corner of the
    # interval tau_d +- 20 %, tau +- 20 %, n in [2, 4]; the parcel truth at each corner scored
    # against the nominal recall and against the union of the corners' recalls
    nominal = trace(0.0)
    f0 = threshold_for_coverage(nominal, LOT, 0.9995)
    base = lot_intervals(nominal, LOT, f0)
    corners = []
    union_lo, union_hi = base[0].t_start_s, base[-1].t_end_s
    for td, tau, n in itertools.product((4.0, 6.0), (20.0, 30.0), (2.0, 4.0)):
        tr = trace(0.0, (td, tau, n))
        ivs = lot_intervals(tr, LOT, threshold_for_coverage(tr, LOT, 0.9995))
        union_lo, union_hi = min(union_lo, ivs[0].t_start_s), max(union_hi, ivs[-1].t_end_s)
        to = parcel_times(0.0, pk, (td, tau, n))
        corners.append(
            {
                "tis": [td, tau, n],
                "start_shift_s": ivs[0].t_start_s - base[0].t_start_s,
                "end_shift_s": ivs[-1].t_end_s - base[-1].t_end_s,
                "nominal_recall_parcel_coverage": score(nominal, base, to)["parcel_coverage"],
            }
        )
    for c in corners:
        to = parcel_times(0.0, pk, tuple(c["tis"]))  # type: ignore[arg-type]
        inside = (to >= union_lo) & (to < union_hi + DT)
        c["union_recall_parcel_coverage"] = float(inside.mean())
    total = nominal.outlet_kg_s.sum(axis=1)
    union_kg = float(total[(T >= union_lo) & (T <= union_hi)].sum() * DT)
    result["rtd_uncertainty"] = {
        "nominal_interval": [base[0].t_start_s, base[-1].t_end_s],
        "union_interval": [union_lo, union_hi],
        "union_extra_product": union_kg / sum(iv.product_kg for iv in base) - 1.0,
        "corners": corners,
    }
    print(json.dumps(result["rtd_uncertainty"]))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
