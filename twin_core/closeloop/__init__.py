"""Close the loop: residuals, candidate effects, identification, before/after reports.

- ``data``: :class:`RunData` (arrays of a recording), training / held-out splits, event
  markers; outliers of the NIR record are removed by the project's one Hampel filter,
  ``twin_core.rtd.outliers.hampel`` (``variant="pearson"``: NaN gaps kept);
- ``diagnostics``: residual bias, trend, autocorrelation, spectrum, cross-correlation with
  inputs and events, pulse fronts and tails;
- ``effects``: the candidate-effect registry (:data:`EFFECTS`, defined in
  ``twin_core.plant.effects`` because the plant simulator injects the same effects);
- ``identify``: fit / select / test (BIC, held-out error, held-out likelihood-ratio test);
- ``report``: :func:`close_loop` -> :class:`CloseLoopResult` (``to_dict()`` is the JSON report),
  :func:`online_finding` for a window of the live twin;
- ``scenarios``: the standard excitation scenario and effect magnitudes used for validation.
"""

from twin_core.closeloop.data import RunData, Split, make_split
from twin_core.closeloop.diagnostics import pulse_responses, residual_diagnostics
from twin_core.closeloop.identify import (
    Candidate,
    Identification,
    IdentifyOptions,
    candidate_list,
    dm_test,
    heldout_lr_test,
    identify,
)
from twin_core.closeloop.report import CloseLoopResult, Finding, close_loop, online_finding
from twin_core.plant.effects import EFFECTS, Effect, ParamSpec, make_effect, register

__all__ = [
    "EFFECTS",
    "Candidate",
    "CloseLoopResult",
    "Effect",
    "Finding",
    "Identification",
    "IdentifyOptions",
    "ParamSpec",
    "RunData",
    "Split",
    "candidate_list",
    "close_loop",
    "dm_test",
    "heldout_lr_test",
    "identify",
    "make_effect",
    "make_split",
    "online_finding",
    "pulse_responses",
    "register",
    "residual_diagnostics",
]
