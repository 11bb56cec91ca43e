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
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from twin_core.closeloop.identify import FitResult, Identification, effect_side, refit

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

    def product_labels(self) -> list[str]:
        """Labels of the product-side reading's effects (empty without one)."""
        return list(self.reading.labels) if self.reading is not None else []


def _best_equivalent(step: FitResult, side: str) -> FitResult | None:
    """The best-scoring equivalent of an accepted step on ``side`` (equivalents are sorted by
    whole-record BIC)."""
    for eq in step.equivalents:
        if effect_side(eq.labels[-1]) == side:
            return eq
    return None


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


def attribute(ident: Identification) -> Attribution:
    """Product-at-risk and the two readings of an identification (module docstring)."""
    if not ident.accepted:
        return Attribution(False, None)
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
