"""RTD pipeline and funnel benchmarks (targets: pipeline < 50 ms, 200 x 200 funnel < 1 s).

Run: python benchmarks/rtd_pipeline.py. Side by side in one run:
- pipeline (Hampel + wavelet denoise + truncation + AD fit) vs the same fit done with
  scipy.optimize.curve_fit on the raw profile (the usual script approach);
- funnel by the closed form h max(F(t) - F(t-d)) vs brute-force time-domain convolution of
  every pulse (the seed's workflow), reporting the ratio and the max difference;
- peers rtdpy / bio-rtd are timed if importable (rtdpy fails on numpy 2.x).
Medians of repeated runs; the machine is shared, so compare the ratios.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.optimize import curve_fit

from twin_core.quality.funnel import funnel, funnel_brute_force
from twin_core.rtd.denoise import denoise
from twin_core.rtd.fitting import fit
from twin_core.rtd.models import axial_dispersion_open
from twin_core.rtd.noise import synthesize
from twin_core.rtd.outliers import hampel
from twin_core.rtd.profiles import e_curve
from twin_core.rtd.truncation import truncate_relative


def median_time(fn, repeat: int = 7) -> float:
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def main() -> None:
    t = np.arange(1000) * 0.25
    s = 10 * axial_dispersion_open(t, 11.92, 16.37, 7.67) / 0.0436
    rng = np.random.default_rng(0)
    y = s + synthesize(s, 0.1, 0.07, 0.03, rng)
    y[rng.choice(1000, 8, replace=False)] += 3.0

    def pipeline():
        c = hampel(y, t=t).y
        d = denoise(c, "wavelet").y
        tr = truncate_relative(d, 0.0375)
        return fit(t, e_curve(t, tr), "ad_open")

    def plain_curve_fit():
        e = e_curve(t, y)
        return curve_fit(axial_dispersion_open, t, e, p0=(5.0, 20.0, 5.0), bounds=(0, np.inf))

    pipeline()  # warm caches
    tp = median_time(pipeline)
    tc = median_time(plain_curve_fit)
    steps = {
        "hampel": median_time(lambda: hampel(y, t=t)),
        "wavelet": median_time(lambda: denoise(y, "wavelet")),
        "fit": median_time(lambda: fit(t, e_curve(t, y), "ad_open")),
    }
    r = pipeline()
    print("== RTD pipeline, 1000 samples (outliers + wavelet + truncation + AD fit)")
    print(f"pipeline            {1e3 * tp:8.2f} ms   (target < 50 ms)  params {r.params}")
    print("  steps: " + ", ".join(f"{k} {1e3 * v:.2f} ms" for k, v in steps.items()))
    print(f"curve_fit raw only  {1e3 * tc:8.2f} ms   ratio pipeline/curve_fit {tp / tc:.2f}")

    tf = np.arange(0.0, 300.0, 0.25)
    e = axial_dispersion_open(tf, 11.92, 16.37, 7.67)
    d = np.linspace(0, 60, 200)
    h = np.linspace(0, 50, 200)
    funnel(tf, e, d, h)
    tfun = median_time(lambda: funnel(tf, e, d, h), 5)
    d_small = d[::20]
    h_small = h[::20]
    tb = median_time(lambda: funnel_brute_force(tf, e, d_small, h_small), 1)
    tb_full = tb * (d.size * h.size) / (d_small.size * h_small.size)
    a = funnel(tf, e, d_small, h_small)
    b = funnel_brute_force(tf, e, d_small, h_small)
    print("== funnel 200 x 200 (1200-sample E)")
    print(f"closed form         {1e3 * tfun:8.2f} ms   (target < 1000 ms)")
    print(
        f"brute force (est.)  {1e3 * tb_full:8.0f} ms   ratio {tb_full / tfun:.0f}x; "
        f"max |diff| {np.max(np.abs(a.max_dev - b.max_dev)):.3g} % on a 10 x 10 subgrid"
    )
    for peer in ("rtdpy", "bio_rtd"):
        try:
            __import__(peer)
            print(f"peer {peer}: importable (not timed here: no common pipeline API)")
        except Exception as exc:  # noqa: BLE001 - report any import failure
            print(f"peer {peer}: not available ({type(exc).__name__}: {exc})")


if __name__ == "__main__":
    main()
