"""Report of ``twin close-loop``: effects found, errors before/after, decision and diagnostics.

Written by ``twin_core.closeloop.CloseLoopResult.to_dict()`` and validated with
:class:`CloseLoopReport` before it is written as JSON. Concentrations are % w/w, times s.

:class:`ModelFinding` is the live twin's message of the same loop run on a window of the bus
(``twin/<line>/closeloop/finding``, published by the closeloop service, adopted by the blender).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, model_validator

from schemas.base import Finite, Ident, Message, NonNegative, StrictModel, Text

__all__ = [
    "CandidateScore",
    "CloseLoopReport",
    "Decision",
    "EffectFound",
    "EffectSpec",
    "ErrorPair",
    "Errors",
    "ModelFinding",
    "ParamEstimate",
    "StructureEntry",
    "Windows",
    "WindowError",
]


class ParamEstimate(StrictModel):
    """A fitted parameter with its standard error and 95 % interval (clipped to bounds)."""

    name: str
    value: Finite
    stderr: NonNegative | None = None
    ci95_low: Finite | None = None
    ci95_high: Finite | None = None
    unit: str
    lower: Finite
    upper: Finite


class EffectFound(StrictModel):
    """An effect claimed: registry name, target feeder (feeder effects), parameters, scores
    of the step that accepted it."""

    name: str
    target: str | None = None
    label: str
    params: list[ParamEstimate]
    delta_bic: Finite | None = None
    heldout_rel_improvement: Finite | None = None
    lr_z: Finite | None = None
    p_value: Finite | None = Field(None, ge=0.0, le=1.0)
    alternatives: list[str] = Field(
        default_factory=list,
        description="other candidates that explain the data about as well (BIC within the "
        "ambiguity margin): not distinguishable with this excitation",
    )


class WindowError(StrictModel):
    rmse: NonNegative
    mae: NonNegative
    n: int = Field(ge=0)


class ErrorPair(StrictModel):
    train: WindowError
    heldout: WindowError


class Errors(StrictModel):
    """RMSE and MAE of measured - predicted (% w/w, Hampel outliers replaced)."""

    before: ErrorPair
    after: ErrorPair


class Windows(StrictModel):
    split: Literal["tail", "blocks"]
    description: str
    train_s: list[Finite] = Field(min_length=2, max_length=2)
    heldout_s: list[Finite] = Field(min_length=2, max_length=2)
    n_train: int = Field(ge=0)
    n_heldout: int = Field(ge=0)


class Decision(StrictModel):
    alpha: float = Field(gt=0.0, lt=1.0)
    min_improvement: Finite
    max_effects: int = Field(ge=0)
    test: str
    unexplained_nmse: Finite
    outliers_removed: int = Field(ge=0)


class CandidateScore(StrictModel):
    """One candidate tried at one step of the forward search."""

    label: str
    params: dict[str, Finite]
    delta_bic: Finite | None = None
    heldout_rel_improvement: Finite | None = None
    lr_z: Finite | None = None
    p_value: Finite | None = None
    dm_stat: Finite | None = None
    dm_p_value: Finite | None = None
    claimable: bool
    converged: bool


class StructureEntry(StrictModel):
    """Structure beyond the candidate library (``twin_core.closeloop.structure``): a parameter
    that changes with the operating point or with time, periodic content in the residual, or
    a corrected blender response. Empirical: a description usable for prediction, found with
    evidence against the declared coloured noise on held-out data, not a named mechanism."""

    kind: Literal["parameter_dependence", "periodic", "kernel_correction"]
    summary: Text = Field(description="one line for a process engineer")
    evidence: dict[str, Finite] = Field(
        default_factory=dict,
        description="statistics and p-values: the training-window search, the held-out "
        "likelihood-ratio z and p, the held-out relative MSE improvement, ...",
    )
    estimates: dict[str, tuple[Finite, Finite, Finite]] = Field(
        default_factory=dict, description="name -> (value, ci95_low, ci95_high)"
    )
    empirical: bool = True
    alternatives: list[str] = Field(
        default_factory=list,
        description="descriptions the data cannot tell apart from this one",
    )

    @model_validator(mode="after")
    def _interval_order(self) -> StructureEntry:
        for name, (v, lo, hi) in self.estimates.items():
            if not lo <= v <= hi:
                raise ValueError(
                    f"estimates.{name} must satisfy ci95_low <= value <= ci95_high, got "
                    f"({v}, {lo}, {hi})"
                )
        return self


class CloseLoopReport(StrictModel):
    """The close-loop report (JSON)."""

    version: int = 1
    recording: str
    line: str
    sensor_component: str
    status: Literal["explained", "unexplained", "consistent"] = Field(
        description="explained: effects claimed; unexplained: residual beyond the declared "
        "noise but no effect passes the test; consistent: residual explained by the noise"
    )
    effects: list[EffectFound]
    errors: Errors
    windows: Windows
    decision: Decision
    candidates: list[list[CandidateScore]]
    diagnostics_before: dict[str, Any]
    diagnostics_after: dict[str, Any]
    augmented_model: dict[str, Any]
    n_model_evaluations: int = Field(ge=0)
    figures: list[str] = Field(default_factory=list)
    noise: dict[str, Any] = Field(
        default_factory=dict,
        description="NIR noise used by the decisions: source 'declared' or 'estimated' "
        "(twin_core.closeloop.noise) and its white_sd, pink_sd, proportional_rel",
    )


class EffectSpec(StrictModel):
    """An effect of a line model in dict form (``twin_core.plant.effects.make_effect``)."""

    name: Ident = Field(description="effect name, a key of twin_core.plant.effects.EFFECTS")
    target: Ident | None = Field(None, description="feeder a feeder-stage effect acts on")
    params: dict[Ident, Finite] = Field(default_factory=dict, description="parameter values")


class ModelFinding(Message):
    """What the online close-loop found on one window. Key: ``twin/<line>/closeloop/finding``.

    ``status``: as :class:`CloseLoopReport`; ``effects``: the effects claimed on this window
    (parameters with standard errors); ``model_effects``: every effect of the model after this
    window (the ones adopted before plus the new ones: what the blender adopts);
    ``errors``: RMSE / MAE of the model before and after, on the window's training and held-out
    parts.
    """

    SIGNAL = "finding"

    finding_id: Ident = Field(description="unique id: <line>.closeloop-<window end, ms>")
    status: Literal["explained", "unexplained", "consistent"]
    t_start_s: NonNegative = Field(description="window start, plant time, s")
    t_end_s: NonNegative = Field(description="window end, plant time, s")
    effects: list[EffectFound] = Field(default_factory=list)
    model_effects: list[EffectSpec] = Field(default_factory=list)
    errors: Errors
