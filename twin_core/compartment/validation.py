"""Compare a model RTD with a reference (DEM particle transit times or an exact RTD).

Metrics: mean and variance (with standard errors for samples), the Kolmogorov-Smirnov
distance sup |F_model - F_ref| and the Wasserstein-1 (earth mover's) distance
int |F_model - F_ref| dt (Villani, *Optimal Transport*, 2009, Remark 6.6: for 1-D
distributions W1 is the L1 distance of the CDFs), also relative to the reference mean.

A DEM run observes only the transits that start and end inside its recording window of length
W; for a stationary process such intervals have the density E(t) (W - t)+ / norm (window
censoring of renewal intervals, Cox, *Renewal Theory*, 1962, ch. 5; the same length bias as
in survival analysis).  :func:`window_censored` applies it to a model E(t) so that it can be
compared with the transit times of a run shorter than the RTD's tail.
"""

from __future__ import annotations

import numpy as np


def window_censored(t: np.ndarray, e: np.ndarray, window_s: float) -> np.ndarray:
    """E_W(t) = E(t) (W - t)+ / int E(s) (W - s)+ ds: the law of transits observed entirely
    inside a recording window of length W (module docstring)."""
    if window_s <= 0:
        raise ValueError(f"window_s must be > 0, got {window_s}")
    t = np.asarray(t, dtype=float)
    w = np.asarray(e, dtype=float) * np.clip(window_s - t, 0.0, None)
    area = float(np.trapezoid(w, t))
    if area <= 0:
        raise ValueError(f"no model transit fits in a window of {window_s} s")
    return w / area


def _cdf_from_e(t: np.ndarray, e: np.ndarray) -> np.ndarray:
    F = np.concatenate([[0.0], np.cumsum(0.5 * (e[1:] + e[:-1]) * np.diff(t))])
    return np.minimum(F, 1.0)


def compare_rtd(
    t: np.ndarray,
    e_model: np.ndarray,
    e_ref: np.ndarray | None = None,
    samples: np.ndarray | None = None,
) -> dict[str, float]:
    """Mean, variance, KS and W1 of the model E(t) against ``e_ref`` on the same grid or
    against transit-time ``samples`` (s; non-finite samples are dropped and counted)."""
    t = np.asarray(t, dtype=float)
    e_model = np.asarray(e_model, dtype=float)
    if e_model.shape != t.shape:
        raise ValueError(f"e_model must have the shape of t {t.shape}, got {e_model.shape}")
    if (e_ref is None) == (samples is None):
        raise ValueError("give exactly one of e_ref or samples")
    Fm = _cdf_from_e(t, e_model)
    area_m = float(Fm[-1])
    mean_m = float(np.trapezoid(t * e_model, t) / area_m)
    var_m = float(np.trapezoid((t - mean_m) ** 2 * e_model, t) / area_m)
    out: dict[str, float] = {"model_area": area_m, "model_mean": mean_m, "model_var": var_m}
    if e_ref is not None:
        e_ref = np.asarray(e_ref, dtype=float)
        if e_ref.shape != t.shape:
            raise ValueError(f"e_ref must have the shape of t {t.shape}, got {e_ref.shape}")
        Fr = _cdf_from_e(t, e_ref)
        area_r = float(Fr[-1])
        mean_r = float(np.trapezoid(t * e_ref, t) / area_r)
        var_r = float(np.trapezoid((t - mean_r) ** 2 * e_ref, t) / area_r)
        out.update(ref_area=area_r, ref_mean=mean_r, ref_var=var_r)
    else:
        s = np.asarray(samples, dtype=float)
        fin = np.isfinite(s)
        s = np.sort(s[fin])
        if s.size < 2:
            raise ValueError(f"samples needs >= 2 finite values, got {s.size}")
        Fr = np.searchsorted(s, t, side="right") / s.size
        mean_r = float(s.mean())
        var_r = float(s.var(ddof=1))
        m4 = float(np.mean((s - mean_r) ** 4))
        out.update(
            ref_mean=mean_r,
            ref_var=var_r,
            ref_mean_se=float(np.sqrt(var_r / s.size)),
            ref_var_se=float(np.sqrt(max(m4 - var_r**2, 0.0) / s.size)),
            ref_n=float(s.size),
            ref_dropped=float((~fin).sum()),
        )
    dF = np.abs(Fm - Fr)
    out["ks"] = float(dF.max())
    out["w1_s"] = float(np.trapezoid(dF, t))
    out["w1_rel"] = out["w1_s"] / mean_r
    out["mean_rel_err"] = (mean_m - mean_r) / mean_r
    out["var_rel_err"] = (var_m - var_r) / var_r if var_r > 0 else float("nan")
    return out
