"""The diverter's window of a flagged feeder disturbance: lot boundaries vs predicted excursion.

On the ordinary records of ``benchmarks/live_decisions.py`` (line1 with refills, a line-rate
change and flow disturbances; the plant's truth the declared Table 6.2 blender, the twin's
prediction the compartment-model blender of ``line1.yaml``), the blender's and the diverter's
cores (``twin_core.online.recorded.RecordedDecisions``, no bus: the same decisions as the
services on the same messages) decide with each window rule; good product diverted and OOS
product accepted are scored against the simulator's true outlet, each command's window held
until the alert's next command replaces it.

Run: ``python benchmarks/divert_window_tuning.py --seeds 0:4`` (the seeds the defaults were
chosen on) and ``--seeds 4:8`` (held out).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import benchmarks.live_decisions as ld  # noqa: E402
from benchmarks.machine import describe  # noqa: E402
from schemas.line import LineSpec  # noqa: E402
from twin_core.online.recorded import RecordedDecisions  # noqa: E402

RULES = [
    ("lot", 0.0, 0.0),
    ("excursion", 0.3, 5.0),
    ("excursion", 0.2, 3.0),
    ("excursion", 0.1, 2.0),
    ("excursion", 0.0, 0.0),
]


def decided_windows(spec: LineSpec, msgs: list) -> list[tuple[float, float]]:
    """The divert windows the cores decide on ``msgs``, each until its successor."""
    rd = RecordedDecisions(spec)
    outs = []
    for k, m in msgs:
        outs += rd.push(k, m)[1]
    outs += rd.finish()
    cmds: dict[str, list[tuple[float, float, float, str]]] = {}
    for o in outs:
        if o.kind == "divert":
            cmds.setdefault(o.alert_id, []).append((o.t, o.t_start, o.t_end, "divert"))
    return [w for own in ld.gate_windows(cmds).values() for w in own]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0:4", help="first:last+1")
    ap.add_argument("--hours", type=float, default=3.0)
    args = ap.parse_args(argv)
    a, b = (int(x) for x in args.seeds.split(":"))
    spec0 = LineSpec.from_file(ld.LINE)
    recs = [ld.ordinary_record(s, args.hours) for s in range(a, b)]
    print(describe())
    print(f"seeds {a}..{b - 1}, {args.hours:g} h each\n")
    print(
        "| window | guard % w/w | pad s | false divert kg (% of production) | missed OOS kg (% of OOS) |"
    )
    print("|---|---|---|---|---|")
    for mode, guard, pad in RULES:
        spec = spec0.model_copy(deep=True)
        spec.oos.divert_window = mode
        spec.oos.divert_guard_pct_w_w, spec.oos.divert_pad_s = guard, pad
        fd = mi = oo = pr = 0.0
        t0 = time.perf_counter()
        for run, msgs, _ in recs:
            mass, oos = ld.truth(run, spec)
            dv = ld.union_mask(decided_windows(spec, msgs), run.t_s)
            fd += mass[dv & ~oos].sum()
            mi += mass[oos & ~dv].sum()
            oo += mass[oos].sum()
            pr += mass.sum()
        print(
            f"| {mode} | {guard:g} | {pad:g} | {fd:.3f} ({100 * fd / pr:.2f} %) | {mi:.3f} of "
            f"{oo:.3f} ({100 * mi / oo:.2f} %) |  <!-- {time.perf_counter() - t0:.0f} s -->",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
