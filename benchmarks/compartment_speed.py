"""Speed of the compartment model: build from a 10 x 20 x 20 field, simulate one hour.

Targets (issue 8): build < 2 s (the seed needed 3 + 10 min, chapter 5.2.3); one hour of
whole-blender operation at 0.1 s output < 0.5 s.  Side by side in the same run:

* the peer RTD route (``twin_core.rtd``: axial-dispersion E(t) + ``convolve``) for the same
  hour, the way the line model predicts the outlet today;
* scipy's ``expm_multiply`` on the chained 8-section network for the step response,
  the textbook exact route that the block propagator replaces.

No numba in this area (nothing to compile).  Timings: median of repeats, wall clock.

The network matrices are small and dense (a few hundred compartments): multithreaded
OpenBLAS spins badly on a loaded 2-core machine (a 200 x 200 product measured 50x slower),
so this script pins BLAS to one thread unless OPENBLAS_NUM_THREADS is already set.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from scipy.sparse.linalg import expm_multiply  # noqa: E402

from twin_core.compartment import (  # noqa: E402
    CompartmentModel,
    blender_model_predict,
    blender_model_rtd,
    chain_sections,
    synthetic_blender_fields,
    to_blender_model,
)


def timed(fn, repeat: int = 3) -> tuple[float, object]:
    ts, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), out


def main() -> None:
    print(f"OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}")
    case = synthetic_blender_fields(10, 20, 20)
    noisy = synthetic_blender_fields(10, 20, 20, counts="poisson", seed=1)
    print("== build from a 10 x 20 x 20 field (target < 2 s; seed: 3 + 10 min)")
    for name, fields, src in (
        ("crossings (expected counts)", case.fields, "crossings"),
        ("crossings (Poisson counts)", noisy.fields, "crossings"),
        ("upwinded velocities", case.fields, "velocity"),
    ):
        dt, m = timed(lambda f=fields, s=src: CompartmentModel(flow_source=s).fit(f))
        print(
            f"  {name:28s} {dt:7.3f} s   {m.n_compartments_} compartments, "
            f"{m.periodic_.rate.size} flows, seed ratio {(13 * 60) / dt:,.0f}x faster"
        )
    model = CompartmentModel().fit(case.fields)
    bm = to_blender_model(model, n_sections=8)
    t = np.arange(0.0, 3600.0, 0.1)
    rng = np.random.default_rng(0)
    u = 3.0 + np.repeat(rng.normal(0, 0.1, t.size // 100), 100)
    u[(t >= 600) & (t < 601)] += 10.0

    print("== one hour of whole-blender operation, 0.1 s output (36,000 points; target < 0.5 s)")

    def cold():
        fresh = type(bm).model_validate(bm.model_dump())
        return blender_model_predict(fresh, t, u)

    dt_cold, y = timed(cold)
    blender_model_predict(bm, t, u)
    dt_warm, _ = timed(lambda: blender_model_predict(bm, t, u), repeat=5)
    dt_dyn, _ = timed(
        lambda: blender_model_predict(bm, t, u, flow_scale=np.where(t < 1800, 1.0, 0.7)), repeat=3
    )
    print(f"  compartment model, first call (computes the RTD)  {dt_cold:7.3f} s")
    print(f"  compartment model, later calls (RTD cached)       {dt_warm:7.3f} s")
    print(f"  compartment model, dynamic flows (rpm change)     {dt_dyn:7.3f} s")
    print(f"  mass balance check: sum(out)/sum(in) = {y.sum() / u.sum():.6f}")

    try:
        from twin_core.rtd.convolution import convolve
        from twin_core.rtd.models import axial_dispersion_open

        tau = bm.mean_residence_time_s

        def peer():
            e = axial_dispersion_open(t, 0.0, tau, 10.0)
            return convolve(t, u, e)

        dt_peer, _ = timed(peer)
        print(
            f"  peer RTD route (axial dispersion + rtd.convolve)  {dt_peer:7.3f} s   "
            f"ratio peer/ours(warm) = {dt_peer / dt_warm:.1f}, peer/ours(cold) = "
            f"{dt_peer / dt_cold:.2f}"
        )
    except ImportError as exc:  # pragma: no cover - peer area absent
        print(f"  peer RTD route unavailable: {exc}")

    sec = model.section_
    chain = chain_sections(sec, 8)
    A = chain.rate_matrix().tocsc()
    m0 = chain.impulse_state()
    tt = np.arange(0.0, 120.0, 0.1)
    dt_em, _ = timed(
        lambda: expm_multiply(A, m0, start=0.0, stop=tt[-1], num=tt.size, endpoint=True),
        repeat=1,
    )
    dt_ours, _ = timed(lambda: blender_model_rtd(bm, tt), repeat=1)
    print(
        f"== impulse response, 8 chained sections ({chain.n} states), 0-120 s at 0.1 s:\n"
        f"  scipy expm_multiply on the chain {dt_em:7.3f} s, block propagator + FFT "
        f"convolution {dt_ours:7.3f} s (ratio {dt_em / dt_ours:.1f}x)"
    )


if __name__ == "__main__":
    main()
