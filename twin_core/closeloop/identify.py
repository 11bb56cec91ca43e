"""Identification of undeclared effects: fit candidates, select, and test on held-out data.

Procedure (forward stepwise, at most ``max_effects`` effects):

1. The measured series is cleaned of isolated outliers (Hampel filter, the seed's "outlier
   removal before denoising"); residuals are weighted by the declared noise standard deviation
   sigma(t) (white, pink and proportional parts of the sensor's ``NIRNoise``).
2. For every candidate (effect class x target feeder for feeder effects; a candidate whose
   excitation is absent from the training window, e.g. a refill surge without a refill, is
   skipped), the parameters of the already accepted effects and of the candidate are fitted
   jointly by bounded weighted least squares (``scipy.optimize.least_squares``, trust-region
   reflective, several starts) on the training window.
3. Scores: training BIC = n ln(SSE/n) + k ln n (Schwarz 1978); held-out weighted MSE; and a
   held-out likelihood-ratio test under the declared noise. With e0 the held-out residual of
   the current model and delta = p1 - p0 the change of prediction the candidate (fitted on
   the training window only) makes there, the held-out SSE improvement is
   2 delta'e0 - delta'delta; under H0 (no effect, e0 ~ N(0, C) with C the declared noise
   covariance: diagonal white + proportional variance, plus the 1/f pink covariance computed
   in the Fourier domain) it is normal with mean -delta'delta and variance 4 delta'C delta, so
   its one-sided p-value is 1 - Phi(T), T = delta'e0 / sqrt(delta'C delta) (the signed root
   of the Gaussian likelihood ratio for e0 = beta delta + noise). The Diebold-Mariano
   statistic (Diebold & Mariano 1995; Harvey, Leybourne & Newbold 1997 correction; Newey-West
   long-run variance with ``hac_lag_s`` of lags) of d_t = e0_t^2 - e1_t^2 is reported too.
4. A candidate is *claimed* only if its BIC beats the current model, its held-out weighted
   MSE drops by at least ``min_improvement`` (relative), and the held-out LR p-value is below
   ``alpha`` / (number of candidates tried at that step) (Bonferroni). ``min_improvement`` is
   the margin that noise alone does not produce: calibrated by simulation of runs without
   effects (``benchmarks/closeloop_confusion.py``, docs/closeloop.md). Among the claimable
   candidates the one with the lowest BIC over the whole record (training and held-out
   residuals, parameters from the training fit; ``select="bic_all"``) is accepted (or the
   lowest held-out error, ``select="heldout"``), and the search repeats with the augmented
   model. Claimable candidates whose whole-record BIC is within ``ambiguity_bic`` (10: "very
   strong" evidence, Kass & Raftery 1995) of the accepted one are reported as
   indistinguishable alternatives (e.g. a sensor drift and a feed-factor drift of the API
   feeder when the API flow hardly changes). With two effects accepted, a replacement step
   (sequential floating selection) tries swapping either of them for every other candidate
   and keeps a pair that lowers the whole-record BIC and the held-out error while both of its
   effects pass the claim test (greedy forward steps can pick an effect that mimics the sum
   of two others first).
5. When nothing is claimed but the residual is not explained by the declared noise (the mean
   of (r / sigma)^2 above ``unexplained_nmse`` on the training or the held-out window) the
   status is ``"unexplained"`` and the report shows the residual; otherwise
   ``"consistent"``.

Parameter uncertainties: standard errors from the Gauss-Newton covariance s^2 (J^T J)^-1 of the
weighted fit, inflated by sqrt((1 + rho1) / (1 - rho1)) for the lag-1 autocorrelation of the
weighted residual (AR(1) variance inflation), with 95 % intervals +-1.96 SE clipped to bounds.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, stats

from twin_core.closeloop.data import RunData, Split, make_split
from twin_core.plant.effects import EFFECTS, Effect
from twin_core.plant.model import LineModel, outlet_concentration, sensor_signal
from twin_core.plant.nir import noise_sd
from twin_core.rtd.outliers import hampel


@dataclass(frozen=True)
class Candidate:
    """A candidate effect: a registered effect class and, for feeder effects, its target."""

    name: str
    target: str | None = None

    @property
    def cls(self) -> type[Effect]:
        return EFFECTS[self.name]

    @property
    def label(self) -> str:
        return f"{self.name}[{self.target}]" if self.target else self.name


def candidate_list(
    model: LineModel, data: RunData, train: np.ndarray, names: Sequence[str] | None = None
) -> list[Candidate]:
    """All candidates applicable to the model and excited in the training window."""
    names = list(EFFECTS) if names is None else list(names)
    out: list[Candidate] = []
    for name in names:
        if name not in EFFECTS:
            raise ValueError(f"candidate name must be one of {sorted(EFFECTS)}, got {name!r}")
        cls = EFFECTS[name]
        if name == "back_mixing" and not ({"pe", "n"} & set(model.config.blender.params)):
            continue
        if cls.stage == "feeder":
            for feeder in data.inputs.flows_kg_h:
                if name == "refill_surge":
                    rf = data.inputs.refilling.get(feeder)
                    if rf is None or not np.any(rf & train):
                        continue
                out.append(Candidate(name, feeder))
        else:
            out.append(Candidate(name))
    return out


class _Evaluator:
    """Predictions of the probe reading for effect sets, reusing the declared outlet when only
    sensor-stage effects change."""

    def __init__(self, model: LineModel, data: RunData) -> None:
        self.model = model
        self.data = data
        self.sensor = model.config.sensor
        self.t = data.t_s
        self._cache: dict[tuple, np.ndarray] = {}
        self.n_eval = 0

    def outlet(self, effects: Sequence[Effect]) -> np.ndarray:
        """Outlet concentration; cached on the parameters of the rtd/feeder effects (sensor
        effects do not change it)."""
        key = tuple(
            (e.name, e.target, tuple(e.vector())) for e in effects if e.stage in ("rtd", "feeder")
        )
        hit = self._cache.get(key)
        if hit is None:
            hit = self._outlet([e for e in effects if e.stage in ("rtd", "feeder")])
            if len(self._cache) > 256:
                self._cache.clear()
            self._cache[key] = hit
        return hit

    def _outlet(self, effects: Sequence[Effect]) -> np.ndarray:
        allx = [*self.model.effects, *effects]
        c = outlet_concentration(self.data.inputs, self.model.config.blender, allx)
        out = c.get(self.sensor.component)
        return np.zeros_like(self.t) if out is None else out

    def predict(self, effects: Sequence[Effect]) -> np.ndarray:
        self.n_eval += 1
        c = self.outlet(effects)
        return sensor_signal(
            self.t, c, [*self.model.effects, *effects], self.sensor.noise.baseline_offset
        )


@dataclass
class FitResult:
    """A fitted effect set on the training window and its scores."""

    labels: list[str]
    effects: list[Effect]
    k: int
    sse_train: float
    n_train: int
    bic: float
    mse_heldout: float
    pred: np.ndarray
    stderr: list[np.ndarray] = field(default_factory=list)
    dm_stat: float = float("nan")
    dm_p_value: float = float("nan")
    lr_z: float = float("nan")
    p_value: float = float("nan")
    rel_improvement: float = float("nan")
    delta_bic: float = float("nan")
    #: BIC over training + held-out with the training parameters (selection score)
    bic_all: float = float("nan")
    claimable: bool = False
    converged: bool = True
    #: other claimable candidates of the same step within ``ambiguity_bic`` of this one
    alternatives: list[str] = field(default_factory=list)


def _pack(effects: Sequence[Effect]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x = np.concatenate([e.vector() for e in effects]) if effects else np.zeros(0)
    lo = np.concatenate([e.bounds()[0] for e in effects]) if effects else np.zeros(0)
    hi = np.concatenate([e.bounds()[1] for e in effects]) if effects else np.zeros(0)
    return x, lo, hi


def _unpack(effects: Sequence[Effect], x: np.ndarray) -> list[Effect]:
    out, i = [], 0
    for e in effects:
        k = len(e.params)
        out.append(e.with_vector(x[i : i + k]))
        i += k
    return out


def _bic(sse: float, n: int, k: int) -> float:
    """Gaussian BIC n ln(SSE / n) + k ln n (Schwarz 1978) of a weighted fit."""
    return n * math.log(max(sse, 1e-300) / n) + k * math.log(n)


def dm_test(e0: np.ndarray, e1: np.ndarray, hac_lag: int) -> tuple[float, float]:
    """One-sided Diebold-Mariano test that model 1 has lower squared loss than model 0.

    d_t = e0_t^2 - e1_t^2; DM = mean(d) / sqrt(LRV / n), LRV the Newey-West (Bartlett)
    long-run variance with ``hac_lag`` lags; Harvey-Leybourne-Newbold correction factor
    sqrt((n + 1 - 2h + h(h-1)/n) / n) with h = 1, p from Student t with n - 1 dof.
    Returns (statistic, p-value).
    """
    d = np.asarray(e0, dtype=float) ** 2 - np.asarray(e1, dtype=float) ** 2
    n = d.size
    if n < 5:
        return 0.0, 1.0
    dc = d - d.mean()
    gamma0 = float(dc @ dc) / n
    lrv = gamma0
    L = int(min(max(hac_lag, 0), n - 1))
    for lag in range(1, L + 1):
        g = float(dc[lag:] @ dc[:-lag]) / n
        lrv += 2.0 * (1.0 - lag / (L + 1.0)) * g
    if lrv <= 0:
        return (math.inf, 0.0) if d.mean() > 0 else (0.0, 1.0)
    dm = d.mean() / math.sqrt(lrv / n)
    h = 1
    dm *= math.sqrt((n + 1 - 2 * h + h * (h - 1) / n) / n)
    return float(dm), float(stats.t.sf(dm, n - 1))


class NoiseCovariance:
    """Quadratic form delta' C delta of the declared NIR noise covariance on a record.

    C = diag(white_sd^2 + (proportional_rel * |p|)^2) + pink_sd^2 C_pink, with C_pink the
    covariance of the unit-variance 1/f process of ``twin_core.rtd.noise.pink_noise`` over the
    record: delta' C_pink delta = sum_k a_k^2 |D_k|^2 / sum_k a_k^2, D = rfft(delta),
    a_k^2 = 1/f_k (periodic stationary process; exact for the generator up to its
    standardisation).
    """

    def __init__(self, pred: np.ndarray, noise, alpha: float = 1.0) -> None:
        n = pred.size
        self.diag = noise.white_sd**2 + (noise.proportional_rel * np.abs(pred)) ** 2
        f = np.fft.rfftfreq(n)
        a2 = np.zeros_like(f)
        a2[1:] = f[1:] ** (-alpha)
        self.a2 = a2 / a2.sum()
        self.pink_var = noise.pink_sd**2

    def quad(self, delta: np.ndarray) -> float:
        d = np.asarray(delta, dtype=float)
        D = np.fft.rfft(d)
        return float(d @ (self.diag * d) + self.pink_var * np.sum(self.a2 * np.abs(D) ** 2))


def heldout_lr_test(e0: np.ndarray, delta: np.ndarray, cov: NoiseCovariance) -> tuple[float, float]:
    """T = delta'e0 / sqrt(delta'C delta) and its one-sided p-value 1 - Phi(T) (see module).

    ``e0`` and ``delta`` are full-length arrays, zero outside the held-out window.
    """
    q = cov.quad(delta)
    if q <= 0:
        return 0.0, 1.0
    z = float(delta @ e0) / math.sqrt(q)
    return z, float(stats.norm.sf(z))


@dataclass
class IdentifyOptions:
    """Settings of :func:`identify` (see module docstring)."""

    candidates: Sequence[str] | None = None
    max_effects: int = 2
    alpha: float = 0.05
    min_improvement: float = 0.03
    hac_lag_s: float = 60.0
    split: str = "tail"
    train_fraction: float = 0.6
    block_s: float = 120.0
    skip_s: float = 0.0
    unexplained_nmse: float = 1.3
    max_nfev: int = 200
    select: str = "bic_all"
    ambiguity_bic: float = 10.0
    swap: bool = True


def _swap_refine(accepted, base, cands, ev, y_f, sigma, train, held, opt, score, claimable):
    """Replacement step of a two-effect forward search (sequential floating selection,
    Pudil, Novovicova & Kittler 1994): try replacing either accepted effect by every other
    candidate (joint refit); keep the best pair if it lowers the whole-record BIC and the
    held-out error, and if both of its effects still pass the claim test in order."""
    final = accepted[-1]
    best = None
    for i in range(len(final.effects)):
        keep = [e for j, e in enumerate(final.effects) if j != i]
        keep_labels = [lab for j, lab in enumerate(final.labels) if j != i]
        names = {lab.split("[")[0] for lab in final.labels}
        for cand in cands:
            if cand.name in names:
                continue
            fr = _fit(
                ev,
                _start_sets(keep, cand),
                [*keep_labels, cand.label],
                y_f,
                sigma,
                train,
                held,
                opt.max_nfev,
            )
            if fr.bic_all < final.bic_all and fr.mse_heldout < final.mse_heldout:
                if best is None or fr.bic_all < best[0].bic_all:
                    best = (fr, keep, keep_labels)
    if best is None:
        return accepted, final
    fr, keep, keep_labels = best
    first = _fit(ev, [keep], keep_labels, y_f, sigma, train, held, opt.max_nfev)
    score(first, base)
    score(fr, first)
    m = max(len(cands), 1)
    first.claimable = claimable(first, opt.alpha / m)
    fr.claimable = claimable(fr, opt.alpha / m)
    if not (first.claimable and fr.claimable):
        return accepted, final
    fr.alternatives = [final.labels[-1]] if final.bic_all - fr.bic_all < opt.ambiguity_bic else []
    return [first, fr], fr


@dataclass
class Identification:
    """Result of :func:`identify`."""

    status: str
    accepted: list[FitResult]
    steps: list[list[FitResult]]
    base: FitResult
    final: FitResult
    split: Split
    measured: np.ndarray
    sigma: np.ndarray
    outliers: np.ndarray
    options: IdentifyOptions
    n_eval: int = 0


def _fit(
    ev: _Evaluator,
    start_sets: list[list[Effect]],
    labels: list[str],
    y: np.ndarray,
    sigma: np.ndarray,
    train: np.ndarray,
    held: np.ndarray,
    max_nfev: int,
    n_refine: int = 2,
) -> FitResult:
    best = None
    if len(start_sets) > n_refine:
        # screen the starts by their cost, refine the best ``n_refine`` of them
        costs = []
        for effects in start_sets:
            r0 = ((y - ev.predict(effects)) / sigma)[train]
            costs.append(float(r0 @ r0))
        order = np.argsort(costs)[:n_refine]
        start_sets = [start_sets[i] for i in order]
    for effects in start_sets:
        x0, lo, hi = _pack(effects)
        if x0.size == 0:
            pred = ev.predict([])
            r = (y - pred) / sigma
            best = (float(np.sum(r[train] ** 2)), effects, None)
            break
        x0 = np.clip(x0, lo, hi)

        def resid(x: np.ndarray, effects=effects) -> np.ndarray:
            p = ev.predict(_unpack(effects, x))
            return ((y - p) / sigma)[train]

        span = hi - lo
        try:
            sol = optimize.least_squares(
                resid,
                x0,
                bounds=(lo, hi),
                x_scale=np.maximum(span * 0.05, 1e-6),
                diff_step=1e-4,
                ftol=1e-6,
                xtol=1e-6,
                gtol=1e-6,
                max_nfev=max_nfev,
                method="trf",
            )
        except (ValueError, FloatingPointError):
            continue
        cost = 2.0 * float(sol.cost)
        if best is None or cost < best[0]:
            best = (cost, _unpack(effects, sol.x), sol)
    if best is None:
        raise RuntimeError(f"no start converged for {labels}")
    sse, effs, sol = best
    pred = ev.predict(effs)
    r = (y - pred) / sigma
    n_tr = int(train.sum())
    k = int(sum(len(e.params) for e in effs))
    bic = n_tr * math.log(max(sse, 1e-300) / n_tr) + k * math.log(n_tr)
    stderr: list[np.ndarray] = []
    if sol is not None and k > 0:
        J = sol.jac
        rt = r[train]
        s2 = sse / max(n_tr - k, 1)
        rho = float(np.clip(np.corrcoef(rt[1:], rt[:-1])[0, 1], -0.95, 0.95)) if n_tr > 3 else 0.0
        infl = math.sqrt((1 + rho) / (1 - rho)) if rho > 0 else 1.0
        try:
            cov = np.linalg.pinv(J.T @ J) * s2
            se = np.sqrt(np.clip(np.diag(cov), 0, None)) * infl
        except np.linalg.LinAlgError:
            se = np.full(k, np.nan)
        i = 0
        for e in effs:
            stderr.append(se[i : i + len(e.params)])
            i += len(e.params)
    return FitResult(
        labels=labels,
        effects=list(effs),
        k=k,
        sse_train=sse,
        n_train=n_tr,
        bic=bic,
        mse_heldout=float(np.mean(r[held] ** 2)),
        bic_all=_bic(float(np.sum(r[train | held] ** 2)), int(np.sum(train | held)), k),
        pred=pred,
        stderr=stderr,
        converged=bool(sol.success) if sol is not None else True,
    )


def _start_sets(accepted: list[Effect], cand: Candidate, max_starts: int = 6) -> list[list[Effect]]:
    cls = cand.cls
    per_param = [p.starts or (p.default,) for p in cls.params]
    combos = list(itertools.product(*per_param))[:max_starts]
    return [
        [*accepted, cls(target=cand.target, **dict(zip([p.name for p in cls.params], c)))]
        for c in combos
    ]


def identify(
    model: LineModel, data: RunData, options: IdentifyOptions | None = None
) -> Identification:
    """Find the undeclared effects in ``data`` relative to ``model`` (see module docstring)."""
    opt = options or IdentifyOptions()
    if opt.max_effects < 0:
        raise ValueError(f"max_effects must be >= 0, got {opt.max_effects}")
    if opt.select not in ("bic_all", "heldout"):
        raise ValueError(f"select must be 'bic_all' or 'heldout', got {opt.select!r}")
    if not 0 < opt.alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {opt.alpha}")
    cleaned = hampel(data.measured, variant="pearson")
    y, outl = cleaned.y, cleaned.mask
    finite = np.isfinite(y)
    split = make_split(data.t_s, opt.split, opt.train_fraction, opt.block_s, opt.skip_s)
    train = split.train & finite
    held = split.heldout & finite
    ev = _Evaluator(model, data)
    declared_pred = ev.predict([])
    sigma = noise_sd(declared_pred, model.config.sensor.noise)
    sigma = np.maximum(sigma, 1e-6)
    y_f = np.where(finite, y, 0.0)
    dt = float(data.t_s[1] - data.t_s[0])
    hac = int(round(opt.hac_lag_s / dt))
    cov = NoiseCovariance(declared_pred, model.config.sensor.noise)

    def score(fr: FitResult, prev: FitResult) -> None:
        """Held-out tests and BIC of ``fr`` against the model ``prev`` it extends."""
        e0 = ((y_f - prev.pred) / sigma)[held]
        e1 = ((y_f - fr.pred) / sigma)[held]
        fr.dm_stat, fr.dm_p_value = dm_test(e0, e1, hac)
        fr.lr_z, fr.p_value = heldout_lr_test(
            np.where(held, y_f - prev.pred, 0.0), np.where(held, fr.pred - prev.pred, 0.0), cov
        )
        fr.rel_improvement = 1.0 - fr.mse_heldout / prev.mse_heldout
        fr.delta_bic = fr.bic - prev.bic

    def claimable(fr: FitResult, level: float) -> bool:
        return bool(
            fr.delta_bic < 0 and fr.rel_improvement >= opt.min_improvement and fr.p_value < level
        )

    base = _fit(ev, [[]], [], y_f, sigma, train, held, opt.max_nfev)
    current = base
    accepted: list[FitResult] = []
    steps: list[list[FitResult]] = []
    cands = candidate_list(model, data, train, opt.candidates)
    for _ in range(opt.max_effects):
        used = {lab for lab in current.labels}
        used_names = {lab.split("[")[0] for lab in current.labels}
        todo = [c for c in cands if c.label not in used and c.name not in used_names]
        if not todo:
            break
        results = []
        for cand in todo:
            starts = _start_sets(current.effects, cand)
            fr = _fit(
                ev, starts, [*current.labels, cand.label], y_f, sigma, train, held, opt.max_nfev
            )
            score(fr, current)
            results.append(fr)
        level = opt.alpha / len(results)
        for fr in results:
            fr.claimable = claimable(fr, level)
        steps.append(results)
        ok = [fr for fr in results if fr.claimable]
        if not ok:
            break
        key = (lambda f: f.mse_heldout) if opt.select == "heldout" else (lambda f: f.bic_all)
        current = min(ok, key=key)
        current.alternatives = [
            f.labels[-1]
            for f in ok
            if f is not current and f.bic_all - current.bic_all < opt.ambiguity_bic
        ]
        accepted.append(current)

    if len(accepted) == 2 and opt.swap:
        accepted, current = _swap_refine(
            accepted, base, cands, ev, y_f, sigma, train, held, opt, score, claimable
        )

    if accepted:
        status = "explained"
    else:
        r = (y_f - base.pred) / sigma
        nmse_tr = float(np.mean(r[train] ** 2))
        nmse_ho = float(np.mean(r[held] ** 2))
        status = "unexplained" if max(nmse_tr, nmse_ho) > opt.unexplained_nmse else "consistent"
    return Identification(
        status=status,
        accepted=accepted,
        steps=steps,
        base=base,
        final=current,
        split=split,
        measured=y,
        sigma=sigma,
        outliers=outl,
        options=opt,
        n_eval=ev.n_eval,
    )
