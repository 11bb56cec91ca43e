"""Response surfaces by ordinary least squares and stepwise term selection.

Model (JMP "Fit Least Squares" conventions, which the seed used):

    y = b0 + sum_i b_i x_i + sum_{i<j} b_ij (x_i - c_i)(x_j - c_j) + sum_i b_ii (x_i - c_i)^2

with physical (uncoded) factors x and the centres c_i the means of the factors over the fitted
runs ("centre polynomials"), which is why the seed's Eq. (10) reads (PP_SF - 0.35)^2.
Estimates, standard errors s sqrt(diag (X^T X)^-1), t ratios, two-sided p values, the ANOVA
table (model / error / corrected total, F ratio, Prob > F), R^2, adjusted R^2, RMSE and the
information criteria

    -2 logL = n ln(2 pi SSE / n) + n,
    AIC = -2 logL + 2k,  AICc = AIC + 2k(k+1)/(n-k-1),  BIC = -2 logL + k ln n,

with k = number of coefficients + 1 (the error variance), as in JMP's stepwise platform.

Stepwise selection (Efroymson 1960; criterion-based as in JMP / R ``step``): forward, backward
or mixed moves, each move chosen by the largest drop in AIC/AICc/BIC, or by p values
(enter if p < p_enter, leave if p > p_leave). The seed's two-step procedure for definitive
screening designs (Jones & Nachtsheim 2011, 2017) is :class:`TwoStepRSM`: step 1 selects main
effects; step 2 keeps them and selects among their two-factor interactions and quadratics
(strong effect heredity: a second-order term only if all its parent main effects are in).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import pandas as pd
from scipy import stats

__all__ = [
    "Term",
    "parse_term",
    "term_name",
    "ResponseSurface",
    "stepwise",
    "StepwiseResult",
    "TwoStepRSM",
    "check_table",
]

Term = tuple[str, ...]
Criterion = Literal["aic", "aicc", "bic", "p"]


def term_name(term: Term) -> str:
    """'A' for a main effect, 'A*B' for an interaction, 'A*A' for a quadratic."""
    return "*".join(term)


def parse_term(text: str | Sequence[str]) -> Term:
    """Inverse of :func:`term_name`; also accepts 'A^2' and tuples."""
    if not isinstance(text, str):
        return tuple(str(x) for x in text)
    s = text.replace(" ", "")
    if s.endswith("^2"):
        return (s[:-2], s[:-2])
    return tuple(s.split("*"))


def check_table(
    data: pd.DataFrame,
    factors: Sequence[str],
    response: str | None = None,
    min_runs: int = 2,
) -> None:
    """Validate a design/results table: columns present, numeric, finite, not constant.

    Raises ``ValueError`` naming the offending column (and rows) otherwise.
    """
    if not isinstance(data, pd.DataFrame):
        raise ValueError(f"data must be a pandas DataFrame, got {type(data).__name__}")
    needed = list(factors) + ([response] if response is not None else [])
    missing = [c for c in needed if c not in data.columns]
    if missing:
        raise ValueError(f"table lacks column(s) {missing}; it has {list(data.columns)}")
    if len(data) < min_runs:
        raise ValueError(f"table has {len(data)} runs, need at least {min_runs}")
    for c in needed:
        col = pd.to_numeric(data[c], errors="coerce")
        bad = data.index[~np.isfinite(col.to_numpy(dtype=float))].tolist()
        if bad:
            raise ValueError(f"column {c!r} has missing or non-numeric values in rows {bad[:10]}")
    for c in factors:
        if data[c].nunique() < 2:
            raise ValueError(
                f"factor {c!r} is constant ({data[c].iloc[0]}): its effect cannot be estimated"
            )


def _all_factors(terms: Sequence[Term]) -> list[str]:
    seen: list[str] = []
    for t in terms:
        for f in t:
            if f not in seen:
                seen.append(f)
    return seen


def _design_matrix(
    data: pd.DataFrame | Mapping[str, np.ndarray],
    terms: Sequence[Term],
    centers: Mapping[str, float],
) -> np.ndarray:
    cols_in = {f: np.asarray(data[f], dtype=float) for f in _all_factors(terms)}
    n = len(next(iter(cols_in.values()))) if cols_in else len(data)
    cols = [np.ones(n)]
    for t in terms:
        if len(t) == 1:
            cols.append(cols_in[t[0]])
        else:
            v = np.ones(n)
            for f in t:
                v = v * (cols_in[f] - centers[f])
            cols.append(v)
    return np.column_stack(cols)


@dataclass
class ResponseSurface:
    """OLS response surface with JMP-style centred polynomial terms.

    ``ResponseSurface(terms=["A", "B", "A*A"]).fit(data, "y")``. After ``fit``:
    ``coef_`` (pandas Series, 'Intercept' first), ``stderr_``, ``tvalues_``, ``pvalues_``,
    ``centers_`` (factor means), ``anova_`` (DataFrame), ``r2_``, ``r2_adj_``, ``rmse_``,
    ``sse_``, ``n_``, ``aic_``, ``aicc_``, ``bic_``, ``residuals_``, ``fitted_``.
    """

    terms: Sequence[str | Term] = ()
    center: bool = True
    response: str | None = field(default=None, init=False)

    def fit(self, data: pd.DataFrame, response: str) -> ResponseSurface:
        terms = [parse_term(t) for t in self.terms]
        if len(set(terms)) != len(terms):
            raise ValueError(f"terms contain duplicates: {[term_name(t) for t in terms]}")
        factors = _all_factors(terms)
        p = len(terms) + 1
        check_table(data, factors, response)
        n = len(data)
        if n <= p:
            raise ValueError(
                f"too few runs for the terms: {n} runs for {p} coefficients (need > {p} to "
                "estimate the error)"
            )
        self.terms_ = terms
        self.response = response
        self.factors_ = factors
        self.centers_ = {f: (float(data[f].mean()) if self.center else 0.0) for f in factors}
        x = _design_matrix(data, terms, self.centers_)
        y = data[response].to_numpy(dtype=float)
        rank = np.linalg.matrix_rank(x)
        if rank < p:
            raise ValueError(
                f"terms {[term_name(t) for t in terms]} are not estimable from this design "
                f"(model matrix rank {rank} < {p} coefficients; aliased or constant terms)"
            )
        q, r = np.linalg.qr(x)
        beta = np.linalg.solve(r, q.T @ y)
        fitted = x @ beta
        resid = y - fitted
        sse = float(resid @ resid)
        sst = float(((y - y.mean()) ** 2).sum())
        dfe = n - p
        mse = sse / dfe
        rinv = np.linalg.inv(r)
        cov = mse * (rinv @ rinv.T)
        se = np.sqrt(np.clip(np.diag(cov), 0.0, np.inf))
        with np.errstate(divide="ignore", invalid="ignore"):
            tval = beta / se
        pval = 2.0 * stats.t.sf(np.abs(tval), dfe)
        names = ["Intercept"] + [term_name(t) for t in terms]
        self.coef_ = pd.Series(beta, index=names)
        self._coef_list = [float(b) for b in beta]
        self.stderr_ = pd.Series(se, index=names)
        self.tvalues_ = pd.Series(tval, index=names)
        self.pvalues_ = pd.Series(pval, index=names)
        self.cov_ = pd.DataFrame(cov, index=names, columns=names)
        ssm = sst - sse
        dfm = p - 1
        f_ratio = (ssm / dfm) / mse if dfm > 0 and mse > 0 else float("nan")
        p_f = float(stats.f.sf(f_ratio, dfm, dfe)) if dfm > 0 and mse > 0 else float("nan")
        self.anova_ = pd.DataFrame(
            {
                "DF": [dfm, dfe, n - 1],
                "Sum of Squares": [ssm, sse, sst],
                "Mean Square": [ssm / dfm if dfm else float("nan"), mse, float("nan")],
                "F Ratio": [f_ratio, float("nan"), float("nan")],
                "Prob > F": [p_f, float("nan"), float("nan")],
            },
            index=pd.Index(["Model", "Error", "C. Total"], name="Source"),
        )
        self.n_ = n
        self.sse_ = sse
        self.sst_ = sst
        self.r2_ = 1.0 - sse / sst if sst > 0 else float("nan")
        self.r2_adj_ = 1.0 - (sse / dfe) / (sst / (n - 1)) if sst > 0 else float("nan")
        self.rmse_ = math.sqrt(mse)
        k = p + 1
        m2ll = n * math.log(2 * math.pi * max(sse, 1e-300) / n) + n
        self.aic_ = m2ll + 2 * k
        self.aicc_ = self.aic_ + (2 * k * (k + 1) / (n - k - 1) if n - k - 1 > 0 else float("inf"))
        self.bic_ = m2ll + k * math.log(n)
        self.fitted_ = fitted
        self.residuals_ = resid
        self.actual_ = y
        return self

    # ------------------------------------------------------------------ use
    def predict(self, data: pd.DataFrame | Mapping[str, float | Sequence[float]]) -> np.ndarray:
        """Predicted response for rows of ``data`` (DataFrame or mapping of factor values)."""
        if not isinstance(data, pd.DataFrame):
            data = {k: np.atleast_1d(np.asarray(v, dtype=float)) for k, v in data.items()}
        missing = [f for f in self.factors_ if f not in data]
        if missing:
            raise ValueError(f"predict needs factor column(s) {missing}")
        if not self.factors_:
            n = (
                len(data)
                if isinstance(data, pd.DataFrame)
                else max([len(v) for v in data.values()], default=1)
            )
            return np.full(n, float(self.coef_.iloc[0]))
        x = _design_matrix(data, self.terms_, self.centers_)
        return x @ self.coef_.to_numpy()

    def predict_point(self, values: Mapping[str, float]) -> float:
        """Prediction at one point given as scalars (fast path for solvers)."""
        coef = self._coef_list
        out = coef[0]
        for t, b in zip(self.terms_, coef[1:]):
            if len(t) == 1:
                out += b * values[t[0]]
            else:
                v = b
                for f in t:
                    v *= values[f] - self.centers_[f]
                out += v
        return out

    def prediction_variance(
        self, data: pd.DataFrame | Mapping[str, float | Sequence[float]]
    ) -> np.ndarray:
        """Variance of the fitted mean at the rows of ``data``: x0^T Cov(b) x0."""
        if not isinstance(data, pd.DataFrame):
            data = {k: np.atleast_1d(np.asarray(v, dtype=float)) for k, v in data.items()}
        x = _design_matrix(data, self.terms_, self.centers_)
        return np.einsum("ij,jk,ik->i", x, self.cov_.to_numpy(), x)

    def predict_interval(
        self,
        data: pd.DataFrame | Mapping[str, float | Sequence[float]],
        alpha: float = 0.05,
        kind: Literal["confidence", "prediction"] = "prediction",
    ) -> pd.DataFrame:
        """Prediction with a two-sided t interval: 'confidence' for the mean response
        (x0' Cov x0), 'prediction' for a new run (adds the error variance s^2)."""
        if not 0 < alpha < 1:
            raise ValueError(f"alpha must be in (0, 1), got {alpha}")
        if kind not in ("confidence", "prediction"):
            raise ValueError(f"kind must be 'confidence' or 'prediction', got {kind!r}")
        mean = self.predict(data)
        var = self.prediction_variance(data)
        if kind == "prediction":
            var = var + self.rmse_**2
        half = stats.t.ppf(1 - alpha / 2, self.n_ - len(self.terms_) - 1) * np.sqrt(var)
        return pd.DataFrame({"predicted": mean, "lower": mean - half, "upper": mean + half})

    def gradient(self, values: Mapping[str, float]) -> dict[str, float]:
        """Analytic d(prediction)/d(factor) at one point."""
        grad = {f: 0.0 for f in self.factors_}
        for t, b in zip(self.terms_, self.coef_.to_numpy()[1:]):
            if len(t) == 1:
                grad[t[0]] += b
                continue
            for i, f in enumerate(t):
                other = 1.0
                for j, g in enumerate(t):
                    if j != i:
                        other *= values[g] - self.centers_[g]
                grad[f] += b * other
        return grad

    def criterion(self, name: Criterion) -> float:
        return {"aic": self.aic_, "aicc": self.aicc_, "bic": self.bic_}[name]

    def display_name(self, term: Term) -> str:
        """JMP-style label: 'PP_SF', '(PP_SF-0.35)*(PW_SF-0.35)'."""
        if len(term) == 1:
            return term[0]
        return "*".join(f"({f}-{self.centers_[f]:.7g})" for f in term)

    def parameter_table(self) -> pd.DataFrame:
        """JMP 'Parameter Estimates': Estimate, Std Error, t Ratio, Prob>|t|."""
        labels = ["Intercept"] + [self.display_name(t) for t in self.terms_]
        return pd.DataFrame(
            {
                "Estimate": self.coef_.to_numpy(),
                "Std Error": self.stderr_.to_numpy(),
                "t Ratio": self.tvalues_.to_numpy(),
                "Prob>|t|": self.pvalues_.to_numpy(),
            },
            index=pd.Index(labels, name="Term"),
        )

    def effect_summary(self) -> pd.DataFrame:
        """JMP 'Effect Summary': terms by LogWorth = -log10(p), largest first."""
        p = self.pvalues_.drop("Intercept")
        return (
            pd.DataFrame({"LogWorth": -np.log10(np.maximum(p.to_numpy(), 1e-300)), "PValue": p})
            .sort_values("LogWorth", ascending=False)
            .rename_axis("Source")
        )

    def equation(self, digits: int = 7) -> str:
        """The fitted surface as text in the seed's form (e.g. its Eq. 10)."""
        parts = [f"{self.coef_.iloc[0]:.{digits}g}"]
        for t, b in zip(self.terms_, self.coef_.to_numpy()[1:]):
            sign = "-" if b < 0 else "+"
            label = self.display_name(t)
            if len(t) == 2 and t[0] == t[1]:
                label = f"({t[0]}-{self.centers_[t[0]]:.7g})^2"
            parts.append(f"{sign} {abs(b):.{digits}g}*{label}")
        return f"{self.response} = " + " ".join(parts)

    def report(self) -> str:
        """Text report: summary of fit, ANOVA and parameter estimates (like JMP)."""
        lines = [
            f"Response {self.response}",
            f"RSquare {self.r2_:.4f}  RSquare Adj {self.r2_adj_:.4f}  RMSE {self.rmse_:.6g}  "
            f"N {self.n_}  AICc {self.aicc_:.4f}  BIC {self.bic_:.4f}",
            "",
            "Analysis of Variance",
            self.anova_.to_string(float_format=lambda v: f"{v:.6g}"),
            "",
            "Parameter Estimates",
            self.parameter_table().to_string(float_format=lambda v: f"{v:.7g}"),
            "",
            self.equation(),
        ]
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-able description (terms, centres, coefficients, fit statistics)."""
        return {
            "response": self.response,
            "terms": [term_name(t) for t in self.terms_],
            "centers": self.centers_,
            "coef": self.coef_.to_dict(),
            "stderr": self.stderr_.to_dict(),
            "r2": self.r2_,
            "r2_adj": self.r2_adj_,
            "rmse": self.rmse_,
            "sse": self.sse_,
            "n": self.n_,
        }


# --------------------------------------------------------------------------- stepwise
def _heredity_ok(term: Term, model: Sequence[Term], heredity: str) -> bool:
    if len(term) == 1 or heredity == "none":
        return True
    parents = {(f,) for f in term}
    inside = sum(p in model for p in parents)
    return inside == len(parents) if heredity == "strong" else inside >= 1


def _removable(term: Term, model: Sequence[Term], heredity: str) -> bool:
    """A main effect cannot leave while a second-order term needing it stays."""
    if len(term) > 1 or heredity == "none":
        return True
    rest = [t for t in model if t != term]
    return all(_heredity_ok(t, [u for u in rest if u != t], heredity) for t in rest if len(t) > 1)


@dataclass
class StepwiseResult:
    """Outcome of :func:`stepwise`: the final fitted model and the move history."""

    model: ResponseSurface
    terms: list[Term]
    history: pd.DataFrame


def stepwise(
    data: pd.DataFrame,
    response: str,
    candidates: Sequence[str | Term],
    criterion: Criterion = "bic",
    direction: Literal["forward", "backward", "both"] = "both",
    forced: Sequence[str | Term] = (),
    start: Sequence[str | Term] | None = None,
    heredity: Literal["strong", "weak", "none"] = "strong",
    p_enter: float = 0.1,
    p_leave: float = 0.1,
    max_steps: int = 200,
) -> StepwiseResult:
    """Select terms from ``candidates`` (``forced`` terms always in) by stepwise OLS.

    Each step evaluates every admissible move (add for forward/both, remove for
    backward/both) and takes the best: the lowest AIC/AICc/BIC, or for ``criterion='p'`` the
    smallest p value below ``p_enter`` to add / the largest above ``p_leave`` to remove. It
    stops when no move improves. ``start`` defaults to the forced terms (forward/both) or to all
    candidates (backward).
    """
    cands = [parse_term(c) for c in candidates]
    forced_t = [parse_term(c) for c in forced]
    if criterion not in ("aic", "aicc", "bic", "p"):
        raise ValueError(f"criterion must be 'aic', 'aicc', 'bic' or 'p', got {criterion!r}")
    if direction not in ("forward", "backward", "both"):
        raise ValueError(f"direction must be 'forward', 'backward' or 'both', got {direction!r}")
    check_table(data, _all_factors(cands + forced_t), response)
    if start is None:
        current = (
            list(forced_t) if direction != "backward" else list(dict.fromkeys(forced_t + cands))
        )
    else:
        current = list(dict.fromkeys(forced_t + [parse_term(s) for s in start]))
    n = len(data)

    def fit(terms: list[Term]) -> ResponseSurface | None:
        if len(terms) + 2 > n:
            return None
        try:
            return ResponseSurface(terms=terms).fit(data, response)
        except ValueError:
            return None

    model = fit(current)
    if model is None:
        raise ValueError(
            f"the starting model {[term_name(t) for t in current]} cannot be fitted with {n} runs"
        )
    history = [
        {
            "step": 0,
            "action": "start",
            "term": "",
            "n_terms": len(current),
            "sse": model.sse_,
            "aicc": model.aicc_,
            "bic": model.bic_,
            "p": float("nan"),
        }
    ]
    for step in range(1, max_steps + 1):
        moves: list[tuple[float, str, Term, ResponseSurface]] = []
        if direction in ("forward", "both"):
            for c in cands:
                if c in current or not _heredity_ok(c, current, heredity):
                    continue
                m = fit(current + [c])
                if m is None:
                    continue
                if criterion == "p":
                    pv = float(m.pvalues_[term_name(c)])
                    if pv < p_enter:
                        moves.append((pv - 1.0, "enter", c, m))  # smaller p first
                else:
                    moves.append(
                        (m.criterion(criterion) - model.criterion(criterion), "enter", c, m)
                    )
        if direction in ("backward", "both"):
            for c in current:
                if c in forced_t or not _removable(c, current, heredity):
                    continue
                rest = [t for t in current if t != c]
                m = fit(rest)
                if m is None:
                    continue
                if criterion == "p":
                    pv = float(model.pvalues_[term_name(c)])
                    if pv > p_leave:
                        moves.append((-pv - 1.0, "remove", c, m))  # larger p first
                else:
                    moves.append(
                        (m.criterion(criterion) - model.criterion(criterion), "remove", c, m)
                    )
        if criterion != "p":
            moves = [mv for mv in moves if mv[0] < -1e-9]
        if not moves:
            break
        if criterion == "p":
            removes = [mv for mv in moves if mv[1] == "remove"]
            best = min(removes or moves, key=lambda mv: mv[0])
        else:
            best = min(moves, key=lambda mv: mv[0])
        _, action, term, new = best
        current = current + [term] if action == "enter" else [t for t in current if t != term]
        pv = (
            float(new.pvalues_[term_name(term)])
            if action == "enter"
            else float(model.pvalues_[term_name(term)])
        )
        model = new
        history.append(
            {
                "step": step,
                "action": action,
                "term": term_name(term),
                "n_terms": len(current),
                "sse": model.sse_,
                "aicc": model.aicc_,
                "bic": model.bic_,
                "p": pv,
            }
        )
        if (
            len(history) > 3
            and history[-1]["term"] == history[-3]["term"]
            and history[-1]["action"] == history[-3]["action"]
        ):
            break  # p-value cycling guard
    # present terms in a stable order: main effects (data order), then second order
    order = {t: i for i, t in enumerate(forced_t + cands)}
    current.sort(key=lambda t: (len(t) > 1, order.get(t, 10**6)))
    model = ResponseSurface(terms=current).fit(data, response)
    return StepwiseResult(model=model, terms=current, history=pd.DataFrame(history))


def second_order_terms(
    mains: Sequence[str], interactions: bool = True, quadratics: bool = True
) -> list[Term]:
    """Two-factor interactions and quadratics of the given main effects."""
    out: list[Term] = []
    if interactions:
        out += [(a, b) for a, b in itertools.combinations(mains, 2)]
    if quadratics:
        out += [(a, a) for a in mains]
    return out


class TwoStepRSM:
    """The seed's two-step DSD analysis (section 3.3.1.2): step 1 selects main effects by
    stepwise regression; step 2 keeps them and adds two-factor interactions and quadratics
    of the selected factors (strong heredity), again stepwise.

    ``TwoStepRSM(factors, criterion="bic").fit(table, "shear_angle_deg")`` sets
    ``main_effects_``, ``step1_`` (main-effects model, the seed's Fig. 8.1), ``model_`` (final
    model, Fig. 8.2 / Eq. 10), ``history_``.
    """

    def __init__(
        self,
        factors: Sequence[str],
        criterion: Criterion = "bic",
        direction: Literal["forward", "backward", "both"] = "both",
        criterion_step2: Criterion | None = None,
        interactions: bool = True,
        quadratics: bool = True,
        p_enter: float = 0.1,
        p_leave: float = 0.1,
    ) -> None:
        self.factors = list(factors)
        self.criterion = criterion
        self.direction = direction
        self.criterion_step2 = criterion_step2
        self.interactions = interactions
        self.quadratics = quadratics
        self.p_enter = p_enter
        self.p_leave = p_leave

    def fit(self, data: pd.DataFrame, response: str) -> TwoStepRSM:
        check_table(data, self.factors, response, min_runs=3)
        s1 = stepwise(
            data,
            response,
            [(f,) for f in self.factors],
            criterion=self.criterion,
            direction=self.direction,
            p_enter=self.p_enter,
            p_leave=self.p_leave,
        )
        mains = [t[0] for t in s1.terms]
        cands = second_order_terms(mains, self.interactions, self.quadratics)
        kw = dict(
            criterion=self.criterion_step2 or self.criterion,
            forced=s1.terms,
            p_enter=self.p_enter,
            p_leave=self.p_leave,
        )
        try:
            s2 = stepwise(data, response, cands, direction=self.direction, **kw)
        except ValueError:
            if self.direction != "backward":
                raise
            # the full second-order model is not estimable from these runs (more terms
            # than runs, or aliased in the design): select from the main-effects model up
            s2 = stepwise(data, response, cands, direction="both", **kw)
        self.main_effects_ = mains
        self.step1_ = s1.model
        self.model_ = s2.model
        self.history_ = pd.concat(
            [s1.history.assign(stage=1), s2.history.assign(stage=2)], ignore_index=True
        )
        return self

    def predict(self, data: pd.DataFrame | Mapping[str, float | Sequence[float]]) -> np.ndarray:
        return self.model_.predict(data)
