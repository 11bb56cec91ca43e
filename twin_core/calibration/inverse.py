"""Inverse bulk calibration: material parameters that reproduce measured bulk responses.

Given fitted response surfaces y_k = f_k(theta) (k = 1..K) and measured targets y_k*, find
theta within bounds solving the (generally nonlinear) system

    r_k(theta) = (f_k(theta) - y_k*) / s_k = 0,    theta_lo <= theta <= theta_hi,

with s_k the model's RMSE (so a residual of 1 is one model standard error). The seed solved
this with GAMS/BARON (section 3.4.1, Table 3.4). Here the global search is a multi-start
bounded trust-region least squares (scipy ``least_squares``, starts from a scrambled Sobol
sequence) and/or differential evolution (Storn & Price 1997) polished by least squares. Every
distinct minimiser is returned (the seed's "solution multiplicity"), with

* an identifiability diagnosis: rank and condition number of the scaled Jacobian
  dr/d(theta normalised to [0, 1]) at each solution (rank < number of unknowns: the solutions
  form a manifold, the parameters are not identifiable from these responses);
* objective profiles: min over the other unknowns of the cost with one unknown fixed on a grid
  (profile likelihood, Raue et al. 2009): flat zero stretches are non-identifiable directions;
* a recommended solution and the rule used to pick it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
import pandas as pd
from scipy.optimize import differential_evolution, least_squares
from scipy.stats import qmc

__all__ = ["SurfaceModel", "InverseCalibration", "CalibrationResult", "Solution"]

Rule = Literal["min_variance", "nearest_prior", "best_conditioned"]


class SurfaceModel(Protocol):
    """What the solver needs from a fitted model (``ResponseSurface`` provides it)."""

    factors_: list[str]
    rmse_: float

    def predict(self, data: Mapping[str, Any]) -> np.ndarray: ...


@dataclass
class Solution:
    """One distinct minimiser of the calibration objective."""

    params: dict[str, float]
    predicted: dict[str, float]
    residuals: dict[str, float]  # scaled by the model RMSE
    cost: float  # 0.5 * sum of squared scaled residuals
    exact: bool
    jacobian_rank: int
    condition_number: float
    singular_values: list[float]
    on_bound: list[str]
    hits: int
    param_std: dict[str, float] = field(default_factory=dict)
    prediction_variance: float = float("nan")

    def as_row(self) -> dict[str, Any]:
        row: dict[str, Any] = dict(self.params)
        row.update({f"pred_{k}": v for k, v in self.predicted.items()})
        row.update(
            cost=self.cost,
            exact=self.exact,
            jacobian_rank=self.jacobian_rank,
            condition_number=self.condition_number,
            on_bound=",".join(self.on_bound),
            hits=self.hits,
            prediction_variance=self.prediction_variance,
        )
        row.update({f"std_{k}": v for k, v in self.param_std.items()})
        return row


@dataclass
class CalibrationResult:
    """Outcome of :meth:`InverseCalibration.solve`."""

    targets: dict[str, float]
    unknowns: list[str]
    solutions: list[Solution]
    recommended: Solution | None
    rule: str
    identifiable: bool
    diagnosis: str
    n_starts: int
    method: str

    def table(self) -> pd.DataFrame:
        """One row per distinct solution, recommended flagged."""
        rows = []
        for s in self.solutions:
            r = s.as_row()
            r["recommended"] = s is self.recommended
            rows.append(r)
        return pd.DataFrame(rows)


class InverseCalibration:
    """Solve fitted response surfaces backwards for material parameters.

    ``models``: response name -> fitted model; ``unknowns``: parameter -> (lower, upper);
    ``fixed``: values of the other factors the models use. ``scales`` override the residual
    scales (default each model's RMSE).
    """

    def __init__(
        self,
        models: Mapping[str, SurfaceModel],
        unknowns: Mapping[str, tuple[float, float]],
        fixed: Mapping[str, float] | None = None,
        scales: Mapping[str, float] | None = None,
    ) -> None:
        if not models:
            raise ValueError("models must name at least one fitted response surface")
        if not unknowns:
            raise ValueError("unknowns must name at least one parameter with bounds")
        self.models = dict(models)
        self.names = list(unknowns)
        self.lo = np.array([float(unknowns[n][0]) for n in self.names])
        self.hi = np.array([float(unknowns[n][1]) for n in self.names])
        for n, a, b in zip(self.names, self.lo, self.hi):
            if not (np.isfinite(a) and np.isfinite(b) and a < b):
                raise ValueError(
                    f"bounds of {n!r} must be finite with lower < upper, got ({a}, {b})"
                )
        self.fixed = {k: float(v) for k, v in (fixed or {}).items()}
        clash = set(self.fixed) & set(self.names)
        if clash:
            raise ValueError(f"parameters {sorted(clash)} are both unknown and fixed")
        for key, m in self.models.items():
            lacking = [f for f in m.factors_ if f not in self.names and f not in self.fixed]
            if lacking:
                raise ValueError(
                    f"model {key!r} uses factor(s) {lacking} that are neither unknown nor fixed"
                )
        self.scales = {
            k: float((scales or {}).get(k, getattr(m, "rmse_", 1.0)) or 1.0)
            for k, m in self.models.items()
        }
        for k, s in self.scales.items():
            if not s > 0:
                raise ValueError(f"scale of {k!r} must be > 0, got {s}")

    # ------------------------------------------------------------------ core maps
    def _theta(self, u: np.ndarray) -> np.ndarray:
        return self.lo + u * (self.hi - self.lo)

    def _values(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        """Factor columns for one (d,) or many (d, S) parameter vectors."""
        if theta.ndim == 1:
            theta = theta[:, None]
        s = theta.shape[1]
        vals = {k: np.full(s, v) for k, v in self.fixed.items()}
        for i, n in enumerate(self.names):
            vals[n] = theta[i]
        return vals

    def predict(self, params: Mapping[str, float]) -> dict[str, float]:
        """Model predictions at one parameter set (unknowns given, fixed filled in)."""
        theta = np.array([params[n] for n in self.names], dtype=float)
        vals = self._values(theta)
        return {k: float(m.predict(vals)[0]) for k, m in self.models.items()}

    def _residuals(self, u: np.ndarray, targets: np.ndarray, keys: list[str]) -> np.ndarray:
        theta = self._theta(u)
        point = {**self.fixed, **{n: float(v) for n, v in zip(self.names, theta)}}
        out = np.empty(len(keys))
        for i, (k, t) in enumerate(zip(keys, targets)):
            m = self.models[k]
            if hasattr(m, "predict_point"):
                pred = m.predict_point(point)
            else:
                pred = m.predict({a: [b] for a, b in point.items()})[0]
            out[i] = (pred - t) / self.scales[k]
        return out

    def _cost_vec(self, u: np.ndarray, targets: np.ndarray, keys: list[str]) -> np.ndarray:
        """0.5 sum r^2 for many points at once: u has shape (d, S)."""
        vals = self._values(self.lo[:, None] + u * (self.hi - self.lo)[:, None])
        tot = np.zeros(u.shape[1])
        for k, t in zip(keys, targets):
            r = (self.models[k].predict(vals) - t) / self.scales[k]
            tot += r * r
        return 0.5 * tot

    def _jacobian(self, u: np.ndarray, targets: np.ndarray, keys: list[str]) -> np.ndarray:
        theta = self._theta(u)
        point = {**self.fixed, **{n: float(v) for n, v in zip(self.names, theta)}}
        span = self.hi - self.lo
        jac = np.zeros((len(keys), len(self.names)))
        for i, k in enumerate(keys):
            m = self.models[k]
            if hasattr(m, "gradient"):
                g = m.gradient(point)
                jac[i] = [g.get(n, 0.0) for n in self.names]
            else:  # central differences
                for j in range(len(self.names)):
                    h = 1e-6 * span[j]
                    up, dn = dict(point), dict(point)
                    up[self.names[j]] += h
                    dn[self.names[j]] -= h
                    jac[i, j] = (
                        m.predict({a: [b] for a, b in up.items()})[0]
                        - m.predict({a: [b] for a, b in dn.items()})[0]
                    ) / (2 * h)
            jac[i] *= span / self.scales[k]
        return jac

    # ------------------------------------------------------------------ solve
    def _check_targets(self, targets: Mapping[str, float]) -> tuple[list[str], np.ndarray]:
        unknown = [k for k in targets if k not in self.models]
        if unknown:
            raise ValueError(f"targets {unknown} have no model; models: {list(self.models)}")
        keys = [k for k in self.models if k in targets]
        if not keys:
            raise ValueError("targets must give at least one measured response")
        vals = np.array([float(targets[k]) for k in keys])
        if not np.all(np.isfinite(vals)):
            raise ValueError(f"targets must be finite, got {dict(zip(keys, vals))}")
        return keys, vals

    def _local(
        self, u0: np.ndarray, tv: np.ndarray, keys: list[str], free: np.ndarray | None = None
    ):
        if free is None:
            res = least_squares(
                self._residuals,
                u0,
                jac=self._jacobian,
                bounds=(0.0, 1.0),
                args=(tv, keys),
                method="trf",
                xtol=1e-14,
                ftol=1e-15,
                gtol=1e-15,
                max_nfev=400,
            )
            return res.x, float(res.cost)
        fixed_u = u0.copy()

        def r_sub(v: np.ndarray) -> np.ndarray:
            full = fixed_u.copy()
            full[free] = v
            return self._residuals(full, tv, keys)

        def j_sub(v: np.ndarray) -> np.ndarray:
            full = fixed_u.copy()
            full[free] = v
            return self._jacobian(full, tv, keys)[:, free]

        res = least_squares(
            r_sub,
            u0[free],
            jac=j_sub,
            bounds=(0.0, 1.0),
            method="trf",
            xtol=1e-14,
            ftol=1e-15,
            gtol=1e-15,
            max_nfev=400,
        )
        full = fixed_u.copy()
        full[free] = res.x
        return full, float(res.cost)

    def solve(
        self,
        targets: Mapping[str, float],
        n_starts: int = 64,
        method: Literal["multistart", "de", "both"] = "both",
        seed: int | np.random.Generator | None = 0,
        exact_tol: float = 1e-10,
        distinct_tol: float = 1e-3,
        rule: Rule = "min_variance",
        prior: Mapping[str, float] | None = None,
        max_solutions: int = 50,
    ) -> CalibrationResult:
        """Global search for all parameter sets reproducing ``targets``.

        ``exact_tol``: cost (0.5 sum of squared RMSE-scaled residuals) below which a minimiser
        counts as an exact solution. ``distinct_tol``: two minimisers closer than this in the
        [0, 1]-normalised parameter box are the same solution. ``rule`` picks the recommended
        solution among the exact ones (or among all minimisers when none is exact):

        * ``min_variance``: smallest summed prediction variance of the surfaces (relative to
          their error variance) at the solution, i.e. where the surfaces are best supported by
          the design runs; needs models with ``prediction_variance``;
        * ``nearest_prior``: closest (normalised distance) to ``prior`` (default: box centre);
        * ``best_conditioned``: smallest Jacobian condition number (most robust to errors in
          the measured responses).
        """
        keys, tv = self._check_targets(targets)
        if method not in ("multistart", "de", "both"):
            raise ValueError(f"method must be 'multistart', 'de' or 'both', got {method!r}")
        if rule not in ("min_variance", "nearest_prior", "best_conditioned"):
            raise ValueError(
                f"rule must be 'min_variance', 'nearest_prior' or 'best_conditioned', got {rule!r}"
            )
        if n_starts < 1:
            raise ValueError(f"n_starts must be >= 1, got {n_starts}")
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        d = len(self.names)
        found: list[tuple[np.ndarray, float]] = []
        if method in ("multistart", "both"):
            starts = qmc.Sobol(d, scramble=True, seed=rng).random(n_starts)
            for u0 in starts:
                found.append(self._local(u0, tv, keys))
        if method in ("de", "both"):
            for _ in range(2 if method == "both" else max(2, n_starts // 16)):
                de = differential_evolution(
                    self._de_objective(tv, keys),
                    [(0.0, 1.0)] * d,
                    seed=rng,
                    tol=1e-8,
                    maxiter=200,
                    polish=False,
                    init="sobol",
                    vectorized=True,
                    updating="deferred",
                )
                found.append(self._local(np.clip(de.x, 0, 1), tv, keys))
        # cluster minimisers
        found.sort(key=lambda p: p[1])
        clusters: list[list[Any]] = []  # [u, cost, hits]
        for u, c in found:
            for cl in clusters:
                if np.linalg.norm(u - cl[0]) < distinct_tol:
                    cl[2] += 1
                    break
            else:
                clusters.append([u, c, 1])
        exact = [cl for cl in clusters if cl[1] <= exact_tol]
        chosen = exact if exact else clusters
        n_total = len(chosen)
        chosen = chosen[:max_solutions]
        sols = [self._describe(cl[0], cl[1], cl[2], tv, keys, cl[1] <= exact_tol) for cl in chosen]
        rec, rule_text = self._recommend(sols, rule, prior)
        ident, diag = self._diagnose(sols, rec, keys, n_total, bool(exact))
        return CalibrationResult(
            targets=dict(zip(keys, tv.tolist())),
            unknowns=list(self.names),
            solutions=sols,
            recommended=rec,
            rule=rule_text,
            identifiable=ident,
            diagnosis=diag,
            n_starts=n_starts,
            method=method,
        )

    def _de_objective(self, tv: np.ndarray, keys: list[str]):
        def f(u: np.ndarray) -> np.ndarray:
            u2 = u if u.ndim == 2 else u[:, None]
            return self._cost_vec(u2, tv, keys)

        return f

    def _describe(
        self, u: np.ndarray, cost: float, hits: int, tv: np.ndarray, keys: list[str], exact: bool
    ) -> Solution:
        theta = self._theta(u)
        params = {n: float(v) for n, v in zip(self.names, theta)}
        pred = self.predict(params)
        jac = self._jacobian(u, tv, keys)
        sv = np.linalg.svd(jac, compute_uv=False)
        rank = int(np.sum(sv > 1e-8 * max(sv[0], 1e-300))) if sv.size else 0
        cond = (
            float(sv[0] / sv[-1])
            if sv.size and sv[-1] > 0 and len(sv) == len(self.names)
            else float("inf")
        )
        on_bound = [n for n, x in zip(self.names, u) if x < 1e-7 or x > 1 - 1e-7]
        # linearised parameter uncertainty from the surfaces' prediction errors
        vals = self._values(theta)
        pv = []
        for k in keys:
            m = self.models[k]
            if hasattr(m, "prediction_variance"):
                pv.append(float(m.prediction_variance(vals)[0]) / self.scales[k] ** 2)
            else:
                pv.append(float("nan"))
        pv_arr = np.array(pv)
        std: dict[str, float] = {}
        if rank == len(self.names) and np.all(np.isfinite(pv_arr)):
            jp = np.linalg.pinv(jac)
            cov_u = jp @ np.diag(pv_arr) @ jp.T
            std = {
                n: float(np.sqrt(max(cov_u[i, i], 0.0)) * (self.hi[i] - self.lo[i]))
                for i, n in enumerate(self.names)
            }
        return Solution(
            params=params,
            predicted=pred,
            residuals={k: (pred[k] - t) / self.scales[k] for k, t in zip(keys, tv)},
            cost=cost,
            exact=exact,
            jacobian_rank=rank,
            condition_number=cond,
            singular_values=sv.tolist(),
            on_bound=on_bound,
            hits=hits,
            param_std=std,
            prediction_variance=float(np.nansum(pv_arr))
            if np.any(np.isfinite(pv_arr))
            else float("nan"),
        )

    def _recommend(
        self, sols: list[Solution], rule: Rule, prior: Mapping[str, float] | None
    ) -> tuple[Solution | None, str]:
        if not sols:
            return None, "no solution"
        if rule == "min_variance" and all(np.isfinite(s.prediction_variance) for s in sols):
            best = min(sols, key=lambda s: (s.prediction_variance, s.cost))
            return best, (
                "min_variance: the solution where the response surfaces have the smallest "
                "summed prediction variance (best supported by the design runs)"
            )
        if rule == "best_conditioned":
            best = min(sols, key=lambda s: (s.condition_number, s.cost))
            return best, "best_conditioned: smallest Jacobian condition number"
        centre = {
            n: (prior or {}).get(n, 0.5 * (a + b)) for n, a, b in zip(self.names, self.lo, self.hi)
        }
        span = dict(zip(self.names, self.hi - self.lo))

        def dist(s: Solution) -> float:
            return float(
                np.sqrt(sum(((s.params[n] - centre[n]) / span[n]) ** 2 for n in self.names))
            )

        best = min(sols, key=lambda s: (dist(s), s.cost))
        src = "prior" if prior else "centre of the bounds"
        return best, f"nearest_prior: closest to the {src} in range-normalised distance"

    def _diagnose(
        self, sols: list[Solution], rec: Solution | None, keys: list[str], n_total: int, exact: bool
    ) -> tuple[bool, str]:
        d, k = len(self.names), len(keys)
        parts = [f"{k} measured responses, {d} unknowns"]
        if rec is None:
            return False, "; ".join(parts + ["no minimiser found"])
        parts.append(
            f"Jacobian rank {rec.jacobian_rank} (condition number {rec.condition_number:.3g}) at "
            "the recommended solution"
        )
        ident = rec.jacobian_rank == d
        if not exact:
            parts.append(
                f"no exact solution within the bounds: {n_total} distinct least-squares minimiser(s),"
                f" best cost {sols[0].cost:.3g}"
            )
        elif not ident:
            parts.append(
                f"not identifiable: the exact solutions form a {d - rec.jacobian_rank}-dimensional "
                f"set ({n_total} distinct points found)"
            )
        elif n_total > 1:
            parts.append(
                f"locally identifiable but not unique: {n_total} distinct exact solutions "
                "(solution multiplicity)"
            )
        else:
            parts.append("locally identifiable and a single solution was found")
        if k < d:
            parts.append("fewer responses than unknowns: fix parameters or add responses")
        return ident and exact, "; ".join(parts)

    # ------------------------------------------------------------------ profiles
    def profile(
        self,
        targets: Mapping[str, float],
        name: str,
        n_points: int = 21,
        n_starts: int = 4,
        seed: int | np.random.Generator | None = 0,
    ) -> pd.DataFrame:
        """Objective profile of one unknown: for each value on a grid across its bounds, the
        minimum cost over the other unknowns (multi-start local least squares)."""
        if name not in self.names:
            raise ValueError(f"name must be one of the unknowns {self.names}, got {name!r}")
        if n_points < 2:
            raise ValueError(f"n_points must be >= 2, got {n_points}")
        keys, tv = self._check_targets(targets)
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        j = self.names.index(name)
        free = np.array([i for i in range(len(self.names)) if i != j], dtype=int)
        rows = []
        grid = np.linspace(0.0, 1.0, n_points)
        prev: np.ndarray | None = None
        for g in grid:
            best_u, best_c = None, np.inf
            inits = [rng.random(len(self.names)) for _ in range(n_starts)]
            if prev is not None:
                inits.insert(0, prev.copy())
            for u0 in inits:
                u0 = u0.copy()
                u0[j] = g
                if free.size:
                    u, c = self._local(u0, tv, keys, free=free)
                else:
                    u, c = u0, float(0.5 * np.sum(self._residuals(u0, tv, keys) ** 2))
                if c < best_c:
                    best_u, best_c = u, c
            prev = best_u
            theta = self._theta(best_u)
            row = {n: float(v) for n, v in zip(self.names, theta)}
            row["cost"] = best_c
            rows.append(row)
        return pd.DataFrame(rows)

    def contour_grid(
        self,
        x: str,
        y: str,
        at: Mapping[str, float],
        n: int = 101,
    ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Each model's prediction on an n x n grid of unknowns ``x`` and ``y`` (over their
        bounds), the other unknowns at ``at``: the seed's Fig. 3.13 contour maps."""
        for v in (x, y):
            if v not in self.names:
                raise ValueError(
                    f"contour axis must be one of the unknowns {self.names}, got {v!r}"
                )
        ix, iy = self.names.index(x), self.names.index(y)
        gx = np.linspace(self.lo[ix], self.hi[ix], n)
        gy = np.linspace(self.lo[iy], self.hi[iy], n)
        xx, yy = np.meshgrid(gx, gy)
        vals = {k: np.full(xx.size, v) for k, v in self.fixed.items()}
        for nme in self.names:
            vals[nme] = np.full(xx.size, float(at[nme])) if nme not in (x, y) else None  # type: ignore[assignment]
        vals[x] = xx.ravel()
        vals[y] = yy.ravel()
        out = {k: m.predict(vals).reshape(xx.shape) for k, m in self.models.items()}
        return xx, yy, out
