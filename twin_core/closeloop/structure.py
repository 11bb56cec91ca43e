"""Structure beyond the candidate library: what the library left in the residual.

``find_structure(data, model, train=, heldout=, noise=)`` searches the residual of ``model``
(the declared model, or the one augmented by the library's identification) for

- ``parameter_dependence`` (``structure_params``): a model parameter that changes with the
  throughput, a screw speed or the time, refitted on windows grouped by them;
- ``periodic`` (``structure_periodic``): sinusoids (multitaper harmonic F-test against the
  local, 1/f-shaped background), with the input they are coherent with;
- ``kernel_correction`` (``structure_kernel``): a regularised non-negative kernel replacing the
  declared blender E(t), its shape compared with E(t).

Every finding is empirical (``empirical=True``: a description usable for prediction, not a
mechanism) and has passed the evidence rules of ``structure_base``: a training-window search
statistic under the declared coloured noise, and the held-out likelihood-ratio test with a
held-out improvement margin. When several searches report, they are accepted in order of their
held-out z and each later one must still pass on the residual left by those accepted before it
(so two descriptions of the same structure are not both reported).

Validation cases generated independently of these searches are in ``structure_cases``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from twin_core.closeloop.data import RunData
from twin_core.closeloop.structure_base import (
    KINDS,
    ResidualContext,
    StructureFinding,
    StructureKind,
    StructureOptions,
    heldout_evidence,
    residual_context,
)
from twin_core.closeloop.structure_kernel import find_kernel_correction
from twin_core.closeloop.structure_params import find_parameter_dependence
from twin_core.closeloop.structure_periodic import find_periodic
from twin_core.plant.model import LineModel

__all__ = [
    "KINDS",
    "SEARCHES",
    "StructureFinding",
    "StructureKind",
    "StructureOptions",
    "find_structure",
]

Search = Callable[[ResidualContext, StructureOptions, np.ndarray], list[StructureFinding]]

#: the searches by kind
SEARCHES: dict[str, Search] = {
    "parameter_dependence": find_parameter_dependence,
    "periodic": find_periodic,
    "kernel_correction": find_kernel_correction,
}


def _accept_jointly(
    ctx: ResidualContext, found: list[StructureFinding], opt: StructureOptions
) -> list[StructureFinding]:
    """Findings in order of held-out z; each after the first must pass the held-out test on
    the residual left by the corrections accepted before it."""
    order = sorted(found, key=lambda f: -f.evidence.get("heldout_z", 0.0))
    accepted: list[StructureFinding] = []
    left = ctx.resid.copy()
    for f in order:
        delta = f.correction(ctx.data, ctx.model)
        if delta is None:
            continue
        if accepted:
            ev = heldout_evidence(ctx, delta, opt.heldout_level(f.kind), opt.min_improvement, left)
            if not ev.passed:
                continue
        accepted.append(f)
        left = left - np.where(ctx.finite, delta, 0.0)
    return accepted


def find_structure(
    data: RunData,
    model: LineModel,
    *,
    train: np.ndarray,
    heldout: np.ndarray,
    noise: Any = None,
    options: StructureOptions | None = None,
) -> list[StructureFinding]:
    """Only structure with evidence against the declared (or estimated) coloured noise.

    ``model``: the model after the library's identification (structure is searched in what the
    library left); ``train`` / ``heldout``: boolean masks over ``data.t_s`` (disjoint);
    ``noise``: the NIR noise to test against (``schemas.line.NIRNoise``, a
    ``twin_core.closeloop.noise.NoiseEstimate``, or None for the model's declared noise).
    Returns the findings accepted (see module), strongest first.
    """
    opt = options or StructureOptions()
    ctx = residual_context(data, model, train, heldout, noise)
    found: list[StructureFinding] = []
    for kind in opt.kinds:
        found += SEARCHES[kind](ctx, opt, ctx.resid)
    return _accept_jointly(ctx, found, opt)
