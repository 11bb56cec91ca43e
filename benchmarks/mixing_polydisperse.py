"""Which mixing indices suit polydisperse beds: every index, number- and volume-weighted, on
packed beds whose species differ in size, beside an equal-size control.

Three beds of the same solid volume (that of 6,000 spheres of radius 1 mm) in a cylinder of
radius 25 mm, two species of equal volume:

* ``equal``: every radius 1 mm (the control: the indices' random-mixture readings);
* ``lognormal``: 10 radius classes of a log-normal distribution (median 1 mm, log-std 0.25),
  the species drawn at random, so both have the same size distribution;
* ``bidisperse``: the tracer of radius 0.75 mm, the other species 1.5 mm (species that differ
  in size, radius ratio 2).

Each bed is packed in three states: ``segregated`` (the tracer starts in the lower part of the
cylinder, the other species above it), ``intermediate`` (half the particles start at random
heights) and ``random`` (every particle starts at a random height). The three packings are the
frames of one run (same particle ids), so the reference-frame indices (VRR, NDM, SM, SSI) take
the segregated packing as their initial state. Cylindrical bins 8 x 4 x 6 hold ~60 particles
of the control each.

The bias of an index on a bed is how far its reading in a state lies from the control's
reading in the same state, as a fraction of the control's full range (segregated -> random):
``bias = (x - x_control) / (x_segregated,control - x_random,control)``, taken at the
segregated and at the random state. An index "suits polydisperse beds" when |bias| < 10 % in
both states on both polydisperse beds with number weighting ("yes"), only with volume
weighting ("with volume weighting"), or neither ("no"). A reference-frame index (VRR, VBBC,
SM, NDM, SSI) reads its initial value at the segregated state by construction.

Run: ``python benchmarks/mixing_polydisperse.py`` (about a minute; prints the table).
"""

from __future__ import annotations

import math
import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from machine import describe  # noqa: E402
from mixing_beds import lognormal_radii, packed_cylinder  # noqa: E402

from twin_core.dem.frames import Frame  # noqa: E402
from twin_core.mixing import (  # noqa: E402
    INDEX_NAMES,
    VOLUME_WEIGHTED,
    CylindricalGrid,
    MixingConfig,
    compute_indices,
)
from twin_core.mixing.properties import index_properties  # noqa: E402

SOLID_VOLUME = 6000 * 4.0 / 3.0 * math.pi * 1e-3**3
CYLINDER_RADIUS = 0.025
STATES = {"segregated": 0.0, "intermediate": 0.5, "random": 1.0}
BIAS_LIMIT = 0.10


def bed_radii(kind: str, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Radii and types (0 = tracer) of a bed of :data:`SOLID_VOLUME`, species of equal volume."""
    if kind == "equal":
        n = round(SOLID_VOLUME / (4.0 / 3.0 * math.pi * 1e-3**3))
        return np.full(n, 1e-3), (np.arange(n) % 2).astype(np.int64)
    if kind == "bidisperse":
        v = 0.5 * SOLID_VOLUME / (4.0 / 3.0 * math.pi)
        n_a, n_b = round(v / 0.75e-3**3), round(v / 1.5e-3**3)
        radii = np.concatenate([np.full(n_a, 0.75e-3), np.full(n_b, 1.5e-3)])
        return radii, np.repeat([0, 1], [n_a, n_b]).astype(np.int64)
    if kind == "lognormal":
        r = lognormal_radii(8000, rng)
        r = r[np.cumsum(4.0 / 3.0 * math.pi * r**3) <= SOLID_VOLUME]
        return r, (rng.random(len(r)) < 0.5).astype(np.int64)
    raise ValueError(f"unknown bed {kind!r}")


def start_heights(
    types: np.ndarray, radii: np.ndarray, randomised: float, rng: np.random.Generator
) -> np.ndarray:
    """Starting heights (fractions of the bed height): the tracer below the volume fraction it
    holds, the other species above; a share ``randomised`` of the particles anywhere."""
    v = radii**3
    cut = v[types == 0].sum() / v.sum()
    z = np.where(types == 0, cut * rng.random(len(types)), cut + (1 - cut) * rng.random(len(types)))
    anywhere = rng.random(len(types)) < randomised
    z[anywhere] = rng.random(anywhere.sum())
    return z


def run_bed(kind: str, seed: int = 0) -> dict[str, pd.DataFrame]:
    """Indices of the bed's three states, per weighting (``"number"``, ``"volume"``)."""
    rng = np.random.default_rng(seed)
    radii, types = bed_radii(kind, rng)
    ids = np.arange(len(radii))
    frames, height = [], 0.0
    for k, share in enumerate(STATES.values()):
        heights = start_heights(types, radii, share, rng)
        bed = packed_cylinder(radii, rng, CYLINDER_RADIUS, heights=heights)
        frames.append(Frame(float(k), ids, types, radii, bed.positions, np.zeros((len(ids), 3))))
        height = bed.height
    grid = CylindricalGrid((0.0, 0.0), CYLINDER_RADIUS, 0.0, height, (8, 4, 6))
    out = {}
    for weight in ("number", "volume"):
        cfg = MixingConfig(grid=grid, weight=weight, sm_pairs=20_000)
        df = compute_indices(frames, "all", cfg)
        df.index = list(STATES)
        out[weight] = df
    return out


def bias(value: float, control: float, control_segregated: float, control_random: float) -> float:
    """Shift of a reading from the control's in the same state, over the control's full
    range (segregated -> random)."""
    return (value - control) / (control_segregated - control_random)


def verdict(b_number: list[float], b_volume: list[float] | None) -> str:
    """'yes', 'with volume weighting' or 'no' from the biases on the polydisperse beds."""
    if all(abs(b) < BIAS_LIMIT for b in b_number):
        return "yes"
    if b_volume is not None and all(abs(b) < BIAS_LIMIT for b in b_volume):
        return "with volume weighting"
    return "no"


def table(results: dict[str, dict[str, pd.DataFrame]]) -> pd.DataFrame:
    """One row per index: the control's readings, the polydisperse beds' segregated and random
    readings per weighting, the largest |bias| per weighting, the seed's Figure 4.4 size
    column and the verdict."""
    ctrl = results["equal"]["number"]
    size_col = index_properties()["size"]
    rows = []
    for name in INDEX_NAMES:
        seg, rnd = ctrl.loc["segregated", name], ctrl.loc["random", name]
        row = {"index": name, "fig_4_4_size": "Y" if size_col[name] else "N",
               "control_segregated": seg, "control_random": rnd}  # fmt: skip
        b = {"number": [], "volume": []}
        for kind in ("lognormal", "bidisperse"):
            for weight in ("number", "volume"):
                for state, x_ctrl in (("segregated", seg), ("random", rnd)):
                    x = results[kind][weight].loc[state, name]
                    row[f"{kind}_{weight}_{state}"] = x
                    b[weight].append(bias(x, x_ctrl, seg, rnd))
        row["max_bias_number"] = max(abs(v) for v in b["number"])
        row["max_bias_volume"] = max(abs(v) for v in b["volume"])
        weighted = name in VOLUME_WEIGHTED
        row["suits_polydisperse"] = verdict(b["number"], b["volume"] if weighted else None)
        rows.append(row)
    return pd.DataFrame(rows).set_index("index")


def main() -> None:
    print(describe())
    print("load average (1, 5, 15 min): {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))
    results = {kind: run_bed(kind) for kind in ("equal", "lognormal", "bidisperse")}
    for kind, res in results.items():
        print(f"\n{kind}: number weighting")
        print(res["number"].drop(columns=["t"]).round(3).T.to_string())
    tab = table(results)
    pd.set_option("display.width", 250)
    print("\nreadings (segregated / random) and largest |bias| (fraction of the control's range)")
    out = pd.DataFrame(index=tab.index)
    out["Fig4.4 size"] = tab["fig_4_4_size"]
    out["control"] = _pair(tab, "control_segregated", "control_random")
    for kind in ("bidisperse", "lognormal"):
        for weight in ("number", "volume"):
            out[f"{kind} {weight}"] = _pair(
                tab, f"{kind}_{weight}_segregated", f"{kind}_{weight}_random"
            )
    out["bias number"] = tab["max_bias_number"].map("{:.2f}".format)
    out["bias volume"] = tab["max_bias_volume"].map("{:.2f}".format)
    out["suits polydisperse"] = tab["suits_polydisperse"]
    print(out.to_string())


def _pair(tab: pd.DataFrame, a: str, b: str) -> pd.Series:
    """``"x / y"`` of two columns, three significant digits."""
    return tab[a].map("{:.3g}".format) + " / " + tab[b].map("{:.3g}".format)


if __name__ == "__main__":
    main()
