"""Product-safe attribution: which side of the probe an explanation puts the fault on.

An effect on the product side (feeder, blender, unit: ``Effect.side == "product"``) changes
what leaves the line; one on the probe side (sensor) changes only the reading. When the data
cannot tell them apart -- a finding's effect and its equivalent explanations
(``twin_core.closeloop.identify``: within the BIC margin on the whole record and lowering the
held-out error by the margin too) hold both sides -- the product may be off target although the
probe-side reading says it is fine: ``product_at_risk``. The twin then acts on the
**product-side reading**: the model in which each probe-side effect of the finding is replaced
by its best product-side equivalent (refitted jointly on the training window); its outlet is
what the diverter checks against the specification, and the blender adopts it.

Without a claim the same question is asked of what is left: when the status is
``unexplained`` (the declared model's innovations fail the noise tests), the candidates of the
first step that pass every statistical part of the claim test (training BIC
below the declared model's, held-out likelihood-ratio p-value below the step's Bonferroni level)
but fall short of the practical margin ``min_improvement`` are the **possible explanations**:
not claimed (the margin guards against slow noise), but the data supports them. Those within
``ambiguity_bic`` of the best are listed; when they hold both sides the product is at risk just
the same, the twin acts on the best product-side one, and the discriminating measurement is
designed between the best of each side. A residual the library cannot name is never read as
"the product is fine" when a product-side reading fits it as well as a probe-side one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from twin_core.closeloop.identify import FitResult, Identification, effect_side, refit
from twin_core.closeloop.quality import true_runs

__all__ = ["Attribution", "attribute"]


@dataclass
class Attribution:
    """Sides of a finding's explanations and its two readings (module docstring).

    ``reading``: the product-side fit and ``probe_reading`` the probe-side one (both set when
    the product is at risk; one of them is the identification's final fit); ``groups``: per
    accepted effect, the labels of the explanations the data cannot tell apart (the effect
    first).
    """

    product_at_risk: bool
    reading: FitResult | None
    probe_reading: FitResult | None = None
    groups: list[list[str]] = field(default_factory=list)
    #: without a claim: the possible explanations of what is left, best first (docstring)
    possible: list[FitResult] = field(default_factory=list)

    def product_labels(self) -> list[str]:
        """Labels of the product-side reading's effects (empty without one)."""
        return list(self.reading.labels) if self.reading is not None else []


def _best_on(fits: list[FitResult], side: str) -> FitResult | None:
    """The first of ``fits`` (sorted best first) whose last effect is on ``side``."""
    return next((f for f in fits if effect_side(f.labels[-1]) == side), None)


def _best_equivalent(step: FitResult, side: str) -> FitResult | None:
    """The best-scoring equivalent of an accepted step on ``side`` (equivalents are sorted by
    whole-record BIC)."""
    return _best_on(step.equivalents, side)


def side_reading(ident: Identification, side: str) -> FitResult:
    """The final model with each accepted effect not on ``side`` replaced by its best
    equivalent on ``side`` (refitted jointly; the final fit itself when nothing changes)."""
    final = ident.final
    effects, labels = list(final.effects), list(final.labels)
    replaced = False
    for step in ident.accepted:
        label = step.labels[-1]
        if effect_side(label) == side or label not in labels:
            continue
        alt = _best_equivalent(step, side)
        if alt is not None:
            j = labels.index(label)
            effects[j], labels[j] = alt.effects[-1], alt.labels[-1]
            replaced = True
    return refit(ident, effects, labels) if replaced else final


def possible_explanations(ident: Identification) -> list[FitResult]:
    """First-step candidates of an ``unexplained`` identification without a claim that pass
    the statistical part of the claim test, within ``ambiguity_bic`` of the best (whole-record
    BIC), best first (module docstring)."""
    if ident.accepted or ident.status != "unexplained" or not ident.steps:
        return []
    step = ident.steps[0]
    level = ident.options.alpha / max(len(step), 1)
    ok = [
        f
        for f in step
        if f.converged and f.delta_bic < 0 and f.p_value < level and f.rel_improvement > 0
    ]
    if not ok:
        return []
    best = min(f.bic_all for f in ok)
    near = [f for f in ok if f.bic_all - best <= ident.options.ambiguity_bic]
    return sorted(near, key=lambda f: f.bic_all)


def attribute(ident: Identification) -> Attribution:
    """Product-at-risk and the two readings of an identification (module docstring)."""
    if not ident.accepted:
        possible = possible_explanations(ident)
        product, probe = _best_on(possible, "product"), _best_on(possible, "probe")
        if product is None or probe is None:
            return Attribution(False, None, possible=possible)
        groups = [[f.labels[-1] for f in possible]]
        return Attribution(True, product, probe, groups, possible)
    groups = [[step.labels[-1], *step.alternatives] for step in ident.accepted]
    at_risk = any({effect_side(lab) for lab in g} == {"probe", "product"} for g in groups)
    if not at_risk:
        return Attribution(False, None, None, groups)
    return Attribution(True, side_reading(ident, "product"), side_reading(ident, "probe"), groups)


def outlet_summary(outlet: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """Mean, min and max (% w/w) of an outlet prediction over the samples ``mask``."""
    c = np.asarray(outlet, dtype=float)[mask]
    return {
        "outlet_mean_pct_w_w": float(np.mean(c)),
        "outlet_min_pct_w_w": float(np.min(c)),
        "outlet_max_pct_w_w": float(np.max(c)),
    }


def out_of_spec_spans(
    t_s: np.ndarray, outlet: np.ndarray, lower: float, upper: float
) -> list[tuple[float, float]]:
    """[first, last] plant times (s) of each stretch where ``outlet`` (% w/w) is outside
    [lower, upper]: the part of a window whose product a product-side reading puts out of
    specification."""
    c = np.asarray(outlet, dtype=float)
    t = np.asarray(t_s, dtype=float)
    return [(float(t[a]), float(t[b - 1])) for a, b in true_runs((c < lower) | (c > upper))]
