"""Joint analysis of repeat tracer pulses of one system (the seed repeats each pulse three
times, ch. 6): lack of fit combined over the repeats, estimates pooled with a check that the
repeats agree.

One 250 s record of a small pulse does not carry a weak stagnant zone against its 1/f noise
(docs/rtd.md: no test of one record reaches 95 % power there), but the evidence of k
independent records of the same system adds up.

- **Joint lack of fit.** Each lack-of-fit test of the model (``rtd.likelihood.LackOfFit``:
  ``shape``, ``exchange`` ...) is combined over the repeats by Stouffer's method: with p_i the
  one-sided p-value of repeat i, Z = sum_i Phi^-1(1 - p_i) / sqrt(k) and p = 1 - Phi(Z), which
  is uniform when every p_i is (independent repeats, each test valid) and whose
  noncentrality grows as sqrt(k) times a repeat's when the misfit is the same in every repeat
  (Stouffer et al. 1949, "The American Soldier" vol. 1; Whitlock 2005, J. Evol. Biol. 18,
  1368). The tests are then joined by the same weighted Bonferroni as for one record
  (``lack_of_fit_levels``): the joint fit is adequate when no combined p is below its share
  of alpha. Stouffer's Z is N(0, 1) only when each repeat's p-value is uniform under the
  null: one p-value far too small flags the set alone (a pure AD record whose shape test
  took a 1/f component at its REML bound as known, df 228, gave p = 1.5e-8 and flagged its
  triple); the lack-of-fit tests therefore keep such a component's sampling variance in their
  df (``likelihood._reml_information_inverse``), and the joint test's size on pure repeats is
  measured by ``benchmarks/rtd_repeat_size.py`` (docs/rtd.md).
- **Pooled estimates.** A parameter or derived quantity estimated in each repeat with standard
  error s_i is pooled by inverse variance with a between-repeat variance (run-to-run variation
  of a real line, which three repeats cannot rule out): w_i = 1 / s_i^2, Cochran's
  Q = sum w_i (theta_i - theta_FE)^2 ~ chi2_{k-1} when the repeats agree (Cochran 1954,
  Biometrics 10, 101), tau^2 = max(0, (Q - (k - 1)) / (S1 - S2 / S1)), S1 = sum w_i,
  S2 = sum w_i^2 (DerSimonian & Laird 1986, Control. Clin. Trials 7, 177), w*_i = 1 / (s_i^2 +
  tau^2), theta = sum w*_i theta_i / sum w*_i, and the interval theta +/- t_{k-1} SE with
  SE^2 = sum w*_i (theta_i - theta)^2 / ((k - 1) sum w*_i) (Hartung & Knapp 2001, Stat. Med.
  20, 3875): it covers with or without a run-to-run variation, where the fixed-effect interval
  (SE = S1^-1/2) covered 81 % of the unit test's draws with a variation (34 % of those whose
  Q missed it). A Q that rejects at ``HETEROGENEITY_ALPHA`` is a warning: the repeats disagree.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats

from .likelihood import LACK_OF_FIT_ALPHA, LackOfFit, lack_of_fit_levels, weighted_bonferroni

__all__ = [
    "HETEROGENEITY_ALPHA",
    "JointLackOfFit",
    "Pooled",
    "TEST_FAMILIES",
    "combine_repeat_tests",
    "joint_lack_of_fit",
    "pool",
    "pool_estimates",
    "stouffer",
]

#: level of Cochran's Q at which the repeats are taken to disagree (random-effects interval)
HETEROGENEITY_ALPHA = 0.05
#: p-values are clipped to [P_FLOOR, 1 - P_FLOOR] before the normal quantile (a Monte Carlo
#: p of 0 or an F test's p of 1 would give an infinite z)
P_FLOOR = 1e-15


def stouffer(p_values: ArrayLike) -> float | NDArray[np.float64]:
    """Stouffer's combined one-sided p-value of independent tests:
    Z = sum_i Phi^-1(1 - p_i) / sqrt(k), p = 1 - Phi(Z) (module docstring). A 2-D array
    combines each row (k = its length)."""
    p = np.clip(np.asarray(p_values, dtype=float), P_FLOOR, 1.0 - P_FLOOR)
    if p.size == 0:
        raise ValueError("p_values must not be empty")
    z = np.sum(stats.norm.isf(p), axis=-1) / math.sqrt(p.shape[-1])
    out = stats.norm.sf(z)
    return float(out) if np.ndim(out) == 0 else out


@dataclass(frozen=True)
class JointLackOfFit:
    """The lack-of-fit tests of one model combined over repeats (module docstring)."""

    per_repeat: dict[str, tuple[float, ...]]
    """each test's p-value in each repeat"""
    combined: dict[str, float]
    """each test's Stouffer p-value"""
    alpha: float

    @classmethod
    def from_p_values(
        cls, per_repeat: Mapping[str, Sequence[float]], alpha: float = LACK_OF_FIT_ALPHA
    ) -> JointLackOfFit:
        """From each test's p-values in the repeats (test name -> one p per repeat)."""
        per = {k: tuple(float(p) for p in v) for k, v in per_repeat.items()}
        return cls(per, {k: float(stouffer(v)) for k, v in per.items()}, alpha)

    @property
    def levels(self) -> dict[str, float]:
        return lack_of_fit_levels(list(self.combined), self.alpha)

    @property
    def p_value(self) -> float:
        """min_i p_i alpha / level_i (weighted Bonferroni, as for one record)."""
        return weighted_bonferroni(self.combined, self.alpha)[0]

    @property
    def adequate(self) -> bool:
        return bool(self.p_value >= self.alpha)

    @property
    def worst(self) -> str | None:
        """The test with the smallest combined p relative to its level."""
        return weighted_bonferroni(self.combined, self.alpha)[1]

    def as_dict(self) -> dict:
        return {
            "adequate": self.adequate,
            "p_value": self.p_value,
            "alpha": self.alpha,
            "levels": self.levels,
            "method": "each test combined over the repeats by Stouffer's method, then "
            "weighted Bonferroni across tests",
            "tests": {
                k: {"p_value": self.combined[k], "per_repeat": list(self.per_repeat[k])}
                for k in self.combined
            },
        }


#: tests of one alternative under two names: a repeat whose exchange extension did not fit in
#: time keeps the linearised tail test (``rtd.likelihood``); both test AD against a stagnant
#: tail and are combined as one
TEST_FAMILIES = {"tail": "exchange"}


def combine_repeat_tests(
    per_repeat: Sequence[Mapping[str, float]], alpha: float = LACK_OF_FIT_ALPHA
) -> JointLackOfFit:
    """Combine the lack-of-fit p-values of each repeat (``per_repeat[i][test] = p``): tests of
    one family (``TEST_FAMILIES``) count as one, named as the majority of the repeats name it
    (ties: the exchange test); a test missing from a repeat is left out of the joint verdict."""
    if not per_repeat:
        raise ValueError("per_repeat must hold the tests of at least one repeat")
    fam: list[dict[str, tuple[str, float]]] = [
        {TEST_FAMILIES.get(k, k): (k, float(v)) for k, v in tests.items()} for tests in per_repeat
    ]
    per: dict[str, tuple[float, ...]] = {}
    for key in fam[0]:
        if all(key in f for f in fam):
            names = [f[key][0] for f in fam]
            name = max(sorted(set(names), key=lambda n: n != key), key=names.count)
            per[name] = tuple(f[key][1] for f in fam)
    return JointLackOfFit.from_p_values(per, alpha)


def joint_lack_of_fit(
    tests: Sequence[LackOfFit], alpha: float = LACK_OF_FIT_ALPHA
) -> JointLackOfFit:
    """Combine the lack-of-fit tests of one model fitted to each repeat (module docstring;
    :func:`combine_repeat_tests`)."""
    if not tests:
        raise ValueError("tests must hold the lack of fit of at least one repeat")
    return combine_repeat_tests([{x.name: x.p_value for x in lof.tests} for lof in tests], alpha)


@dataclass(frozen=True)
class Pooled:
    """An estimate pooled over repeats (module docstring)."""

    value: float
    stderr: float
    ci: tuple[float, float]
    q: float
    """Cochran's Q"""
    q_p: float
    tau2: float
    """between-repeat variance (0 when the repeats agree)"""
    values: tuple[float, ...]
    stderrs: tuple[float, ...]

    @property
    def agree(self) -> bool:
        return bool(self.q_p >= HETEROGENEITY_ALPHA)

    def as_dict(self) -> dict:
        return {
            "value": self.value,
            "stderr": self.stderr,
            "ci": [self.ci[0], self.ci[1]],
            "repeats_agree": self.agree,
            "cochran_q": self.q,
            "cochran_p": self.q_p,
            "between_repeat_var": self.tau2,
            "per_repeat": [[v, s] for v, s in zip(self.values, self.stderrs)],
        }


def pool(values: Sequence[float], stderrs: Sequence[float], confidence: float = 0.95) -> Pooled:
    """Pooled estimate with Cochran's Q, the DerSimonian-Laird between-repeat variance and the
    Hartung-Knapp t interval (module docstring)."""
    x = np.asarray(values, dtype=float)
    s = np.asarray(stderrs, dtype=float)
    if x.size == 0 or x.size != s.size:
        raise ValueError(f"values and stderrs must have the same non-zero length, got {x.size}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(s)) and np.all(s > 0)):
        raise ValueError(f"stderrs must be finite and > 0, got {s.tolist()}")
    w = 1.0 / s**2
    mean = float(np.sum(w * x) / np.sum(w))
    k = x.size
    q = float(np.sum(w * (x - mean) ** 2))
    q_p = float(stats.chi2.sf(q, k - 1)) if k > 1 else 1.0
    level = 0.5 + confidence / 2
    if k == 1:
        se = float(s[0])
        return Pooled(mean, se, (mean - stats.norm.ppf(level) * se, mean + stats.norm.ppf(level) *
                      se), q, q_p, 0.0, tuple(x), tuple(s))  # fmt: skip
    s1, s2 = float(np.sum(w)), float(np.sum(w**2))
    tau2 = max(0.0, (q - (k - 1)) / (s1 - s2 / s1))
    w = 1.0 / (s**2 + tau2)
    mean = float(np.sum(w * x) / np.sum(w))
    # Hartung-Knapp: the weighted residual variance scales the SE, t with k - 1 df
    se = math.sqrt(float(np.sum(w * (x - mean) ** 2)) / ((k - 1) * float(np.sum(w))))
    half = float(stats.t.ppf(level, k - 1)) * se
    return Pooled(mean, se, (mean - half, mean + half), q, q_p, tau2, tuple(x), tuple(s))


def pool_estimates(estimates: Sequence[Mapping[str, tuple[float, float]]]) -> dict[str, Pooled]:
    """Pool every quantity present in all repeats; ``estimates[i][name] = (value, stderr)``."""
    if not estimates:
        return {}
    names = [k for k in estimates[0] if all(k in e for e in estimates)]
    out = {}
    for name in names:
        vals = [e[name][0] for e in estimates]
        ses = [e[name][1] for e in estimates]
        if all(np.isfinite(v) and np.isfinite(se) and se > 0 for v, se in zip(vals, ses)):
            out[name] = pool(vals, ses)
    return out
