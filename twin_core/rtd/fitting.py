"""Nonlinear least-squares fits of RTD models with standard errors, confidence intervals and
information criteria (lmfit-like reporting).

The model y(t) = A E(t; theta) is fitted by ``scipy.optimize.least_squares`` (trust-region
reflective, bounds). ``scale="fixed"`` fixes A = 1 (fit of a normalized E(t), as the seed);
``scale="free"`` fits A too (fit of a concentration profile, or of an E(t) whose
normalization is itself noisy). Covariance = s^2 (J^T J)^-1, s^2 = RSS / (n - p);
confidence intervals est +/- t_{1-alpha/2, n-p} SE (Bates & Watts 1988, ch. 2);
AIC = n ln(RSS/n) + 2p, BIC = n ln(RSS/n) + p ln n, AICc = AIC + 2p(p+1)/(n-p-1)
(Burnham & Anderson 2002).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats
from scipy.optimize import least_squares

from twin_core.rtd.models import ModelSpec, get_model

__all__ = ["FitResult", "fit", "RTDFit", "compare_models", "initial_guess"]


@dataclass
class FitResult:
    """Estimates, standard errors, confidence intervals and goodness of fit."""

    model: str
    names: tuple[str, ...]
    params: dict[str, float]
    stderr: dict[str, float]
    ci: dict[str, tuple[float, float]]
    cov: NDArray[np.float64]
    rss: float
    n: int
    aic: float
    bic: float
    aicc: float
    success: bool
    message: str
    fitted: NDArray[np.float64] = field(repr=False)
    alpha: float = 0.05

    @property
    def k(self) -> int:
        return len(self.names)

    def as_dict(self) -> dict:
        return {
            "model": self.model,
            "params": self.params,
            "stderr": self.stderr,
            "ci": {k: list(v) for k, v in self.ci.items()},
            "confidence": 1 - self.alpha,
            "rss": self.rss,
            "n": self.n,
            "aic": self.aic,
            "bic": self.bic,
            "aicc": self.aicc,
            "success": self.success,
        }

    def report(self) -> str:
        lines = [f"[[Model]] {self.model}  n={self.n}  AIC={self.aic:.2f}  BIC={self.bic:.2f}"]
        for k in self.names:
            lo, hi = self.ci[k]
            lines.append(
                f"  {k:>10} = {self.params[k]:.5g} +/- {self.stderr[k]:.3g}"
                f"  [{lo:.5g}, {hi:.5g}] ({100 * (1 - self.alpha):.0f} % CI)"
            )
        return "\n".join(lines)


def initial_guess(spec: ModelSpec, t: NDArray, y: NDArray) -> list[NDArray]:
    """Initial parameter vectors (one or more starts) from the profile's moments (clipped at
    zero) and its onset."""
    yc = np.clip(y, 0, None)
    a = np.trapezoid(yc, t)
    if not a > 0:
        raise ValueError(f"profile area must be > 0 for an initial guess, got {a!r}")
    e = yc / a
    mean = float(np.trapezoid(t * e, t))
    std = float(np.sqrt(max(np.trapezoid((t - mean) ** 2 * e, t), 1e-12)))
    onset = float(t[np.argmax(yc > 0.05 * yc.max())])
    g = spec.guess(onset, mean, std)
    starts = g if isinstance(g, list) else [g]
    return [np.array(x, dtype=float) for x in starts]


def fit(
    t: ArrayLike,
    y: ArrayLike,
    model: str | ModelSpec = "ad_open",
    scale: str = "fixed",
    p0: ArrayLike | None = None,
    bounds: tuple[ArrayLike, ArrayLike] | None = None,
    sigma: ArrayLike | str | None = None,
    alpha: float = 0.05,
) -> FitResult:
    """Fit ``model`` (name or ModelSpec) to (t, y); see the module docstring.

    ``sigma``: per-point standard deviations for weighted least squares (optional), or
    ``"auto"``: two-stage feasible weighted least squares. An unweighted fit gives y_hat, the
    variance model Var(r) = a + b y_hat^2 is regressed on the squared residuals (non-negative
    least squares), and the fit is repeated with sigma = sqrt(a + b y_hat^2) (Carroll & Ruppert
    1988, "Transformation and Weighting in Regression", ch. 3). With signal-proportional noise
    this restores the CI coverage (from ~75 % to ~90 % for 8 % proportional noise).
    """
    if isinstance(sigma, str):
        if sigma != "auto":
            raise ValueError(f"sigma must be an array, None or 'auto', got {sigma!r}")
        from scipy.optimize import nnls

        first = fit(t, y, model, scale, p0, bounds, None, alpha)
        yy = np.asarray(y, dtype=float)
        res = yy - first.fitted
        (a, b), _ = nnls(np.column_stack([np.ones_like(yy), first.fitted**2]), res**2)
        a = max(a, 1e-3 * float(np.var(res)), 1e-300)
        x0 = [first.params[k] for k in first.names]
        return fit(t, y, model, scale, x0, bounds, np.sqrt(a + b * first.fitted**2), alpha)
    spec = model if isinstance(model, ModelSpec) else get_model(model)
    tt = np.asarray(t, dtype=float)
    yy = np.asarray(y, dtype=float)
    if tt.shape != yy.shape or tt.ndim != 1:
        raise ValueError(f"t and y must be 1-D of equal shape, got {tt.shape} and {yy.shape}")
    if not (np.all(np.isfinite(tt)) and np.all(np.isfinite(yy))):
        raise ValueError("t and y must be finite, got NaN or inf")
    if scale not in ("fixed", "free"):
        raise ValueError(f"scale must be 'fixed' or 'free', got {scale!r}")
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha!r}")
    names = spec.params + (("scale",) if scale == "free" else ())
    p = len(names)
    if tt.size <= p + 1:
        raise ValueError(f"need more than {p + 1} points to fit {p} parameters, got {tt.size}")
    if sigma is None:
        w = np.ones_like(yy)
    else:
        sg = np.asarray(sigma, dtype=float)
        if sg.shape != yy.shape or not np.all(np.isfinite(sg)) or np.any(sg <= 0):
            raise ValueError("sigma must be positive, finite and shaped like y")
        w = 1.0 / sg
    lo = np.array(spec.lower, float)
    hi = np.array(spec.upper, float)
    if bounds is not None:
        lo, hi = np.asarray(bounds[0], float), np.asarray(bounds[1], float)
    if p0 is None:
        starts = initial_guess(spec, tt, yy)
        a0 = float(np.trapezoid(np.clip(yy, 0, None), tt))
    else:
        starts = [np.asarray(p0, dtype=float)[: len(spec.params)]]
        a0 = float(np.asarray(p0, float)[-1]) if scale == "free" and len(p0) == p else 1.0
    if scale == "free":
        starts = [np.append(x, a0) for x in starts]
        lo = np.append(lo[: len(spec.params)], 0.0)
        hi = np.append(hi[: len(spec.params)], np.inf)
    if lo.size != p or hi.size != p or any(x.size != p for x in starts):
        raise ValueError(f"p0 and bounds must have {p} entries for {names}")
    lo_in = lo + 1e-9 * np.maximum(1, np.abs(np.where(np.isfinite(lo), lo, 0.0)))
    hi_in = hi - 1e-9 * np.maximum(1, np.abs(np.where(np.isfinite(hi), hi, 0.0)))

    def resid(x: NDArray) -> NDArray:
        if scale == "free":
            return w * (x[-1] * spec.func(tt, *x[:-1]) - yy)
        return w * (spec.func(tt, *x) - yy)

    def jac(x: NDArray) -> NDArray:
        if scale == "free":
            j = spec.jac(tt, *x[:-1])  # type: ignore[misc]
            return w[:, None] * np.column_stack([x[-1] * j, spec.func(tt, *x[:-1])])
        return w[:, None] * spec.jac(tt, *x)  # type: ignore[misc]

    res = None
    for x0 in starts:
        r = least_squares(
            resid,
            np.clip(x0, lo_in, hi_in),
            jac=jac if spec.jac is not None else "2-point",
            bounds=(lo, hi),
            method="trf",
            x_scale="jac",
        )
        if res is None or r.cost < res.cost:
            res = r
    assert res is not None
    rss = float(np.sum(res.fun**2))
    n = tt.size
    dof = n - p
    s2 = rss / dof
    jac = res.jac
    try:
        cov = np.linalg.pinv(jac.T @ jac) * s2
    except np.linalg.LinAlgError:
        cov = np.full((p, p), np.nan)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    tq = stats.t.ppf(1 - alpha / 2, dof)
    llf = n * np.log(max(rss, 1e-300) / n)
    aic = float(llf + 2 * p)
    bic = float(llf + p * np.log(n))
    aicc = float(aic + 2 * p * (p + 1) / max(n - p - 1, 1))
    fitted = resid(res.x) / w + yy
    return FitResult(
        model=spec.name,
        names=names,
        params={k: float(v) for k, v in zip(names, res.x)},
        stderr={k: float(v) for k, v in zip(names, se)},
        ci={k: (float(v - tq * s), float(v + tq * s)) for k, v, s in zip(names, res.x, se)},
        cov=cov,
        rss=rss,
        n=n,
        aic=aic,
        bic=bic,
        aicc=aicc,
        success=bool(res.success),
        message=str(res.message),
        fitted=fitted,
        alpha=alpha,
    )


class RTDFit:
    """scikit-learn style wrapper: ``RTDFit("ad_open").fit(t, y)`` then ``params_``,
    ``stderr_``, ``ci_``, ``aic_``, ``bic_``, ``result_`` and ``predict(t)``."""

    def __init__(self, model: str = "ad_open", scale: str = "fixed", alpha: float = 0.05):
        self.model = model
        self.scale = scale
        self.alpha = alpha

    def fit(self, t: ArrayLike, y: ArrayLike, sigma: ArrayLike | None = None) -> RTDFit:
        r = fit(t, y, self.model, scale=self.scale, sigma=sigma, alpha=self.alpha)
        self.result_ = r
        self.params_ = r.params
        self.stderr_ = r.stderr
        self.ci_ = r.ci
        self.aic_ = r.aic
        self.bic_ = r.bic
        return self

    def predict(self, t: ArrayLike) -> NDArray[np.float64]:
        spec = get_model(self.model)
        theta = [self.params_[k] for k in spec.params]
        return self.params_.get("scale", 1.0) * spec.func(np.asarray(t, float), *theta)


def compare_models(
    t: ArrayLike,
    y: ArrayLike,
    models: list[str] | None = None,
    scale: str = "fixed",
    sigma: ArrayLike | str | None = None,
) -> list[FitResult]:
    """Fit several models and return them sorted by AIC (best first); failures are skipped.
    With ``sigma="auto"`` each model gets its own variance model, so AICs compare weighted
    residuals of different weightings: rank unweighted fits when in doubt."""
    names = models or ["ad_open", "ad_closed", "tis", "cstr_pfr", "emg", "zusatz"]
    out = []
    for m in names:
        try:
            out.append(fit(t, y, m, scale=scale, sigma=sigma))
        except (ValueError, np.linalg.LinAlgError, FloatingPointError):
            continue
    return sorted(out, key=lambda r: r.aic)
