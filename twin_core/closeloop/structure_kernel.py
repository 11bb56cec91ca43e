"""A non-parametric correction of the blender response: a regularised non-negative kernel.

The model's outlet concentration of the measured component c is
c(t) = 100 (h * m_c)(t) / (h * m_tot)(t) for a kernel h = E(t) of unit mass (m_c, m_tot the
inlet mass flows of c and of all components, tracer pulses and the model's feeder effects
included; ``twin_core.plant.model``). Writing a kernel of mass g as g times a unit kernel,
c(h) = g 100 (h * m_c) / (h * m_tot), whose derivative at the model's E is

    dc(t) / dh_j = dt c0(t) + dt [100 m_c(t - j dt) - c0(t) m_tot(t - j dt)] / D0(t),

D0 = (E * m_tot) (history: the first flows extended to the past). With constant total flow this
is dt c_in(t - j dt), the kernel from the inlet concentration to the outlet. The correction
h = E + Delta, Delta = sum_k (u_k - E(t_k)) phi_k a combination of hat functions on knots t_k
every ``knot_s`` over [0, L), is fitted to the residual on the training window through the
model's (linear) sensor map S (lag, gain; additive terms cancel):

    min_u  sum_train w (r - S[X (u - e)] - b)^2 + lambda ||D2 (u - e)||^2 + lambda eps ||u - e||^2
    subject to u >= 0 (the kernel is non-negative at the knots) and m'u = m'e (its mass kept),

X = the derivative above times the basis, e = E at the knots, m the masses of the hats, b a
free level (profiled out), D2 second differences (smoothness; lambda -> infinity returns the
declared E). The mass is held at the declared one: with the composition moving by some 10 %,
a gain of the kernel is a near-constant offset g c0 that the free level b (the probe's offset,
the slow 1/f noise) takes as well, and a fitted gain would shift the held-out prediction by a
level the data never fixed; a component lost or held up in the unit is a product-side
candidate of the library, not a shape. The result is a non-negative least-squares problem in u
(Lawson & Hanson 1974) on the Cholesky factor of the penalised Gram matrix (the mass condition
as a stiff quadratic penalty). lambda is chosen by K-fold cross-validation on contiguous blocks of the
training window (Bergmeir & Benitez 2012) among a log grid and infinity; a correction exists
only if a finite lambda predicts the left-out blocks better than the declared E.

The shape is compared with the declared E(t) on [0, L): mean residence time, standard
deviation (``twin_core.rtd.profiles.moments``) and the tail (the share of the mass beyond the
declared E's 99 % time). Uncertainty: moving-block bootstrap (Kunsch 1989) of the training
residual, blocks of ``bootstrap_block_s``, the fit repeated at the chosen lambda; 95 %
percentile intervals. The correction for prediction is S[X (u - e)] on any record.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass
from functools import reduce

import numpy as np
from scipy import linalg
from scipy.optimize import nnls

from twin_core.closeloop.data import RunData
from twin_core.closeloop.structure_base import (
    ResidualContext,
    StructureFinding,
    StructureOptions,
    heldout_evidence,
)
from twin_core.plant.model import (
    LineInputs,
    LineModel,
    inlet_component_flows,
    rtd_kernel,
    sensor_signal,
)
from twin_core.rtd.convolution import convolve
from twin_core.rtd.profiles import moments

#: relative ridge added to the smoothness penalty (makes lambda -> infinity return E)
RIDGE = 1e-3
#: weight of the mass constraint relative to the scale of the penalised Gram matrix
MASS_STIFFNESS = 1e4


def hat_basis(n_knots: int, step: int) -> np.ndarray:
    """Hat (piecewise-linear) functions on knots 0, step, ..., (n_knots - 1) step over the lags
    0 .. n_knots step - 1 (lags n_knots x K; the first hat is the causal half)."""
    lags = np.arange(n_knots * step)
    knots = np.arange(n_knots) * step
    return np.clip(1.0 - np.abs(lags[:, None] - knots[None, :]) / step, 0.0, None)


def hat_convolutions(m: np.ndarray, m0: float, n_knots: int, step: int) -> np.ndarray:
    """sum_j phi_k(j) m(t - j) for every hat phi_k of :func:`hat_basis` (n x K), with m
    extended to the past by ``m0``: one convolution with the triangle, shifted per knot
    (phi_k(j) = tri(j - k step)), and one with the causal half-triangle for k = 0."""
    n = m.size
    pad = n_knots * step + step
    mp = np.concatenate([np.full(pad, m0), m])
    tri = 1.0 - np.abs(np.arange(2 * step - 1) - (step - 1)) / step
    full = np.convolve(mp, tri)
    half = np.convolve(mp, tri[step - 1 :])
    out = np.empty((n, n_knots))
    out[:, 0] = half[pad : pad + n]
    for k in range(1, n_knots):
        a = pad + step - 1 - k * step
        out[:, k] = full[a : a + n]
    return out


def kernel_length_s(model: LineModel, dt: float, kernel_s: float | None) -> float:
    """``kernel_s``, or 6 mean residence times of the model's E(t), within [120, 600] s."""
    if kernel_s is not None:
        return float(kernel_s)
    tk = np.arange(0.0, 3600.0, dt)
    mean = moments(tk, rtd_kernel(model.config.blender, tk, model.effects)).mean
    return float(np.clip(6.0 * mean, 120.0, 600.0))


@dataclass
class KernelDesign:
    """The linearised kernel model of one record: ``x`` (n x K) = S[dc/dh basis], ``e_knots``
    the model's E at the knots, ``e_lags`` its E on the lag grid, ``basis``, ``dt``."""

    x: np.ndarray
    e_knots: np.ndarray
    e_lags: np.ndarray
    basis: np.ndarray
    knots: np.ndarray
    dt: float

    @property
    def mass(self) -> np.ndarray:
        """Mass (integral) of every hat."""
        return self.basis.sum(axis=0) * self.dt


def _feed_only(inputs: LineInputs) -> LineInputs:
    return LineInputs(
        t_s=inputs.t_s,
        flows_kg_h=inputs.flows_kg_h,
        components=inputs.components,
        refilling=inputs.refilling,
    )


def kernel_design(model: LineModel, data: RunData, length_s: float, knot_s: float) -> KernelDesign:
    """Derivative of the predicted reading with respect to the kernel's knot values at the
    model's E (see module), on ``data.t_s``."""
    t = data.t_s
    dt = float(t[1] - t[0])
    n = t.size
    comp = model.config.sensor.component
    flows = inlet_component_flows(data.inputs, model.effects)
    hist = inlet_component_flows(_feed_only(data.inputs), model.effects)
    m_c = np.asarray(flows.get(comp, np.zeros(n)), dtype=float)
    m_tot = np.sum([np.asarray(v, dtype=float) for v in flows.values()], axis=0)
    m_c0 = float(np.atleast_1d(hist.get(comp, np.zeros(1)))[0])
    m_tot0 = float(sum(np.atleast_1d(v)[0] for v in hist.values()))
    step = max(1, int(round(knot_s / dt)))
    n_knots = max(3, int(round(length_s / dt / step)))
    basis = hat_basis(n_knots, step)
    knots = np.arange(n_knots) * step
    tg = t - t[0]
    e_full = rtd_kernel(model.config.blender, tg, model.effects)
    survival = np.clip(1.0 - dt * np.cumsum(e_full), 0.0, None)
    d0 = convolve(tg, m_tot, e_full) + m_tot0 * survival
    c0 = model.outlet(data.inputs).get(comp, np.zeros(n))
    conv_c = hat_convolutions(m_c, m_c0, n_knots, step)
    conv_t = hat_convolutions(m_tot, m_tot0, n_knots, step)
    mass = basis.sum(axis=0) * dt
    x = dt * (100.0 * conv_c - c0[:, None] * conv_t) / d0[:, None]
    x += c0[:, None] * mass[None, :]
    sensor_effects = [e for e in model.effects if e.stage == "sensor"]
    if sensor_effects:
        zero = sensor_signal(t, np.zeros(n), sensor_effects)
        x = np.column_stack(
            [sensor_signal(t, x[:, k], sensor_effects) - zero for k in range(x.shape[1])]
        )
    lag_t = np.arange(basis.shape[0]) * dt
    e_lags = rtd_kernel(model.config.blender, lag_t, model.effects)
    return KernelDesign(x, e_lags[knots], e_lags, basis, knots, dt)


@dataclass
class _Sums:
    """Weighted sums of a set of samples: S_w, S_wx, S_wr, S_wxx, S_wxr, S_wrr."""

    sw: float
    swx: np.ndarray
    swr: float
    swxx: np.ndarray
    swxr: np.ndarray
    swrr: float

    @classmethod
    def of(cls, x: np.ndarray, r: np.ndarray, w: np.ndarray) -> _Sums:
        wx = x * w[:, None]
        return cls(
            float(w.sum()),
            wx.sum(axis=0),
            float(w @ r),
            wx.T @ x,
            wx.T @ r,
            float(w @ r**2),
        )

    def __add__(self, o: _Sums) -> _Sums:
        return _Sums(
            self.sw + o.sw,
            self.swx + o.swx,
            self.swr + o.swr,
            self.swxx + o.swxx,
            self.swxr + o.swxr,
            self.swrr + o.swrr,
        )

    def __sub__(self, o: _Sums) -> _Sums:
        return _Sums(
            self.sw - o.sw,
            self.swx - o.swx,
            self.swr - o.swr,
            self.swxx - o.swxx,
            self.swxr - o.swxr,
            self.swrr - o.swrr,
        )

    def centred(self) -> tuple[np.ndarray, np.ndarray]:
        """Gram matrix and right-hand side with the free level b profiled out."""
        g = self.swxx - np.outer(self.swx, self.swx) / self.sw
        q = self.swxr - self.swx * self.swr / self.sw
        return g, q

    def level(self, u: np.ndarray) -> float:
        return (self.swr - self.swx @ u) / self.sw


def penalty(k: int) -> np.ndarray:
    """D2'D2 + RIDGE I (second differences of the knot values)."""
    d2 = np.diff(np.eye(k), 2, axis=0)
    return d2.T @ d2 + RIDGE * np.eye(k)


def solve_kernel(
    g: np.ndarray,
    q: np.ndarray,
    e: np.ndarray,
    lam: float,
    pen: np.ndarray,
    mass: np.ndarray,
) -> np.ndarray:
    """argmin_{u >= 0} u'Gu - 2q'u + lam (u - e)'P(u - e) with the kernel's mass held at the
    model's, mass'u = mass'e (a stiff quadratic penalty, ``MASS_STIFFNESS`` times G's scale):
    NNLS on the Cholesky factor R of the penalised Gram matrix, ||R u - R^-T rhs||^2."""
    if not math.isfinite(lam):
        return e.copy()
    k = g.shape[0]
    mu = MASS_STIFFNESS * (np.trace(g) + lam * np.trace(pen)) / k / float(mass @ mass)
    a = g + lam * pen + mu * np.outer(mass, mass)
    rhs = q + lam * pen @ e + mu * float(mass @ e) * mass
    try:
        r = linalg.cholesky(a, lower=False)
    except linalg.LinAlgError:
        r = linalg.cholesky(a + 1e-9 * np.trace(a) / k * np.eye(k), lower=False)
    z = linalg.solve_triangular(r, rhs, trans="T")
    u, _ = nnls(r, z, maxiter=10 * k)
    return u


def _block_ids(t: np.ndarray, mask: np.ndarray, block_s: float) -> np.ndarray:
    """Index of the contiguous block of ``block_s`` of every sample (-1 outside ``mask``)."""
    b = np.floor((t - t[0]) / block_s).astype(int)
    return np.where(mask, b, -1)


def choose_lambda(
    design: KernelDesign,
    r: np.ndarray,
    ctx: ResidualContext,
    opt: StructureOptions,
) -> tuple[float, dict[float, float], _Sums]:
    """Blocked K-fold cross-validation of lambda (grid and infinity). Returns (lambda,
    {lambda: CV weighted SSE}, sums of the whole training window)."""
    x, w = design.x, ctx.weight
    blocks = _block_ids(ctx.t, ctx.train, opt.cv_block_s)
    ids = [b for b in np.unique(blocks) if b >= 0]
    per_block = {b: _Sums.of(x[blocks == b], r[blocks == b], w[blocks == b]) for b in ids}
    total = reduce(operator.add, per_block.values()) if ids else _Sums.of(x[:0], r[:0], w[:0])
    if len(ids) < 2 or not total.sw > 0:
        # a window shorter than two CV blocks cannot choose lambda: no correction
        return math.inf, {}, total
    pen = penalty(x.shape[1])
    g_all, _ = total.centred()
    scale = float(np.trace(g_all) / np.trace(pen))
    grid = [scale * 10.0**p for p in np.linspace(-3.0, 3.0, opt.n_lambda)] + [math.inf]
    folds = {b: i % opt.cv_folds for i, b in enumerate(ids)}
    cv = {lam: 0.0 for lam in grid}
    for f in range(min(opt.cv_folds, len(ids))):
        held_ids = [b for b in ids if folds[b] == f]
        sel = np.isin(blocks, held_ids)
        fit = total - reduce(operator.add, (per_block[b] for b in held_ids))
        if not fit.sw > 0:  # every weighted training sample is in this fold
            continue
        g, q = fit.centred()
        for lam in grid:
            u = solve_kernel(g, q, design.e_knots, lam, pen, design.mass)
            res = r[sel] - x[sel] @ u - fit.level(u)
            cv[lam] += float(w[sel] @ res**2)
    best = min(grid, key=lambda lam: cv[lam])
    return best, cv, total


@dataclass
class KernelShape:
    """Mass, mean, standard deviation and tail mass (beyond ``t_tail_s``) of a kernel."""

    mass: float
    mean_s: float
    sd_s: float
    tail: float


def kernel_shape(lag_t: np.ndarray, h: np.ndarray, t_tail_s: float) -> KernelShape:
    """Shape statistics of a kernel on [0, L) (negative values clipped)."""
    hp = np.clip(h, 0.0, None)
    m = moments(lag_t, hp)
    tail = float(np.sum(hp[lag_t > t_tail_s]) / np.sum(hp)) if np.sum(hp) > 0 else 0.0
    return KernelShape(m.area, m.mean, math.sqrt(max(m.variance, 0.0)), tail)


def block_bootstrap(resid: np.ndarray, block: int, rng: np.random.Generator) -> np.ndarray:
    """A moving-block bootstrap replicate of ``resid`` (circular blocks of ``block``)."""
    n = resid.size
    starts = rng.integers(0, n, size=int(math.ceil(n / block)))
    idx = (starts[:, None] + np.arange(block)[None, :]).ravel()[:n] % n
    return resid[idx]


@dataclass(frozen=True)
class KernelPredictor:
    """The correction S[X (u - e)] of a kernel correction on any record (knot values
    ``delta_knots`` = u - e added to the model's E)."""

    delta_knots: tuple[float, ...]
    length_s: float
    knot_s: float

    def __call__(self, data: RunData, model: LineModel) -> np.ndarray:
        d = kernel_design(model, data, self.length_s, self.knot_s)
        return d.x @ np.asarray(self.delta_knots)


def find_kernel_correction(
    ctx: ResidualContext, opt: StructureOptions, e0: np.ndarray
) -> list[StructureFinding]:
    """A kernel correction of the blender response if cross-validation prefers it to the
    declared E(t) and it passes the held-out test (see module)."""
    length = kernel_length_s(ctx.model, ctx.dt, opt.kernel_s)
    design = kernel_design(ctx.model, ctx.data, length, opt.knot_s)
    r = np.where(ctx.finite, e0, 0.0) + design.x @ design.e_knots
    lam, cv, total = choose_lambda(design, r, ctx, opt)
    if not math.isfinite(lam):
        return []
    pen = penalty(design.x.shape[1])
    g, q = total.centred()
    u = solve_kernel(g, q, design.e_knots, lam, pen, design.mass)
    delta = design.x @ (u - design.e_knots)
    ev = heldout_evidence(
        ctx, delta, opt.heldout_level("kernel_correction"), opt.min_improvement, e0=e0
    )
    if not ev.passed:
        return []
    dt = ctx.dt
    lag_t = np.arange(design.e_lags.size) * dt
    e_lags = design.e_lags
    cum = np.cumsum(e_lags) * dt
    t99 = float(lag_t[min(int(np.searchsorted(cum, 0.99 * cum[-1])), lag_t.size - 1)])
    h = e_lags + design.basis @ (u - design.e_knots)
    shape = kernel_shape(lag_t, h, t99)
    declared = kernel_shape(lag_t, e_lags, t99)
    # moving-block bootstrap of the training residual at the chosen lambda
    tr = ctx.train
    level = total.level(u)
    res_tr = (r - design.x @ u - level)[tr]
    rng = np.random.default_rng(opt.seed)
    block = max(1, int(round(opt.bootstrap_block_s / dt)))
    fitted_tr = (design.x @ u + level)[tr]
    x_tr, w_tr = design.x[tr], ctx.weight[tr]
    wx = x_tr * w_tr[:, None]
    boots, curves = [], []
    for _ in range(opt.bootstrap):
        y_b = fitted_tr + block_bootstrap(res_tr - res_tr.mean(), block, rng)
        q_b = wx.T @ y_b - total.swx * float(w_tr @ y_b) / total.sw
        u_b = solve_kernel(g, q_b, design.e_knots, lam, pen, design.mass)
        h_b = e_lags + design.basis @ (u_b - design.e_knots)
        boots.append(kernel_shape(lag_t, h_b, t99))
        curves.append(h_b)

    def ci(name: str, value: float) -> tuple[float, float, float]:
        if not boots:
            return (value, math.nan, math.nan)
        v = np.array([getattr(b, name) for b in boots])
        lo, hi = np.percentile(v, [2.5, 97.5])
        return (float(value), float(min(lo, value)), float(max(hi, value)))

    estimates = {
        "mean_residence_time_s": ci("mean_s", shape.mean_s),
        "sd_s": ci("sd_s", shape.sd_s),
        "tail_fraction": ci("tail", shape.tail),
    }
    alternatives = [
        "a probe-side filter of the same shape (the probe alone cannot tell where the "
        "response is shaped)"
    ]
    cv_decl = cv[math.inf]
    summary = (
        f"blender response differs from the declared E(t): mean residence time "
        f"{shape.mean_s:.1f} s (declared {declared.mean_s:.1f}), sd {shape.sd_s:.1f} s "
        f"(declared {declared.sd_s:.1f}), tail beyond {t99:.0f} s "
        f"{100 * shape.tail:.1f} % (declared {100 * declared.tail:.1f} %); held-out error "
        f"{-100 * ev.rel_improvement:+.1f} % with the kernel (empirical)"
    )
    band = np.percentile(np.array(curves), [2.5, 97.5], axis=0) if curves else None
    return [
        StructureFinding(
            kind="kernel_correction",
            summary=summary,
            evidence={
                "lambda": lam,
                "cv_rel_improvement": 1.0 - cv[lam] / cv_decl if cv_decl > 0 else 0.0,
                "declared_mean_residence_time_s": declared.mean_s,
                "declared_sd_s": declared.sd_s,
                "declared_tail": declared.tail,
                "tail_time_s": t99,
                "kernel_length_s": length,
                "n_bootstrap": float(len(boots)),
                **ev.as_dict(),
            },
            estimates=estimates,
            alternatives=alternatives,
            curves={
                "lag_s": lag_t,
                "kernel": h,
                "declared": e_lags,
                "band": band,
            },
            predictor=KernelPredictor(
                tuple(float(v) for v in u - design.e_knots), length, opt.knot_s
            ),
        )
    ]
