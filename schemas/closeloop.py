"""Report of ``twin close-loop``: data quality, effects found with the explanations the data
cannot tell apart, the product-safe reading, errors before/after, decision and diagnostics.

Written by ``twin_core.closeloop.CloseLoopResult.to_dict()`` and validated with
:class:`CloseLoopReport` before it is written as JSON. Concentrations are % w/w, times s.

:class:`ModelFinding` is the live twin's message of the same loop run on a window of the bus
(``twin/<line>/closeloop/finding``, published by the closeloop service, adopted by the blender,
acted on by the diverter).

Report version 2 (contract 1.3): ``status`` has five values; ``data_quality``,
``product_at_risk``, ``product_reading``, ``discriminating_measurement``, ``structure``,
``remaining`` and ``noise_tests`` are new; every effect lists its ``equivalents`` and ``side``;
``decision`` has ``noise_alpha`` and ``ambiguity_bic`` instead of ``unexplained_nmse``.
Report version 3 (contract 1.4): ``possible_explanations`` (an ``unexplained`` record's
candidates that the data supports without a claim; ``product_at_risk`` counts them).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, model_validator

from schemas.base import Finite, Ident, Message, NonNegative, StrictModel, Text

__all__ = [
    "CandidateScore",
    "ClockOffsetEstimate",
    "CloseLoopReport",
    "DataQualityFlag",
    "Decision",
    "DiscriminatingMeasurement",
    "EffectFound",
    "EffectSpec",
    "Equivalent",
    "PossibleExplanation",
    "ErrorPair",
    "Errors",
    "MeasurementOption",
    "ModelFinding",
    "ParamEstimate",
    "ProductReading",
    "Status",
    "StructureEntry",
    "Windows",
    "WindowError",
]

#: explained: effects claimed and the rest is the noise; partly_explained: effects claimed, the
#: rest is not the noise (``remaining`` says what); unexplained: beyond the noise, no effect
#: passes the test; consistent: the declared model's residual is the noise; data_quality: data
#: faults were flagged and left out, and the rest is the noise
Status = Literal["consistent", "explained", "partly_explained", "unexplained", "data_quality"]

Side = Literal["probe", "product"]


class EffectSpec(StrictModel):
    """An effect of a line model in dict form (``twin_core.plant.effects.make_effect``)."""

    name: Ident = Field(description="effect name, a key of twin_core.plant.effects.EFFECTS")
    target: Ident | None = Field(None, description="feeder (or component, unit stage) it acts on")
    params: dict[Ident, Finite] = Field(default_factory=dict, description="parameter values")


class DataQualityFlag(StrictModel):
    """A data fault found before the fit (``twin_core.closeloop.quality``; ``action``
    ``left_out``: its samples were left out of the identification), or the timing of the
    plant's messages repaired or noted (``repaired`` / ``noted``: a refill's hold, missing or
    re-sent ticks, jitter, irregular sampling, a clock offset; no fault, the status is not
    ``data_quality`` for them)."""

    kind: Literal[
        "stuck",
        "clipping",
        "spike_burst",
        "gap",
        "time_jump",
        "duplicate_stamp",
        "refill_hold",
        "missing_tick",
        "duplicate_tick",
        "jitter",
        "irregular_sampling",
        "clock_offset",
    ]
    series: str = Field(description="nir or <feeder>:flow")
    t_start_s: Finite
    t_end_s: Finite
    n_samples: int = Field(ge=0)
    detail: str = Field("", description="what was seen there (values, lengths, stamps)")
    action: Literal["left_out", "repaired", "noted"] = "left_out"


class ClockOffsetEstimate(StrictModel):
    """A source whose clock is off the record's common clock, estimated from the arrival order
    of the messages (``twin_core.closeloop.quality.estimate_clock_offsets``) and corrected by
    the record: stamps minus true times, s, with the interval the arrival order allows."""

    series: str
    offset_s: Finite
    low_s: Finite
    high_s: Finite
    n_messages: int = Field(ge=0)
    reference: str = Field(description="the stream whose clock the others share")
    applied: bool = True


class _Explanation(StrictModel):
    """An alternative explanation: the effect (label, name, target, side, parameters) and its
    held-out scores."""

    label: str
    name: str
    target: str | None = None
    side: Side
    params: dict[str, Finite]
    heldout_rel_improvement: Finite | None = None
    p_value: Finite | None = Field(None, ge=0.0, le=1.0)


class Equivalent(_Explanation):
    """An explanation the data cannot tell from the effect it is listed with: whole-record BIC
    within the ambiguity margin (the cross-side margin for the other side of the probe),
    held-out error lowered by the margin too."""

    delta_bic: Finite = Field(description="its whole-record BIC minus the effect's")


class PossibleExplanation(_Explanation):
    """Without a claim, a candidate that passes the statistical part of the claim test on what
    is left (training BIC below the declared model's, held-out likelihood-ratio p-value below
    the Bonferroni level) but not the practical margin: supported by the data, not claimed."""

    delta_bic: Finite = Field(description="its training BIC minus the declared model's")
    lr_z: Finite | None = None


class MeasurementOption(StrictModel):
    """An experiment at its chosen size and its predicted power to separate two readings."""

    kind: Literal["assay", "tracer_pulse", "setpoint_step"]
    size: Finite
    unit: str
    power: float = Field(ge=0.0, le=1.0)
    expected_log_lr: NonNegative
    text: str


class DiscriminatingMeasurement(MeasurementOption):
    """The recommended measurement (``twin_core.closeloop.discriminate``, Box & Hill 1967),
    the two readings it separates and every option considered."""

    between: list[str] = Field(default_factory=list)
    options: list[MeasurementOption] = Field(default_factory=list)


class ProductReading(StrictModel):
    """The product-side reading of a finding whose explanations span both sides of the probe:
    the model the twin acts on, and its outlet over the window."""

    effects: list[EffectSpec] = Field(description="effects added to the declared model")
    labels: list[str]
    outlet_mean_pct_w_w: Finite
    outlet_min_pct_w_w: Finite
    outlet_max_pct_w_w: Finite
    t_start_s: Finite
    t_end_s: Finite
    out_of_spec_s: list[tuple[Finite, Finite]] | None = Field(
        None,
        description="[first, last] plant times (s) of each stretch this reading puts outside "
        "the specification (what the diverter diverts); None: not computed (the whole window "
        "is diverted when the outlet range leaves the specification)",
    )


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
    side: Side = "product"
    alternatives: list[str] = Field(
        default_factory=list,
        description="labels of the equivalents: candidates that explain the data about as "
        "well, not distinguishable with this excitation",
    )
    equivalents: list[Equivalent] = Field(default_factory=list)


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
    noise_alpha: float = Field(gt=0.0, lt=1.0)
    ambiguity_bic: NonNegative
    outliers_removed: int = Field(ge=0)
    samples_left_out: int = Field(0, ge=0, description="flagged by the data-quality check")


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


class CloseLoopReport(StrictModel):
    """The close-loop report (JSON)."""

    version: int = 3
    recording: str
    line: str
    sensor_component: str
    status: Status = Field(description="see schemas.closeloop.Status")
    data_quality: list[DataQualityFlag] = Field(default_factory=list)
    clock_offsets: list[ClockOffsetEstimate] = Field(
        default_factory=list, description="sources put back on the common clock"
    )
    effects: list[EffectFound]
    possible_explanations: list[PossibleExplanation] = Field(
        default_factory=list,
        description="status unexplained: candidates the data supports but that are not claimed",
    )
    product_at_risk: bool = Field(
        False,
        description="a probe-side and a product-side explanation (claimed with its equivalents, "
        "or among the possible explanations) are both consistent with the data: the product "
        "may be off target; the twin acts on product_reading",
    )
    product_reading: ProductReading | None = None
    discriminating_measurement: DiscriminatingMeasurement | None = None
    structure: list[StructureEntry] = Field(default_factory=list)
    remaining: str = Field("", description="what the model leaves unexplained, in words")
    noise_tests: dict[str, Any] = Field(
        default_factory=dict, description="innovation tests behind the status"
    )
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
    timing_s: dict[str, NonNegative] = Field(
        default_factory=dict,
        description="CPU seconds of the analysis: data quality, fits, tests, attribution "
        "(equivalents, product reading, discriminating design), structure, diagnostics",
    )


class ModelFinding(Message):
    """What the online close-loop found on one window. Key: ``twin/<line>/closeloop/finding``.

    ``status``, ``data_quality``, ``product_at_risk``, ``product_reading``,
    ``discriminating_measurement``, ``structure``, ``remaining``: as :class:`CloseLoopReport`;
    ``effects``: the effects claimed on this window (parameters with standard errors and their
    equivalents); ``model_effects``: every effect of the model after this window (the ones
    adopted before plus the new ones; the product-side reading when the product is at risk:
    what the blender adopts); ``errors``: RMSE / MAE of the model before and after, on the
    window's training and held-out parts. The diverter diverts the window when the product is
    at risk and the product-side outlet leaves the specification.
    """

    SIGNAL = "finding"

    finding_id: Ident = Field(description="unique id: <line>.closeloop-<window end, ms>")
    status: Status
    t_start_s: NonNegative = Field(description="window start, plant time, s")
    t_end_s: NonNegative = Field(description="window end, plant time, s")
    data_quality: list[DataQualityFlag] = Field(default_factory=list)
    effects: list[EffectFound] = Field(default_factory=list)
    possible_explanations: list[PossibleExplanation] = Field(default_factory=list)
    model_effects: list[EffectSpec] = Field(default_factory=list)
    product_at_risk: bool = False
    product_reading: ProductReading | None = None
    discriminating_measurement: DiscriminatingMeasurement | None = None
    structure: list[StructureEntry] = Field(default_factory=list)
    remaining: str = ""
    errors: Errors
    applies_from_s: NonNegative | None = Field(
        default=None,
        description="plant time from which the twin adopts this finding's model: t_end_s plus "
        "blender.adoption_delay_s (None, contract < 1.5: t + blender.adoption_delay_s)",
    )
