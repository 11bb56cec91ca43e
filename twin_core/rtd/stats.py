"""Statistics across repeats: one-way ANOVA and Tukey HSD grouping letters (seed Table 6.2).

ANOVA: scipy.stats.f_oneway; pairwise comparisons: scipy.stats.tukey_hsd (Tukey 1949); the
compact letter display by the insert-absorb algorithm (Piepho 2004, J. Comput. Graph. Stat.
13, 456): groups sharing a letter are not significantly different at level alpha. Letters are
assigned in the order the groups are given (the first group gets "A").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats

__all__ = ["GroupComparison", "compare_groups", "letters_from_pvalues"]


@dataclass
class GroupComparison:
    labels: list[str]
    means: list[float]
    stds: list[float]
    f_stat: float
    p_anova: float
    p_pairs: NDArray[np.float64]
    letters: list[str]

    def as_rows(self) -> list[dict]:
        return [
            {"group": g, "mean": m, "std": s, "letters": le}
            for g, m, s, le in zip(self.labels, self.means, self.stds, self.letters)
        ]


def letters_from_pvalues(p: ArrayLike, alpha: float = 0.05) -> list[str]:
    """Compact letter display from a symmetric matrix of pairwise p-values."""
    pm = np.asarray(p, dtype=float)
    k = pm.shape[0]
    if pm.shape != (k, k):
        raise ValueError(f"p must be a square matrix, got shape {pm.shape}")
    cols: list[set[int]] = [set(range(k))]
    for i in range(k):
        for j in range(i + 1, k):
            if pm[i, j] < alpha:
                new: list[set[int]] = []
                for c in cols:
                    if i in c and j in c:
                        new.append(c - {i})
                        new.append(c - {j})
                    else:
                        new.append(c)
                # absorb: drop columns contained in another
                uniq: list[set[int]] = []
                for c in sorted(new, key=len, reverse=True):
                    if c and not any(c <= u for u in uniq):
                        uniq.append(c)
                cols = uniq
    cols.sort(key=lambda c: (min(c), -len(c)))
    names = [chr(ord("A") + n) if n < 26 else f"A{n}" for n in range(len(cols))]
    return [" ".join(nm for nm, c in zip(names, cols) if g in c) for g in range(k)]


def compare_groups(groups: dict[str, ArrayLike], alpha: float = 0.05) -> GroupComparison:
    """One-way ANOVA plus Tukey HSD letters for a dict label -> samples (>= 2 each)."""
    labels = list(groups)
    data = [np.asarray(groups[g], dtype=float) for g in labels]
    if len(data) < 2:
        raise ValueError(f"groups must hold >= 2 groups, got {len(data)}")
    for g, d in zip(labels, data):
        if d.size < 2 or not np.all(np.isfinite(d)):
            raise ValueError(f"group {g!r} must hold >= 2 finite values, got {d.size}")
    f, p = stats.f_oneway(*data)
    res = stats.tukey_hsd(*data)
    return GroupComparison(
        labels,
        [float(d.mean()) for d in data],
        [float(d.std(ddof=1)) for d in data],
        float(f),
        float(p),
        res.pvalue,
        letters_from_pvalues(res.pvalue, alpha),
    )
