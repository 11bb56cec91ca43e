"""Parameters that change with the operating point or with time.

The model's parameters (the declared blender parameters and those of the adopted effects) are
refitted on windows of the training data grouped by a covariate x: the throughput (sum of the
reported feeder flows), each feeder's screw speed, or the time. Flows and speeds are taken as
the blender sees them, (E * x)(t) with the model's E(t) (the material at the outlet at t went
through at the throughput of the last residence time).

Linearised refit (one Gauss-Newton step from the model, Jacobian J_p = d prediction / d theta_p
by forward differences): in window g the level shift of parameter p is

    delta_g = sum_g w J_p r / sum_g w J_p^2,   w = 1 / sigma^2,

a linear estimate delta = A'r whose covariance under the declared coloured noise is
V = A'CA (``NoiseWhitener.gram``: the 1/f part correlates the windows). The dependence on x is the
generalised least-squares line through the window estimates at their information-weighted
covariate means, delta_g = a + b (x_g - x_ref): slope b with its standard error
sqrt([(Z'V^-1 Z)^-1]_bb); "constant" is tested by z = b / se(b) (Bonferroni over parameters x
covariates) and, as evidence, by the Wald statistic of equal levels
(D delta)'(D V D')^-1 (D delta) ~ chi^2(G - 1), D the successive differences (the F-test of
window estimates with their standard errors, with the covariance of the windows).

For the search-significant pairs, strongest first (at most ``max_laws``, the held-out level
split among them), one secant step refines the window estimates (Jacobian from the model
evaluated at each window's estimate); the law theta(x) = theta_ref + b (x - x_ref) (clipped to
the parameter's bounds) predicts the outlet at the operating point of every sample (model
evaluated at a few levels of theta, interpolated per sample). Held-out evidence compares it with
the same parameter refitted as a constant on the training window.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from twin_core.closeloop.data import RunData
from twin_core.closeloop.structure_base import (
    HeldoutEvidence,
    ResidualContext,
    StructureFinding,
    StructureOptions,
    heldout_evidence,
    interval,
)
from twin_core.plant.model import LineModel, rtd_kernel
from twin_core.rtd.convolution import convolve


@dataclass(frozen=True)
class TunableParam:
    """A parameter of a line model: a declared blender parameter (``effect_index`` None) or a
    parameter of the model's ``effect_index``-th effect."""

    key: str
    name: str
    value: float
    lower: float
    upper: float
    unit: str
    effect_index: int | None = None

    def model_with(self, model: LineModel, value: float) -> LineModel:
        """The model with this parameter set to ``value`` (clipped to its bounds)."""
        v = float(np.clip(value, self.lower, self.upper))
        if self.effect_index is None:
            params = dict(model.config.blender.params)
            params[self.name] = v
            blender = model.config.blender.model_copy(update={"params": params})
            return LineModel(
                model.config.model_copy(update={"blender": blender}), list(model.effects)
            )
        effects = list(model.effects)
        e = effects[self.effect_index]
        vec = e.vector()
        vec[[p.name for p in e.params].index(self.name)] = v
        effects[self.effect_index] = e.with_vector(vec)
        return LineModel(model.config, effects)

    def step(self) -> float:
        """Forward-difference step: 2 % of the value (blender), 1 % of the range (effects)."""
        if self.effect_index is None:
            return 0.02 * abs(self.value) if self.value != 0 else 0.1
        h = 0.01 * (self.upper - self.lower)
        return h if self.value + h <= self.upper else -h


def _blender_unit(name: str) -> str:
    return "s" if name.startswith(("tau", "mu", "sigma")) else "1"


def tunable_params(model: LineModel) -> list[TunableParam]:
    """The declared blender parameters (bounds [small, 20 x value]) and every parameter of
    the model's effects (their declared bounds)."""
    out = []
    for name, v in model.config.blender.params.items():
        lo = 0.0 if name == "tau_d" or v == 0 else 0.02 * abs(v)
        out.append(
            TunableParam(
                f"blender.{name}", name, float(v), lo, 20.0 * abs(v) + 1.0, _blender_unit(name)
            )
        )
    for i, e in enumerate(model.effects):
        for p in e.params:
            out.append(
                TunableParam(
                    f"{e.label()}.{p.name}", p.name, e.values[p.name], p.lower, p.upper, p.unit, i
                )
            )
    return out


def find_param(model: LineModel, key: str) -> TunableParam:
    """The tunable parameter ``key`` of ``model`` (ValueError if it has none)."""
    for p in tunable_params(model):
        if p.key == key:
            return p
    raise ValueError(f"model has no parameter {key!r}")


def blender_weighted(model: LineModel, t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(E * x)(t) with the model's E(t), x extended to the past by its first value (the
    covariate the material leaving at t has seen)."""
    tg = t - t[0]
    e = rtd_kernel(model.config.blender, tg, model.effects)
    dt = float(t[1] - t[0])
    survival = np.clip(1.0 - dt * np.cumsum(e), 0.0, None)
    return convolve(tg, x, e) + float(x[0]) * survival


def covariates(
    data: RunData, model: LineModel, train: np.ndarray, opt: StructureOptions
) -> dict[str, tuple[np.ndarray, str]]:
    """Covariates varying enough on the training window: ``throughput`` (kg/h),
    ``<feeder>:screw_speed`` (rpm), both as the blender sees them, and ``time`` (h)."""
    t = data.t_s
    inp = data.inputs
    raw: dict[str, tuple[np.ndarray, str]] = {
        "throughput": (sum(np.asarray(f, float) for f in inp.flows_kg_h.values()), "kg/h")
    }
    for k, v in inp.screw_speed_rpm.items():
        raw[f"{k}:screw_speed"] = (np.asarray(v, float), "rpm")
    out: dict[str, tuple[np.ndarray, str]] = {}
    for name, (x, unit) in raw.items():
        if not np.all(np.isfinite(x)):
            continue
        xw = blender_weighted(model, t, x)
        q05, q50, q95 = np.percentile(xw[train], [5, 50, 95])
        if q95 - q05 >= opt.min_rel_spread * abs(q50) and q95 > q05:
            out[name] = (xw, unit)
    span = float(np.ptp(t[train]))
    if span >= opt.min_time_span_s:
        out["time"] = ((t - t[0]) / 3600.0, "h")
    return out


def window_groups(x: np.ndarray, train: np.ndarray, groups: int, by_time: bool) -> np.ndarray:
    """Window index per sample (-1 outside ``train``): equal-count consecutive windows in time,
    or covariate quantile windows."""
    g = np.full(x.size, -1, dtype=int)
    idx = np.flatnonzero(train)
    if by_time:
        g[idx] = np.minimum((np.arange(idx.size) * groups) // idx.size, groups - 1)
        return g
    edges = np.unique(np.percentile(x[idx], np.linspace(0, 100, groups + 1))[1:-1])
    g[idx] = np.searchsorted(edges, x[idx], side="right")
    return g


@dataclass
class WindowFit:
    """Window estimates of one parameter against one covariate and their line."""

    param: TunableParam
    covariate: str
    unit: str
    x_mean: np.ndarray
    levels: np.ndarray
    cov: np.ndarray
    x_ref: float
    a: float
    b: float
    se_a: float
    se_b: float
    wald: float
    wald_p: float
    lack_of_fit_p: float

    @property
    def z(self) -> float:
        return self.b / self.se_b if self.se_b > 0 else 0.0

    @property
    def p_value(self) -> float:
        return float(2 * stats.norm.sf(abs(self.z)))


def fit_windows(
    ctx: ResidualContext,
    param: TunableParam,
    jac: np.ndarray,
    r: np.ndarray,
    x: np.ndarray,
    g: np.ndarray,
    covariate: str,
    unit: str,
) -> WindowFit | None:
    """Window levels delta_g, their covariance A'CA and the GLS line (see module); None when
    fewer than 3 windows carry information on the parameter. ``jac`` may be one column or a
    per-sample column (secant refinement)."""
    w = ctx.weight
    ids = [k for k in np.unique(g) if k >= 0]
    info = np.array([float(np.sum((w * jac**2)[g == k])) for k in ids])
    keep = info > 1e-6 * max(info.max(initial=0.0), 1e-300)
    ids = [k for k, ok in zip(ids, keep) if ok]
    info = info[keep]
    if len(ids) < 3:
        return None
    a_cols = np.column_stack([np.where(g == k, w * jac, 0.0) / s for k, s in zip(ids, info)])
    levels = a_cols.T @ r
    v = ctx.whiten.gram(a_cols)
    x_mean = np.array([float(np.sum((w * jac**2 * x)[g == k])) / s for k, s in zip(ids, info)])
    x_ref = float(np.sum(info * x_mean) / np.sum(info))
    z = np.column_stack([np.ones(len(ids)), x_mean - x_ref])
    vinv = np.linalg.pinv(v)
    zc = np.linalg.pinv(z.T @ vinv @ z)
    coef = zc @ z.T @ vinv @ levels
    res = levels - z @ coef
    lof = float(res @ vinv @ res)
    d = np.diff(np.eye(len(ids)), axis=0)
    dl = d @ levels
    wald = float(dl @ np.linalg.pinv(d @ v @ d.T) @ dl)
    k = len(ids)
    return WindowFit(
        param,
        covariate,
        unit,
        x_mean,
        levels,
        v,
        x_ref,
        float(coef[0]),
        float(coef[1]),
        float(np.sqrt(max(zc[0, 0], 0.0))),
        float(np.sqrt(max(zc[1, 1], 0.0))),
        wald,
        float(stats.chi2.sf(wald, k - 1)),
        float(stats.chi2.sf(lof, k - 2)) if k > 2 else 1.0,
    )


def law_prediction(
    model: LineModel,
    data: RunData,
    param: TunableParam,
    theta: np.ndarray,
    n_levels: int = 5,
) -> np.ndarray:
    """Prediction with the parameter varying per sample as ``theta``: the model evaluated at
    ``n_levels`` values spanning theta, linearly interpolated per sample."""
    lo, hi = float(theta.min()), float(theta.max())
    if hi - lo <= 1e-9 * max(abs(hi), 1.0):
        return param.model_with(model, lo).predict(data.inputs)
    levels = np.linspace(lo, hi, n_levels)
    preds = np.stack([param.model_with(model, v).predict(data.inputs) for v in levels])
    i = np.clip(np.searchsorted(levels, theta) - 1, 0, n_levels - 2)
    f = (theta - levels[i]) / (levels[i + 1] - levels[i])
    cols = np.arange(theta.size)
    return (1 - f) * preds[i, cols] + f * preds[i + 1, cols]


@dataclass(frozen=True)
class LawPredictor:
    """theta(x) = theta_ref + slope (x - x_ref) of the parameter ``key`` against
    ``covariate``, clipped to its bounds; called as a finding's predictor it returns the
    change of the prediction it makes (law prediction - model prediction)."""

    key: str
    covariate: str
    theta_ref: float
    slope: float
    x_ref: float

    def theta_of(self, data: RunData, model: LineModel, param: TunableParam) -> np.ndarray:
        t = data.t_s
        if self.covariate == "time":
            x = (t - t[0]) / 3600.0
        elif self.covariate == "throughput":
            x = blender_weighted(model, t, sum(data.inputs.flows_kg_h.values()))
        else:
            feeder = self.covariate.split(":")[0]
            x = blender_weighted(model, t, data.inputs.screw_speed_rpm[feeder])
        return np.clip(self.theta_ref + self.slope * (x - self.x_ref), param.lower, param.upper)

    def __call__(self, data: RunData, model: LineModel) -> np.ndarray:
        param = find_param(model, self.key)
        theta = self.theta_of(data, model, param)
        return law_prediction(model, data, param, theta) - model.predict(data.inputs)


def _refine(
    ctx: ResidualContext,
    wf: WindowFit,
    g: np.ndarray,
    x: np.ndarray,
    jac: np.ndarray,
    r: np.ndarray,
) -> WindowFit:
    """One secant step: each window's Jacobian from the model at its estimate, then the window
    levels and the line again (``r``: the residual searched)."""
    p = wf.param
    ids = [k for k in np.unique(g) if k >= 0]
    lin = dict(zip(ids, wf.levels)) if len(ids) == len(wf.levels) else None
    if lin is None:
        return wf
    jac_s = np.array(jac, dtype=float)
    r_s = np.array(r, dtype=float)
    for k in ids:
        d = float(lin[k])
        if abs(d) < 1e-9 * max(abs(p.value), 1.0):
            continue
        sel = g == k
        pk = p.model_with(ctx.model, p.value + d).predict(ctx.data.inputs) - ctx.pred
        js = pk / d
        jac_s[sel] = js[sel]
        # residual about the window's estimate, expressed as a step from the model
        r_s[sel] = r[sel] - pk[sel] + d * js[sel]
    out = fit_windows(ctx, p, jac_s, r_s, x, g, wf.covariate, wf.unit)
    return out if out is not None else wf


def _describe(wf: WindowFit) -> str:
    p = wf.param
    unit_x = wf.unit
    what = "time" if wf.covariate == "time" else wf.covariate
    return (
        f"{p.key} changes by {wf.b:+.3g} {p.unit} per {unit_x} of {what} "
        f"({p.value + wf.a:.4g} {p.unit} at {wf.x_ref:.4g} {unit_x}; slope 95 % CI "
        f"{wf.b - 1.96 * wf.se_b:+.3g} .. {wf.b + 1.96 * wf.se_b:+.3g})"
    )


def find_parameter_dependence(
    ctx: ResidualContext, opt: StructureOptions, e0: np.ndarray
) -> list[StructureFinding]:
    """The strongest parameter x covariate dependence in the residual ``e0`` if significant
    on the training window and better than a constant refit on the held-out window."""
    model, data = ctx.model, ctx.data
    cov_x = covariates(data, model, ctx.train, opt)
    if not cov_x:
        return []
    params = []
    for p in tunable_params(model):
        h = p.step()
        jac = (p.model_with(model, p.value + h).predict(data.inputs) - ctx.pred) / h
        if np.any(jac[ctx.train] != 0):
            params.append((p, jac))
    fits: list[tuple[WindowFit, np.ndarray, np.ndarray]] = []
    r = np.where(ctx.finite, e0, 0.0)
    for name, (x, unit) in cov_x.items():
        g = window_groups(x, ctx.train, opt.groups, by_time=name == "time")
        for p, jac in params:
            wf = fit_windows(ctx, p, jac, r, x, g, name, unit)
            if wf is not None and wf.se_b > 0:
                fits.append((wf, g, jac))
    if not fits:
        return []
    n_tests = len(fits)
    fits.sort(key=lambda f: f[0].p_value)
    significant = [f for f in fits if f[0].p_value * n_tests < opt.search_alpha]
    for best, g, jac in significant[: opt.max_laws]:
        law = _heldout_law(ctx, opt, best, g, jac, cov_x[best.covariate][0], r)
        if law is not None:
            return [_law_finding(law, best, fits, n_tests, opt)]
    return []


@dataclass
class _Law:
    wf: WindowFit
    predictor: LawPredictor
    ev: HeldoutEvidence


def _heldout_law(
    ctx: ResidualContext,
    opt: StructureOptions,
    wf0: WindowFit,
    g: np.ndarray,
    jac: np.ndarray,
    x: np.ndarray,
    r: np.ndarray,
) -> _Law | None:
    """The refined law of one parameter x covariate pair if it beats a constant refit of the
    parameter on the held-out window (see module), else None."""
    model, data = ctx.model, ctx.data
    wf = _refine(ctx, wf0, g, x, jac, r)
    p = wf.param
    tr = ctx.train
    const = float(np.sum((ctx.weight * jac * r)[tr]) / np.sum((ctx.weight * jac**2)[tr]))
    p_const = p.model_with(model, p.value + const).predict(data.inputs)
    predictor = LawPredictor(p.key, wf.covariate, p.value + wf.a, wf.b, wf.x_ref)
    p_law = law_prediction(model, data, p, predictor.theta_of(data, model, p))
    ev = heldout_evidence(
        ctx,
        p_law - p_const,
        opt.heldout_level("parameter_dependence"),
        opt.min_improvement,
        e0=np.where(ctx.finite, r - (p_const - ctx.pred), 0.0),
    )
    return _Law(wf, predictor, ev) if ev.passed else None


def _law_finding(
    law: _Law,
    best: WindowFit,
    fits: list[tuple[WindowFit, np.ndarray, np.ndarray]],
    n_tests: int,
    opt: StructureOptions,
) -> StructureFinding:
    """The finding of an accepted law (``fits``: all pairs tried, strongest first)."""
    wf, ev, p = law.wf, law.ev, law.wf.param
    p_search = min(1.0, best.p_value * n_tests)
    se_levels = np.sqrt(np.clip(np.diag(wf.cov), 0.0, None))
    estimates = {
        f"{p.key}:slope_per_{wf.unit}": interval(wf.b, wf.se_b),
        f"{p.key}@{wf.covariate}={wf.x_ref:.4g}": interval(
            p.value + wf.a, wf.se_a, p.lower, p.upper
        ),
    }
    for xm, lv, se in zip(wf.x_mean, wf.levels, se_levels):
        estimates[f"{p.key}@{wf.covariate}={xm:.4g}"] = interval(p.value + lv, se, p.lower, p.upper)
    alternatives = [
        f"{f.param.key} vs {f.covariate} (z {f.z:+.1f})"
        for f, _, _ in fits
        if f is not best and f.p_value * n_tests < opt.search_alpha
    ][:4]
    evidence = {
        "slope_z": wf.z,
        "search_p_value": p_search,
        "n_tests": float(n_tests),
        "constant_chi2": wf.wald,
        "constant_dof": float(len(wf.levels) - 1),
        "constant_p_value": wf.wald_p,
        "lack_of_fit_p_value": wf.lack_of_fit_p,
        "n_windows": float(len(wf.levels)),
        **ev.as_dict(),
    }
    summary = (
        f"{_describe(wf)}; constant rejected (p {max(wf.wald_p, 1e-300):.2g}); held-out error "
        f"{-100 * ev.rel_improvement:+.1f} % against a constant refit (empirical)"
    )
    return StructureFinding(
        kind="parameter_dependence",
        summary=summary,
        evidence=evidence,
        estimates=estimates,
        alternatives=alternatives,
        curves={
            "param": p.key,
            "unit": p.unit,
            "covariate": wf.covariate,
            "covariate_unit": wf.unit,
            "x": wf.x_mean,
            "levels": p.value + wf.levels,
            "se": se_levels,
            "theta_ref": p.value + wf.a,
            "slope": wf.b,
            "x_ref": wf.x_ref,
            "declared": p.value,
        },
        predictor=law.predictor,
    )


__all__ = [
    "LawPredictor",
    "TunableParam",
    "WindowFit",
    "blender_weighted",
    "covariates",
    "find_parameter_dependence",
    "find_param",
    "fit_windows",
    "law_prediction",
    "tunable_params",
    "window_groups",
]
