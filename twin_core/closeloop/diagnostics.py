"""Diagnostics of the residual r(t) = measured(t) - predicted(t).

``residual_diagnostics`` returns a plain dict (JSON-able) with

- ``bias`` (mean, % w/w) and ``trend`` (slope, % w/w per hour) with z-scores: given the noise's
  whitener (``twin_core.closeloop.noise.NoiseWhitener``), generalised least squares on the
  innovations, so the z-scores allow for the 1/f noise (the effective sample size of a level is
  what the coloured noise leaves of it, reported as ``n_effective``); without one, ordinary
  least squares with n_eff = n (1 - rho1) / (1 + rho1) (AR(1) variance inflation, Bayley &
  Hammersley 1946), which slow noise fools;
- ``normalized_mse``: mean of (r / sigma)^2 with sigma the declared noise standard deviation
  (1 when the declared noise explains the residual);
- ``acf`` (autocorrelation at lags 1..max_lag) and the Ljung-Box statistic (Ljung & Box 1978);
- ``spectrum``: Welch power spectral density (Welch 1967), its log-log slope and the share of
  power below 1/300 Hz;
- ``cross_correlation``: for each feeder, the largest |normalised cross-correlation| of the
  residual with the flow deviation and (``<feeder>:screw_speed``) with the screw speed, at lags
  0..max_xcorr_lag_s (the residual lags the input);
- ``events``: event-locked mean residual per event kind over [t_e, t_e + window_s] with z
  (the given events plus ``rpm_change``: steps of a screw speed);
- ``pulse_tails``: for each tracer pulse, the mean residual in its front (rise), peak and tail
  windows (dead zones and bypasses show in the tail and the front).

:func:`innovation_tests` decides whether a model's innovations are the noise (the honest status
of ``twin_core.closeloop.identify``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy import signal, stats

from twin_core.plant.model import LineInputs


def _acf(x: np.ndarray, max_lag: int) -> np.ndarray:
    x = x - x.mean()
    n = x.size
    f = np.fft.rfft(x, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[: max_lag + 1]
    return ac / ac[0] if ac[0] > 0 else np.zeros(max_lag + 1)


def n_effective(x: np.ndarray) -> float:
    """Effective sample size n (1 - rho1) / (1 + rho1) of a series (AR(1) approximation)."""
    x = np.asarray(x, dtype=float)
    if x.size < 3:
        return float(x.size)
    rho = float(np.clip(_acf(x, 1)[1], -0.99, 0.99))
    return float(max(2.0, x.size * (1 - rho) / (1 + rho)))


def max_cross_correlation(
    rc: np.ndarray, m: np.ndarray, x: np.ndarray, max_lag: int
) -> tuple[float, int] | None:
    """Largest |normalised cross-correlation| of a residual with an input, the residual lagging:

        rho(L) = sum r[n + L] u[n] / sqrt(sum r[n + L]^2 sum u[n]^2),  u = x - mean(x),

    over the samples with ``m[n + L]`` (Box & Jenkins, Time Series Analysis, ch. 11: the
    cross-correlation check of a transfer-function model's residual against its input).
    ``rc``: the residual, centred, 0 outside ``m``. Returns (rho at the best lag, lag in
    samples), or None for a constant input.
    """
    u = np.asarray(x, dtype=float) - float(np.mean(x))
    if u.std() == 0:
        return None
    vals = []
    for lag in range(0, max_lag + 1):
        a = rc[lag:]
        b = u[: u.size - lag]
        mm = m[lag:]
        if mm.sum() < 10:
            vals.append(0.0)
            continue
        den = np.sqrt(np.sum(a[mm] ** 2) * np.sum(b[mm] ** 2))
        vals.append(float(np.sum(a[mm] * b[mm]) / den) if den > 0 else 0.0)
    j = int(np.argmax(np.abs(vals)))
    return vals[j], j


def rpm_change_events(
    t_s: np.ndarray, rpm: np.ndarray, source: str, rel: float = 0.05, window: int = 5
) -> list[dict[str, Any]]:
    """Steps of a screw speed as events ``{"t_s", "kind": "rpm_change", "source"}``.

    A step is where the running median over ``window`` samples (robust to single spikes)
    changes within ``window`` samples by more than ``rel`` of its median level and by more than
    six times the speed's own sample noise (1.4826 MAD of the first differences / sqrt 2: a
    controller's normal hunting is not a step); one event per step (the first sample of each
    run of flagged samples).
    """
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(rpm, dtype=float)
    if x.size < 2 * window + 1:
        return []
    med = signal.medfilt(x, kernel_size=2 * (window // 2) + 1)
    level = float(np.median(np.abs(med)))
    if level <= 0:
        return []
    dx = np.diff(x)
    noise = 1.4826 * float(np.median(np.abs(dx - np.median(dx)))) / np.sqrt(2.0)
    d = np.abs(med[window:] - med[:-window])
    flag = np.concatenate([np.zeros(window, bool), d > max(rel * level, 6.0 * noise)])
    starts = np.flatnonzero(flag & ~np.concatenate([[False], flag[:-1]]))
    return [{"t_s": float(t[i]), "kind": "rpm_change", "source": source} for i in starts]


def residual_diagnostics(
    t_s: np.ndarray,
    residual: np.ndarray,
    sigma: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    inputs: LineInputs | None = None,
    events: Sequence[dict[str, Any]] = (),
    max_lag: int = 30,
    max_xcorr_lag_s: float = 120.0,
    window_s: float = 120.0,
    pulse_windows: dict[str, tuple[float, float]] | None = None,
    whitener: Callable[[np.ndarray], np.ndarray] | None = None,
) -> dict[str, Any]:
    """Diagnostics of a residual on the samples ``mask`` (default: all finite). See module.

    ``pulse_windows``: {"front": (a, b), "peak": ..., "tail": ...} in s after each pulse
    (default: 5-25, 25-45, 45-150 s, fitting the Table 6.2 blender). ``whitener``: the noise's
    innovations map for ``residual / sigma`` (needs ``sigma``): bias and trend by generalised
    least squares.
    """
    t = np.asarray(t_s, dtype=float)
    r = np.asarray(residual, dtype=float)
    m = np.isfinite(r) if mask is None else (np.asarray(mask, bool) & np.isfinite(r))
    if m.sum() < 10:
        raise ValueError(f"residual must hold >= 10 finite samples in the mask, got {int(m.sum())}")
    dt = float(t[1] - t[0])
    rr = r[m]
    tt = t[m]
    n = rr.size
    neff = n_effective(rr)
    sd = float(rr.std(ddof=1))
    out: dict[str, Any] = {"n": int(n), "n_effective": neff, "rmse": float(np.sqrt(np.mean(rr**2)))}
    out["mae"] = float(np.mean(np.abs(rr)))
    if whitener is not None and sigma is not None:
        bias, trend, out["n_effective"] = _level_and_trend_gls(t, r, np.asarray(sigma), m, whitener)
        out["bias"], out["trend"] = bias, trend
    else:
        out["bias"] = {
            "mean": float(rr.mean()),
            "z": float(rr.mean() / (sd / np.sqrt(neff)) if sd > 0 else 0.0),
        }
        x = (tt - tt.mean()) / 3600.0
        sxx = float(x @ x)
        slope = float(x @ (rr - rr.mean()) / sxx) if sxx > 0 else 0.0
        res = rr - rr.mean() - slope * x
        se = (
            float(np.sqrt(res @ res / max(n - 2, 1) / sxx) * np.sqrt(n / neff))
            if sxx > 0
            else np.inf
        )
        out["trend"] = {"slope_per_h": slope, "z": float(slope / se) if se > 0 else 0.0}
    if sigma is not None:
        s = np.asarray(sigma, dtype=float)[m]
        out["normalized_mse"] = float(np.mean((rr / s) ** 2))
    lag = min(max_lag, n // 4)
    acf = _acf(rr, lag)
    k = np.arange(1, lag + 1)
    q = float(n * (n + 2) * np.sum(acf[1:] ** 2 / (n - k)))
    out["acf"] = {"lags": k.tolist(), "values": acf[1:].tolist(), "rho1": float(acf[1])}
    out["ljung_box"] = {"q": q, "lags": int(lag), "p": float(stats.chi2.sf(q, lag))}
    # spectrum on the contiguous filled series (gaps: linear interpolation)
    full = np.interp(t, tt, rr)[m.argmax() : len(t) - m[::-1].argmax()]
    nper = int(min(256, full.size))
    f, p = signal.welch(full - full.mean(), fs=1.0 / dt, nperseg=nper)
    good = f > 0
    slope_psd = (
        float(np.polyfit(np.log(f[good]), np.log(p[good] + 1e-30), 1)[0]) if good.sum() > 3 else 0.0
    )
    low = f < 1.0 / 300.0
    out["spectrum"] = {
        "frequency_hz": f.tolist(),
        "psd": p.tolist(),
        "loglog_slope": slope_psd,
        "low_frequency_share": float(p[low].sum() / p.sum()) if p.sum() > 0 else 0.0,
    }
    # cross-correlation with the feeder flows and screw speeds
    xc: dict[str, Any] = {}
    if inputs is not None:
        nl = int(max_xcorr_lag_s / dt)
        rc = np.where(m, r - rr.mean(), 0.0)
        series = dict(inputs.flows_kg_h)
        series.update({f"{k}:screw_speed": v for k, v in inputs.screw_speed_rpm.items()})
        for name, u in series.items():
            res_xc = max_cross_correlation(rc, m, u, nl)
            if res_xc is not None:
                xc[name] = {"max_abs": abs(res_xc[0]), "value": res_xc[0], "lag_s": res_xc[1] * dt}
        # screw-speed changes are events too (the controller's or an operator's step)
        events = list(events)
        for name, u in inputs.screw_speed_rpm.items():
            events += rpm_change_events(t, u, name)
    out["cross_correlation"] = xc
    # event-locked averages
    ev_out: dict[str, Any] = {}
    kinds = sorted({str(e.get("kind")) for e in events})
    for kind in kinds:
        sel = np.zeros_like(m)
        for e in events:
            if e.get("kind") == kind:
                t0 = float(e["t_s"])
                sel |= (t >= t0) & (t < t0 + window_s)
        sel &= m
        if sel.sum() >= 5:
            v = r[sel]
            ne = n_effective(v)
            z = float(v.mean() / (sd / np.sqrt(ne))) if sd > 0 else 0.0
            ev_out[kind] = {
                "n": int(sel.sum()),
                "mean": float(v.mean()),
                "rms": float(np.sqrt(np.mean(v**2))),
                "z": z,
            }
    out["events"] = ev_out
    # pulse windows
    tails = []
    if inputs is not None:
        for p in inputs.tracers:
            wins = pulse_windows or {
                "front": (5.0, 25.0),
                "peak": (25.0, 45.0),
                "tail": (45.0, 150.0),
            }
            row: dict[str, Any] = {"t_s": p.t_s, "component": p.component}
            for key, (a, b) in wins.items():
                sel = m & (t >= p.t_s + a) & (t < p.t_s + b)
                row[key] = float(r[sel].mean()) if sel.any() else None
            tails.append(row)
    out["pulse_tails"] = tails
    return out


def _level_and_trend_gls(
    t: np.ndarray,
    r: np.ndarray,
    sigma: np.ndarray,
    m: np.ndarray,
    whitener: Callable[[np.ndarray], np.ndarray],
) -> tuple[dict[str, float], dict[str, float], float]:
    """Level b0 (% w/w) and trend b1 (% w/w per h) of a residual by generalised least squares
    under the noise: the innovations of r / sigma regressed on those of 1 / sigma and
    (t - mean t) / sigma, noise variance 1 (the noise's own), z = b / se. Returns (bias, trend,
    n_effective), n_effective = |W(1 / sigma)|^2 median(sigma)^2: how many independent samples
    the coloured noise leaves for estimating a level."""
    tc = (t - float(np.mean(t[m]))) / 3600.0
    e = whitener(np.where(m, r / sigma, 0.0))[m]
    X = np.column_stack(
        [whitener(np.where(m, 1.0 / sigma, 0.0))[m], whitener(np.where(m, tc / sigma, 0.0))[m]]
    )
    xtx = X.T @ X
    beta = np.linalg.solve(xtx, X.T @ e)
    se = np.sqrt(np.diag(np.linalg.inv(xtx)))
    bias = {"mean": float(beta[0]), "z": float(beta[0] / se[0])}
    trend = {"slope_per_h": float(beta[1]), "z": float(beta[1] / se[1])}
    return bias, trend, float(xtx[0, 0] * np.median(sigma[m]) ** 2)


def innovation_tests(
    e: np.ndarray,
    regressors: np.ndarray | None = None,
    lags: int = 20,
    alpha: float = 0.01,
) -> dict[str, Any]:
    """Are these innovations i.i.d. N(0, 1), as the noise model says? Four tests:

    - ``scale``: sum e^2 ~ chi2(n): the normalised MSE inside its sampling band (upper tail:
      more than the noise; ``mse_band`` is the band's upper end, mean e^2 at 1 - alpha / 4);
    - ``level_trend``: the explained sum of squares of e regressed on ``regressors`` (n x k,
      the innovations of a level and a trend) ~ chi2(k), with each coefficient's z;
    - ``ljung_box``: Q = n (n + 2) sum_{k<=lags} r_k^2 / (n - k) ~ chi2(lags) (Ljung & Box
      1978): structure left at short lags;
    - ``cumulative_periodogram``: the normalised cumulative periodogram against the uniform
      line, Kolmogorov-Smirnov (Bartlett 1955; Durbin 1969): a peak or a slope of the spectrum.

    ``consistent``: every p-value >= alpha / 4 (Bonferroni); ``failed``: the tests that reject.
    """
    e = np.asarray(e, dtype=float)
    n = e.size
    if n < 2 * lags + 4:
        raise ValueError(f"innovations must hold >= {2 * lags + 4} samples, got {n}")
    level = alpha / 4.0
    out: dict[str, Any] = {"n": int(n), "alpha": alpha, "mse": float(e @ e / n)}
    out["mse_band"] = float(stats.chi2.ppf(1.0 - level, n) / n)
    p = {"scale": float(stats.chi2.sf(e @ e, n))}
    if regressors is not None:
        X = np.asarray(regressors, dtype=float)
        beta, *_ = np.linalg.lstsq(X, e, rcond=None)
        fitted = X @ beta
        se = np.sqrt(np.diag(np.linalg.pinv(X.T @ X)))
        p["level_trend"] = float(stats.chi2.sf(fitted @ fitted, X.shape[1]))
        out["level_trend_z"] = [float(b / s) if s > 0 else 0.0 for b, s in zip(beta, se)]
    acf = _acf(e, lags)
    k = np.arange(1, lags + 1)
    q = float(n * (n + 2) * np.sum(acf[1:] ** 2 / (n - k)))
    p["ljung_box"] = float(stats.chi2.sf(q, lags))
    out["ljung_box_q"] = q
    per = np.abs(np.fft.rfft(e - e.mean())[1 : (n - 1) // 2 + 1]) ** 2
    cum = np.cumsum(per)[:-1] / per.sum()
    ks = stats.kstest(cum, "uniform")
    p["cumulative_periodogram"] = float(ks.pvalue)
    out["cumulative_periodogram_d"] = float(ks.statistic)
    out["p"] = p
    out["p_min"] = float(min(p.values()))
    out["failed"] = sorted(name for name, v in p.items() if v < level)
    out["consistent"] = not out["failed"]
    return out


def _moments(t: np.ndarray, y: np.ndarray) -> dict[str, float | None]:
    w = np.asarray(y, dtype=float)  # not clipped: zero-mean noise averages out of the moments
    a = float(np.sum(w))
    if a <= 0:
        return {"area": 0.0, "mean_s": None, "sd_s": None, "peak": float(np.max(y, initial=0.0))}
    m = float(np.sum(w * t) / a)
    sd = float(np.sqrt(max(np.sum(w * (t - m) ** 2) / a, 0.0)))
    return {"area": a, "mean_s": m, "sd_s": sd, "peak": float(np.max(y))}


def pulse_responses(
    t_s: np.ndarray,
    measured: np.ndarray,
    predicted: np.ndarray,
    inputs: LineInputs,
    window_s: float = 150.0,
    baseline_s: float = 30.0,
    backgrounds: Sequence[np.ndarray] | None = None,
) -> list[dict[str, Any]]:
    """Measured vs predicted response to every tracer pulse (moments of seed Eqs. 3-4).

    For a pulse at t_p the response is the signal over [t_p, t_p + window_s) minus its
    baseline (mean over [t_p - baseline_s, t_p)); area (% w/w s), mean time after the pulse
    and standard deviation (first and second moments of the response, as E(t) = C / int C),
    and peak height, for the measurement and the prediction, with their
    differences. With ``backgrounds`` (one array per pulse: the prediction of the same model
    without that pulse) the response is signal - background instead, which removes flow dips
    and refills overlapping the pulse. Pulses whose window leaves the record are skipped.
    """
    t = np.asarray(t_s, dtype=float)
    y = np.asarray(measured, dtype=float)
    p = np.asarray(predicted, dtype=float)
    out = []
    for i, pulse in enumerate(inputs.tracers):
        t0 = pulse.t_s
        win = (t >= t0) & (t < t0 + window_s) & np.isfinite(y)
        base = (t >= t0 - baseline_s) & (t < t0) & np.isfinite(y)
        if t0 + window_s > t[-1] or win.sum() < 10 or base.sum() < 3:
            continue
        tt = t[win] - t0
        dt = float(t[1] - t[0])
        if backgrounds is not None:
            bg = np.asarray(backgrounds[i], dtype=float)[win]
            mm = _moments(tt, y[win] - bg)
            pm = _moments(tt, p[win] - bg)
        else:
            mm = _moments(tt, y[win] - float(np.mean(y[base])))
            pm = _moments(tt, p[win] - float(np.mean(p[base])))
        mm["area"] *= dt
        pm["area"] *= dt
        diff = {
            k: (mm[k] - pm[k]) if mm[k] is not None and pm[k] is not None else None
            for k in ("area", "mean_s", "sd_s", "peak")
        }
        out.append(
            {
                "t_s": t0,
                "mass_kg": pulse.mass_kg,
                "component": pulse.component,
                "measured": mm,
                "predicted": pm,
                "measured_minus_predicted": diff,
            }
        )
    return out
