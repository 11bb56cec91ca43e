"""Decisions, not diagnoses: which side of the probe the diverter acts on when the data cannot tell.

A close-loop finding can name a probe-side effect (the NIR reads wrong, the product is fine)
whose product-side look-alike (the product is off, the NIR reads it right) fits the data as
well. Three policies for what the diverter does with such a finding, each scored on the
product the plant really made:

- ``product-side`` (the twin's policy, ``schemas.closeloop.ModelFinding.product_reading``):
  when any product-side explanation is among the equivalents of a claim, act on the
  product-side reading: divert where its outlet leaves the specification;
- ``best-supported``: act on the product-side reading only when the best-scoring explanation
  (lowest whole-record BIC among the claim and its equivalents) is product-side;
- ``weighted``: weigh the explanations by their BIC weights w_i = exp(-dBIC_i / 2) / sum
  (Burnham & Anderson 2002, ch. 2.9) and act on the product-side reading when the product
  side's weight is >= 1 / (1 + k), k = 3 the cost of accepting a kilogram of bad product over
  diverting a kilogram of good product (a Bayes decision with that loss).

Records: the open-world benchmark's look-alike pairs (``twin_core.plant.openworld_cases``:
the product-side effect through the finite-volume blender, or the probe-side effect fitted to
give the same noise-free reading), at the benchmark's size and at ``--scale`` times it (large
enough to take the product out of specification), in the "no tracers, noise x1" setting. The
close-loop runs offline on each whole record (``twin_core.closeloop.check.check_recording``);
the diverter's own decisions on the record (funnel, predicted and measured outlet:
``twin_core.online.recorded.RecordedDecisions``) are the same under every policy, and the
policy's windows are added to them. Scored against the simulator's true outlet: good product
diverted, OOS product accepted.

Run: ``python benchmarks/closeloop_policies.py [--seeds 2] [--scale 4]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import benchmarks.live_decisions as ld  # noqa: E402
from benchmarks.divert_window_tuning import decided_windows  # noqa: E402
from benchmarks.machine import describe  # noqa: E402
from schemas.line import LineSpec  # noqa: E402
from twin_core.closeloop.attribution import out_of_spec_spans  # noqa: E402
from twin_core.closeloop.check import check_recording  # noqa: E402
from twin_core.closeloop.identify import IdentifyOptions  # noqa: E402
from twin_core.plant.model import LineModel  # noqa: E402
from twin_core.plant.openworld_cases import LOOKALIKE_PAIRS, Case, Setting, run_case  # noqa: E402

LINE = ROOT / "services" / "configs" / "line1.yaml"
POLICIES = ("product-side", "best-supported", "weighted")
#: cost of accepting bad product over diverting good product (the weighted policy)
MISS_COST = 3.0


def scaled_case(pair: str, role: str, scale: float) -> Case:
    """The look-alike case with its product-side effect's size times ``scale``."""
    case = Case.lookalike(pair, role)
    if scale == 1.0:
        return case
    p = LOOKALIKE_PAIRS[pair]
    spec = {**p.product, "params": {k: v * scale for k, v in p.product["params"].items()}}
    LOOKALIKE_PAIRS[f"{pair}x{scale:g}"] = type(p)(spec, p.probe)
    return Case.lookalike(f"{pair}x{scale:g}", role)


def line_spec(cfg: Any) -> LineSpec:
    """The run's declared line with line1's specification and OOS settings."""
    base = LineSpec.from_file(LINE)
    data = base.model_dump()
    data.update(cfg.model_dump())
    data["services"] = ["blender", "oos"]
    return LineSpec.model_validate(data)


def explanations(report: dict[str, Any]) -> list[tuple[str, float]]:
    """(side, delta BIC) of every claimed effect and its equivalents."""
    out = []
    for e in report.get("effects", []):
        out.append((e.get("side") or "probe", 0.0))
        out += [(q.get("side") or "probe", float(q["delta_bic"])) for q in e.get("equivalents", [])]
    return out


def acts_on_product(report: dict[str, Any], policy: str) -> bool:
    """Whether ``policy`` acts on the report's product-side reading (module docstring)."""
    ex = explanations(report)
    if not report.get("product_reading") or not any(s == "product" for s, _ in ex):
        return False
    if policy == "product-side":
        return True
    if policy == "best-supported":
        return min(ex, key=lambda x: x[1])[0] == "product"
    d = np.array([x[1] for x in ex])
    w = np.exp(-(d - d.min()) / 2.0)
    w_product = float(w[[s == "product" for s, _ in ex]].sum() / w.sum())
    return w_product >= 1.0 / (1.0 + MISS_COST)


def policy_windows(report: dict[str, Any], spec: LineSpec, run: Any) -> list[tuple[float, float]]:
    """The stretches the product-side reading puts out of specification."""
    reading = report["product_reading"]
    model = LineModel(spec, reading["effects"])
    comp = spec.sensor.component
    c = model.outlet(run.inputs())[comp]
    lim = next(s for s in spec.spec if s.component == comp)
    t = run.t_s
    m = (t >= reading["t_start_s"]) & (t <= reading["t_end_s"])
    return out_of_spec_spans(t[m], c[m], lim.lower_pct_w_w, lim.upper_pct_w_w)


def score(
    run: Any, spec: LineSpec, windows: list[tuple[float, float]]
) -> tuple[float, float, float]:
    """(good product diverted, OOS product accepted, OOS product) kg."""
    mass, oos = ld.truth(run, spec)
    dv = ld.union_mask(windows, run.t_s)
    return float(mass[dv & ~oos].sum()), float(mass[oos & ~dv].sum()), float(mass[oos].sum())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--scale", type=float, default=4.0)
    ap.add_argument("--out", type=Path, default=Path("out/closeloop_policies.jsonl"))
    args = ap.parse_args(argv)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    setting = Setting(tracers=False, noise=1.0)
    rows = []
    print(describe(), flush=True)
    for scale in (1.0, args.scale):
        for pair in list(LOOKALIKE_PAIRS)[:4]:
            for role in ("product", "probe"):
                for seed in range(args.seeds):
                    t0 = time.perf_counter()
                    cr = run_case(scaled_case(pair, role, scale), setting, 700000 + seed)
                    spec = line_spec(cr.run.config)
                    report = check_recording(cr.messages, cr.run.config, IdentifyOptions())
                    base = decided_windows(spec, cr.messages)
                    row = {"pair": pair, "role": role, "scale": scale, "seed": seed}
                    row["status"] = report["status"]
                    row["claims"] = [e["label"] for e in report.get("effects", [])]
                    row["baseline"] = score(cr.run, spec, base)
                    for pol in POLICIES:
                        extra = []
                        if acts_on_product(report, pol):
                            extra = policy_windows(report, spec, cr.run)
                        row[pol] = score(cr.run, spec, base + extra)
                    rows.append(row)
                    with args.out.open("a") as fh:
                        fh.write(json.dumps(row) + "\n")
                    print(
                        f"{pair} x{scale:g} {role} seed {seed}: {row['status']} {row['claims']} "
                        + " ".join(f"{p} {row[p][0]:.3f}/{row[p][1]:.3f}" for p in POLICIES)
                        + f" of OOS {row['baseline'][2]:.3f} ({time.perf_counter() - t0:.0f} s)",
                        flush=True,
                    )
    print("\n| size | policy | good product diverted kg | OOS product accepted kg (of) |")
    print("|---|---|---|---|")
    for scale in (1.0, args.scale):
        rs = [r for r in rows if r["scale"] == scale]
        for pol in ("baseline", *POLICIES):
            fd = sum(r[pol][0] for r in rs)
            mi = sum(r[pol][1] for r in rs)
            oo = sum(r[pol][2] for r in rs)
            print(f"| x{scale:g} | {pol} | {fd:.3f} | {mi:.3f} ({oo:.3f}) |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
