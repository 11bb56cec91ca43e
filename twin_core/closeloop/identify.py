"""Identification of undeclared effects: fit candidates, select, test on held-out data, and say
honestly how much is explained.

Procedure (forward stepwise, at most ``max_effects`` effects):

1. The measured series is cleaned of isolated outliers (Hampel filter, the seed's "outlier
   removal before denoising"); samples the data-quality check flagged
   (``twin_core.closeloop.quality``), missing samples and the start-up ``skip_s`` are left out.
   The residual r = y - prediction is divided by the noise standard deviation sigma(t) (white,
   pink and proportional parts of the sensor's ``NIRNoise``) and turned into **innovations**
   (``twin_core.closeloop.noise.NoiseWhitener``): under the declared coloured noise they are
   independent N(0, 1), each depending on the past only. Every sum of squares below is one of
   innovations, so fits are generalised least squares and the tests allow for the 1/f noise
   (the effective sample size of a slow pattern is what the noise leaves of it, not n).
2. For every candidate (effect class x target feeder for feeder effects, the measured
   component for unit effects; a candidate whose excitation is absent from the training window,
   e.g. a refill surge without a refill, is skipped), the parameters of the already accepted
   effects and of the candidate are fitted jointly by bounded least squares on the training
   innovations (``scipy.optimize.least_squares``, trust-region reflective; the starts are
   screened by cost and the best one or two refined).
3. Scores: training BIC = n ln(SSE/n) + k ln n (Schwarz 1978); held-out innovation MSE; and a
   held-out likelihood-ratio test. With e0 and e1 the held-out innovations of the current model
   and of the candidate (fitted on the training window only) and d = e0 - e1 (the innovations
   of the candidate's change of prediction), under H0 (no further effect) e0 is i.i.d. N(0, 1)
   and independent of d (causal whitening: d depends on the training data and the deterministic
   inputs), so T = d'e0 / |d| ~ N(0, 1) exactly; its one-sided p-value is 1 - Phi(T), the
   signed root of the Gaussian likelihood ratio for e0 = beta d + noise. The Diebold-Mariano
   statistic (Diebold & Mariano 1995; Harvey, Leybourne & Newbold 1997 correction; Newey-West
   long-run variance with ``hac_lag_s`` of lags) of e0^2 - e1^2 is reported too.
4. A candidate is *claimed* only if its BIC beats the current model, its held-out innovation
   MSE drops by at least ``min_improvement`` (relative), and the held-out LR p-value is below
   ``alpha`` / (number of candidates tried at that step) (Bonferroni). ``min_improvement`` is
   the margin that noise alone does not produce (calibrated by simulation of runs without
   effects: ``benchmarks/closeloop_confusion.py``, docs/closeloop.md). Among the claimable
   candidates the one with the lowest BIC over the whole record (training and held-out
   innovations, parameters from the training fit; ``select="bic_all"``) is accepted (or the
   lowest held-out error, ``select="heldout"``; after the first step the ``joint_top`` best
   claimable candidates are first refitted with every parameter free), and the search repeats
   with the augmented model. With two effects accepted, a replacement step (sequential floating selection) tries
   swapping either of them for every other candidate and keeps a pair that lowers the
   whole-record BIC and the held-out error while both of its effects pass the claim test.
5. **Equivalent explanations**: every candidate of the accepting step whose whole-record BIC is
   within ``ambiguity_bic`` (10: "very strong" evidence, Kass & Raftery 1995) of the accepted
   one and that lowers the held-out error by the margin too is an explanation the data cannot
   tell apart from it (e.g. a probe gain and API lost in the blender); they are listed with
   their scores, across stages (probe and product side). An explanation on the other side of
   the probe is kept in view up to ``cross_side_bic`` (50) instead: mistaking the product for
   the probe (or the reverse) costs the most -- a product absolved by a probe-side reading --,
   and BIC differences are computed under the declared noise: if its slow (1/f) part is
   underestimated k-fold, a difference of D under it is one of about D / k in truth
   (held-out plant data showed level/trend z-scores 3x the declared noise's: k ~ 5-10), so
   the other side is dropped only at D > 50, still "very strong" (> 10) for k = 5.
6. **Status** (the honest one): with an effect claimed, ``explained`` only if the held-out
   innovations of the augmented model (under the noise at its own level: sigma(t) from its
   prediction) are consistent with the noise
   (``twin_core.closeloop.diagnostics.innovation_tests``: scale inside its chi-square band,
   no level or trend, Ljung-Box and cumulative-periodogram whiteness, Bonferroni at
   ``noise_alpha``), else ``partly_explained``; without a claim ``consistent`` when the
   declared model's innovations (training and held-out) pass the same tests, else
   ``unexplained``.

Parameter uncertainties: standard errors from the Gauss-Newton covariance s^2 (J^T J)^-1 of the
fit on innovations (independent under the noise, so no correlation inflation), 95 % intervals
+-1.96 SE clipped to bounds.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize, stats

from twin_core.closeloop.data import RunData, Split, make_split, split_kept
from twin_core.closeloop.diagnostics import innovation_tests
from twin_core.closeloop.noise import NoiseWhitener
from twin_core.plant.effects import EFFECTS, Effect
from twin_core.plant.model import LineModel, OutletModel, sensor_signal
from twin_core.plant.nir import noise_sd
from twin_core.rtd.outliers import hampel

#: the five statuses of a close-loop report (see the module docstring; ``data_quality`` is set
#: by ``twin_core.closeloop.report.close_loop`` when flagged data faults are all there is)
#: relative tolerances of the fits (cost, step, gradient): a cost change of 1e-5 moves a BIC of
#: 7200 samples by < 0.1
FIT_TOL = 1e-5

STATUSES = ("consistent", "explained", "partly_explained", "unexplained", "data_quality")


@dataclass(frozen=True)
class Candidate:
    """A candidate effect: a registered effect class and its target (the feeder of a feeder
    effect, the component of a unit effect)."""

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
        elif cls.stage == "unit":
            out.append(Candidate(name, model.config.sensor.component))
        else:
            out.append(Candidate(name))
    return out


def effect_side(label: str) -> str:
    """``"probe"`` or ``"product"`` of a candidate label (``name`` or ``name[target]``)."""
    return "probe" if EFFECTS[label.split("[")[0]].stage == "sensor" else "product"


class _Evaluator:
    """Predictions of the probe reading and their innovations for effect sets on one record.

    The outlet of the measured component is kept per set of outlet-changing (feeder, rtd, unit)
    effects, so sensor-stage effects cost no convolution; the convolutions themselves reuse the
    inflow and kernel spectra (``twin_core.plant.model.OutletModel``).
    """

    def __init__(self, model: LineModel, data: RunData) -> None:
        self.model = model
        self.t = data.t_s
        self.sensor = model.config.sensor
        self.om = OutletModel(data.inputs, model.config.blender)
        self._cache: dict[tuple, np.ndarray] = {}
        self.n_eval = 0
        pred0 = self.predict([])
        self.sigma = np.maximum(noise_sd(pred0, self.sensor.noise), 1e-6)
        self.n_record = data.noise_record_n()
        self.whiten = NoiseWhitener(self.sigma, self.sensor.noise, self.n_record)
        self.n_eval = 0
        self.y = np.zeros_like(self.t)
        self.usable = np.zeros(self.t.size, dtype=bool)

    def set_measured(self, y: np.ndarray, usable: np.ndarray) -> None:
        """The measured series (outliers replaced) and the samples the fits use."""
        self.y = np.where(usable, y, 0.0)
        self.usable = usable

    def outlet(self, effects: Sequence[Effect]) -> np.ndarray:
        """Outlet concentration of the measured component (% w/w)."""
        allx = [*self.model.effects, *effects]
        key = tuple((e.name, e.target, tuple(e.vector())) for e in allx if e.stage != "sensor")
        hit = self._cache.get(key)
        if hit is None:
            c = self.om.concentrations(allx, [self.sensor.component]).get(self.sensor.component)
            hit = np.zeros_like(self.t) if c is None else c
            if len(self._cache) > 256:
                self._cache.clear()
            self._cache[key] = hit
        return hit

    def predict(self, effects: Sequence[Effect]) -> np.ndarray:
        self.n_eval += 1
        c = self.outlet(effects)
        return sensor_signal(
            self.t, c, [*self.model.effects, *effects], self.sensor.noise.baseline_offset
        )

    def innovations(self, pred: np.ndarray, exact_head: bool = True) -> np.ndarray:
        """Innovations of the residual y - pred (samples left out enter as 0); see
        ``NoiseWhitener`` for ``exact_head`` (off in the fits' objective)."""
        z = np.where(self.usable, (self.y - pred) / self.sigma, 0.0)
        return self.whiten(z, exact_head)


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
    innov: np.ndarray
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
    #: fits of the same step the data cannot tell from this one (module docstring, item 5)
    equivalents: list[FitResult] = field(default_factory=list)

    @property
    def alternatives(self) -> list[str]:
        """Labels of the equivalent explanations."""
        return [f.labels[-1] for f in self.equivalents]


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
    """Gaussian BIC n ln(SSE / n) + k ln n (Schwarz 1978) of a fit on innovations."""
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


def heldout_lr_test(e0: np.ndarray, e1: np.ndarray) -> tuple[float, float]:
    """T = d'e0 / |d|, d = e0 - e1, and its one-sided p-value 1 - Phi(T) (module item 3).

    ``e0``, ``e1``: held-out innovations of the current model and of the candidate.
    """
    d = np.asarray(e0, dtype=float) - np.asarray(e1, dtype=float)
    q = float(d @ d)
    if q <= 0:
        return 0.0, 1.0
    z = float(d @ np.asarray(e0, dtype=float)) / math.sqrt(q)
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
    max_nfev: int = 100
    select: str = "bic_all"
    ambiguity_bic: float = 10.0
    #: margin for an explanation on the other side of the probe (module docstring, item 5)
    cross_side_bic: float = 50.0
    swap: bool = True
    #: claimable candidates of a step after the first refitted jointly before the choice
    joint_top: int = 3
    #: level of the noise-consistency tests behind ``explained`` / ``consistent``
    noise_alpha: float = 0.01


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
    #: samples the fits and tests use (finite, not flagged, not skipped)
    usable: np.ndarray
    #: innovation tests of the model the status rests on (module docstring, item 6)
    noise_tests: dict[str, Any]
    whitener: NoiseWhitener
    n_eval: int = 0
    #: the predictions' evaluator (refits of other readings use it: :func:`refit`)
    evaluator: Any = None
    #: CPU seconds of the tests (held-out scores, innovation tests) within the identification
    tests_s: float = 0.0

    @property
    def train(self) -> np.ndarray:
        return self.split.train & self.usable

    @property
    def heldout(self) -> np.ndarray:
        return self.split.heldout & self.usable


def _fit(
    ev: _Evaluator,
    start_sets: list[list[Effect]],
    labels: list[str],
    train: np.ndarray,
    held: np.ndarray,
    max_nfev: int,
    n_refine: int = 1,
    n_fixed: int = 0,
) -> FitResult:
    """Bounded least squares on the training innovations from the best ``n_refine`` starts;
    the first ``n_fixed`` effects of each start keep their parameters."""
    best = None
    if len(start_sets) > n_refine:
        costs = []
        for effects in start_sets:
            r0 = ev.innovations(ev.predict(effects), exact_head=False)[train]
            costs.append(float(r0 @ r0))
        order = np.argsort(costs)[:n_refine]
        start_sets = [start_sets[i] for i in order]
    for effects in start_sets:
        fixed, free = list(effects[:n_fixed]), list(effects[n_fixed:])
        x0, lo, hi = _pack(free)
        if x0.size == 0:
            r = ev.innovations(ev.predict(effects), exact_head=False)[train]
            best = (float(r @ r), list(effects), None)
            break
        x0 = np.clip(x0, lo, hi)

        def resid(x: np.ndarray, fixed=fixed, free=free) -> np.ndarray:
            p = ev.predict([*fixed, *_unpack(free, x)])
            return ev.innovations(p, exact_head=False)[train]

        try:
            sol = optimize.least_squares(
                resid,
                x0,
                bounds=(lo, hi),
                x_scale=np.maximum((hi - lo) * 0.05, 1e-6),
                diff_step=1e-4,
                ftol=FIT_TOL,
                xtol=FIT_TOL,
                gtol=FIT_TOL,
                max_nfev=max_nfev,
                method="trf",
            )
        except (ValueError, FloatingPointError):
            continue
        cost = 2.0 * float(sol.cost)
        if best is None or cost < best[0]:
            best = (cost, [*fixed, *_unpack(free, sol.x)], sol)
    if best is None:
        raise RuntimeError(f"no start converged for {labels}")
    _, effs, sol = best
    pred = ev.predict(effs)
    e = ev.innovations(pred)
    sse = float(e[train] @ e[train])
    n_tr = int(train.sum())
    k = int(sum(len(x.params) for x in effs))
    stderr = _stderr(sol, effs[n_fixed:], sse, n_tr, k)
    if stderr:
        stderr = [np.full(len(x.params), np.nan) for x in effs[:n_fixed]] + stderr
    return FitResult(
        labels=labels,
        effects=list(effs),
        k=k,
        sse_train=sse,
        n_train=n_tr,
        bic=_bic(sse, n_tr, k),
        mse_heldout=float(np.mean(e[held] ** 2)),
        bic_all=_bic(float(np.sum(e[train | held] ** 2)), int(np.sum(train | held)), k),
        pred=pred,
        innov=e,
        stderr=stderr,
        converged=bool(sol.success) if sol is not None else True,
    )


def _stderr(sol: Any, effects: Sequence[Effect], sse: float, n: int, k: int) -> list[np.ndarray]:
    """Per-effect standard errors from the Gauss-Newton covariance s^2 (J'J)^-1 of a fit."""
    if sol is None or k == 0:
        return []
    J = sol.jac
    s2 = sse / max(n - k, 1)
    try:
        se = np.sqrt(np.clip(np.diag(np.linalg.pinv(J.T @ J) * s2), 0, None))
    except np.linalg.LinAlgError:
        se = np.full(k, np.nan)
    out, i = [], 0
    for e in effects:
        out.append(se[i : i + len(e.params)])
        i += len(e.params)
    return out


def _start_sets(accepted: list[Effect], cand: Candidate, max_starts: int = 6) -> list[list[Effect]]:
    cls = cand.cls
    per_param = [p.starts or (p.default,) for p in cls.params]
    combos = list(itertools.product(*per_param))[:max_starts]
    return [
        [*accepted, cls(target=cand.target, **dict(zip([p.name for p in cls.params], c)))]
        for c in combos
    ]


class _Search:
    """The forward search's shared state: evaluator, windows, options and the scoring rules."""

    def __init__(self, ev: _Evaluator, train: np.ndarray, held: np.ndarray, opt: IdentifyOptions):
        self.ev = ev
        self.train = train
        self.held = held
        self.opt = opt
        dt = float(ev.t[1] - ev.t[0])
        self.hac = int(round(opt.hac_lag_s / dt))
        self.tests_s = 0.0

    def fit(self, start_sets: list[list[Effect]], labels: list[str], n_fixed: int = 0) -> FitResult:
        """:func:`_fit` on the search's windows: two starts refined for effects of more than
        one parameter, one otherwise."""
        n_refine = 2 if start_sets and start_sets[0] and len(start_sets[0][-1].params) > 1 else 1
        return _fit(
            self.ev,
            start_sets,
            labels,
            self.train,
            self.held,
            self.opt.max_nfev,
            n_refine,
            n_fixed,
        )

    def score(self, fr: FitResult, prev: FitResult) -> None:
        """Held-out tests and BIC of ``fr`` against the model ``prev`` it extends."""
        t0 = time.process_time()
        e0 = prev.innov[self.held]
        e1 = fr.innov[self.held]
        fr.dm_stat, fr.dm_p_value = dm_test(e0, e1, self.hac)
        fr.lr_z, fr.p_value = heldout_lr_test(e0, e1)
        fr.rel_improvement = 1.0 - fr.mse_heldout / prev.mse_heldout
        fr.delta_bic = fr.bic - prev.bic
        self.tests_s += time.process_time() - t0

    def joint(self, fr: FitResult, prev: FitResult, level: float) -> FitResult:
        """``fr`` (fitted with the earlier effects held) refitted with every parameter free,
        scored against ``prev``; ``fr`` itself if the joint fit no longer passes the claim."""
        j = self.fit([list(fr.effects)], list(fr.labels))
        self.score(j, prev)
        j.claimable = self.claimable(j, level)
        return j if j.claimable and j.sse_train <= fr.sse_train else fr

    def claimable(self, fr: FitResult, level: float) -> bool:
        return bool(
            fr.delta_bic < 0
            and fr.rel_improvement >= self.opt.min_improvement
            and fr.p_value < level
        )

    def equivalents(self, chosen: FitResult, results: Sequence[FitResult]) -> list[FitResult]:
        """Fits of a step within ``ambiguity_bic`` of the chosen one (``cross_side_bic`` for
        one on the other side of the probe) that lower the held-out error by the margin too
        (module docstring, item 5), best first."""
        side = effect_side(chosen.labels[-1])

        def margin(f: FitResult) -> float:
            same = effect_side(f.labels[-1]) == side
            return self.opt.ambiguity_bic if same else self.opt.cross_side_bic

        out = [
            f
            for f in results
            if f is not chosen
            and f.bic_all - chosen.bic_all <= margin(f)
            and f.rel_improvement >= self.opt.min_improvement
        ]
        return sorted(out, key=lambda f: f.bic_all)


def _swap_refine(
    search: _Search, accepted: list[FitResult], base: FitResult, cands: list[Candidate]
) -> tuple[list[FitResult], FitResult]:
    """Replacement step of a two-effect forward search (sequential floating selection,
    Pudil, Novovicova & Kittler 1994): try replacing either accepted effect by every other
    candidate (joint refit); keep the best pair if it lowers the whole-record BIC and the
    held-out error, and if both of its effects still pass the claim test in order."""
    final = accepted[-1]
    best = None
    names = {lab.split("[")[0] for lab in final.labels}
    for i in range(len(final.effects)):
        keep = [e for j, e in enumerate(final.effects) if j != i]
        keep_labels = [lab for j, lab in enumerate(final.labels) if j != i]
        for cand in cands:
            if cand.name in names:
                continue
            fr = search.fit(_start_sets(keep, cand), [*keep_labels, cand.label], len(keep))
            if fr.bic_all < final.bic_all and fr.mse_heldout < final.mse_heldout:
                if best is None or fr.bic_all < best[0].bic_all:
                    best = (fr, keep, keep_labels)
    if best is None:
        return accepted, final
    fr, keep, keep_labels = best
    fr = search.fit([list(fr.effects)], list(fr.labels))
    keep = fr.effects[:-1]
    first = search.fit([keep], keep_labels)
    search.score(first, base)
    search.score(fr, first)
    level = search.opt.alpha / max(len(cands), 1)
    first.claimable = search.claimable(first, level)
    fr.claimable = search.claimable(fr, level)
    if not (first.claimable and fr.claimable):
        return accepted, final
    fr.equivalents = [final] if final.bic_all - fr.bic_all < search.opt.ambiguity_bic else []
    return [first, fr], fr


def _check_options(opt: IdentifyOptions) -> None:
    if opt.max_effects < 0:
        raise ValueError(f"max_effects must be >= 0, got {opt.max_effects}")
    if opt.select not in ("bic_all", "heldout"):
        raise ValueError(f"select must be 'bic_all' or 'heldout', got {opt.select!r}")
    if not 0 < opt.alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {opt.alpha}")
    if not 0 < opt.noise_alpha < 1:
        raise ValueError(f"noise_alpha must be in (0, 1), got {opt.noise_alpha}")
    if opt.cross_side_bic < opt.ambiguity_bic:
        raise ValueError(
            f"cross_side_bic must be >= ambiguity_bic ({opt.ambiguity_bic}), got {opt.cross_side_bic}"
        )


def _forward_search(
    search: _Search, base: FitResult, cands: list[Candidate]
) -> tuple[list[FitResult], list[list[FitResult]], FitResult]:
    """Forward steps (module docstring, items 2-5): returns (accepted, steps, final)."""
    opt = search.opt
    current = base
    accepted: list[FitResult] = []
    steps: list[list[FitResult]] = []
    for _ in range(opt.max_effects):
        used_names = {lab.split("[")[0] for lab in current.labels}
        todo = [c for c in cands if c.name not in used_names]
        if not todo:
            break
        results = []
        n_fixed = len(current.effects)
        for cand in todo:
            starts = _start_sets(current.effects, cand)
            fr = search.fit(starts, [*current.labels, cand.label], n_fixed)
            search.score(fr, current)
            results.append(fr)
        level = opt.alpha / len(results)
        for fr in results:
            fr.claimable = search.claimable(fr, level)
        steps.append(results)
        ok = [fr for fr in results if fr.claimable]
        if not ok:
            break
        key: Callable[[FitResult], float] = (
            (lambda f: f.mse_heldout) if opt.select == "heldout" else (lambda f: f.bic_all)
        )
        if n_fixed:
            ok = _joint_refits(search, results, ok, current, level, key)
        chosen = min(ok, key=key)
        chosen.equivalents = search.equivalents(chosen, results)
        current = chosen
        accepted.append(current)
    if len(accepted) == 2 and opt.swap:
        accepted, current = _swap_refine(search, accepted, base, cands)
    return accepted, steps, current


def _joint_refits(
    search: _Search,
    results: list[FitResult],
    ok: list[FitResult],
    current: FitResult,
    level: float,
    key: Callable[[FitResult], float],
) -> list[FitResult]:
    """The ``joint_top`` best claimable fits of a step after the first (fitted with the earlier
    effects held) refitted with every parameter free (:meth:`_Search.joint`), in place in
    ``results``: held earlier effects bias the ranking of the new one (a dead zone fitted
    without the offset favours a gain). Returns the claimable fits."""
    for fr in sorted(ok, key=key)[: search.opt.joint_top]:
        results[results.index(fr)] = search.joint(fr, current, level)
    return [fr for fr in results if fr.claimable]


def identify(
    model: LineModel,
    data: RunData,
    options: IdentifyOptions | None = None,
    exclude: np.ndarray | None = None,
) -> Identification:
    """Find the undeclared effects in ``data`` relative to ``model`` (see module docstring).

    ``exclude``: samples to leave out (flagged by the data-quality check).
    """
    opt = options or IdentifyOptions()
    _check_options(opt)
    ev = _Evaluator(model, data)
    cleaned = hampel(data.measured, variant="pearson", min_scale=ev.sigma)
    y, outl = cleaned.y, cleaned.mask
    split = make_split(data.t_s, opt.split, opt.train_fraction, opt.block_s, opt.skip_s)
    usable = np.isfinite(y) & (split.train | split.heldout)
    if exclude is not None:
        usable &= ~np.asarray(exclude, dtype=bool)
    train = split.train & usable
    held = split.heldout & usable
    if exclude is not None and (train.sum() < 10 or held.sum() < 10) and usable.sum() >= 20:
        # the quality check left out a whole window (e.g. all after a clock jump): lay the
        # windows over the usable samples
        split = split_kept(data.t_s, usable, opt.split, opt.train_fraction, opt.block_s, opt.skip_s)
        train, held = split.train & usable, split.heldout & usable
    if train.sum() < 10 or held.sum() < 10:
        raise ValueError(
            f"usable samples must be >= 10 in each window, got {int(train.sum())} training "
            f"and {int(held.sum())} held out"
        )
    ev.set_measured(y, usable)
    search = _Search(ev, train, held, opt)
    base = search.fit([[]], [])
    cands = candidate_list(model, data, train, opt.candidates)
    accepted, steps, current = _forward_search(search, base, cands)
    t0 = time.process_time()
    tests_on = held if accepted else (train | held)
    e, regress = _status_innovations(ev, current.pred, tests_on)
    noise_tests = innovation_tests(e, regress, alpha=opt.noise_alpha)
    tests_s = search.tests_s + time.process_time() - t0
    if accepted:
        status = "explained" if noise_tests["consistent"] else "partly_explained"
    else:
        status = "consistent" if noise_tests["consistent"] else "unexplained"
    return Identification(
        status=status,
        accepted=accepted,
        steps=steps,
        base=base,
        final=current,
        split=split,
        measured=y,
        sigma=ev.sigma,
        outliers=outl,
        options=opt,
        usable=usable,
        noise_tests=noise_tests,
        whitener=ev.whiten,
        n_eval=ev.n_eval,
        evaluator=ev,
        tests_s=tests_s,
    )


def _status_innovations(
    ev: _Evaluator, pred: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Innovations of the model ``pred`` on the samples ``mask`` under the noise at *its*
    level (sigma(t) from ``pred``: an effect that moves the reading, a drift or a gain, moves
    the proportional part of the noise with it), and the innovations of a unit level and of a
    linear trend (per hour, centred on the tested samples): the status tests' inputs."""
    sigma = np.maximum(noise_sd(pred, ev.sensor.noise), 1e-6)
    whiten = NoiseWhitener(sigma, ev.sensor.noise, ev.n_record)
    z = np.where(ev.usable, (ev.y - pred) / sigma, 0.0)
    tc = (ev.t - float(np.mean(ev.t[mask]))) / 3600.0
    cols = [
        whiten(np.where(ev.usable, 1.0 / sigma, 0.0)),
        whiten(np.where(ev.usable, tc / sigma, 0.0)),
    ]
    return whiten(z)[mask], np.column_stack(cols)[mask]


def refit(ident: Identification, effects: Sequence[Effect], labels: Sequence[str]) -> FitResult:
    """A fit of ``effects`` (starting from their values) on the identification's training
    window, scored against its declared model: e.g. the product-side reading of a finding."""
    ev = ident.evaluator
    search = _Search(ev, ident.train, ident.heldout, ident.options)
    fr = search.fit([list(effects)], list(labels))
    search.score(fr, ident.base)
    return fr
