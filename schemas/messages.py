"""Messages on the twin's bus (the wire contract).

Each model documents its key expression (``twin/<line>/<unit>/<id>/<signal>``, see
:mod:`schemas.keys`), carries ``t`` (plant time, s) and ``seq`` (per-publisher counter) and declares
units in field names. Payloads are the compact JSON of the model (``Message.to_json_bytes``).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, StringConstraints, model_validator

from schemas.base import Finite, Fraction, Ident, Message, NonNegative, Positive, Text
from schemas.blender_model import BlenderModel

#: quality flag of a measurement: ``good``; ``suspect`` (e.g. flagged outlier, out of calibration
#: range); ``bad`` (sensor fault: the value must not be used)
Quality = Literal["good", "suspect", "bad"]


class FeederFlow(Message):
    """State of one loss-in-weight feeder. Key: ``twin/<line>/feeder/<feeder_id>/flow``."""

    SIGNAL = "flow"

    component: Ident = Field(description="material fed, e.g. 'api' or 'excipient'")
    mass_flow_kg_h: NonNegative = Field(description="measured mass flow, kg/h")
    setpoint_kg_h: NonNegative | None = Field(default=None, description="flow set point, kg/h")
    screw_speed_rpm: NonNegative = Field(description="screw speed, rev/min")
    hopper_mass_kg: NonNegative = Field(description="material in the hopper, kg")
    feed_factor_g_rev: NonNegative = Field(description="feed factor, g/rev")
    refilling: bool = Field(default=False, description="True while the hopper is being refilled")


class MeasuredConcentration(Message):
    """A PAT (e.g. NIR) measurement. Key: ``twin/<line>/pat/<sensor>/concentration``.

    ``concentration_pct_w_w`` may be slightly negative: a calibrated NIR baseline carries noise
    around zero.
    """

    SIGNAL = "concentration"

    sensor: Ident = Field(description="sensor id, e.g. 'nir1'")
    component: Ident = Field(description="component measured, e.g. 'api'")
    concentration_pct_w_w: Finite = Field(description="concentration, % w/w")
    quality: Quality = Field(default="good", description="quality flag")


#: a model version: the first 16 hex digits of a SHA-256 content hash
ModelVersion = Annotated[str, StringConstraints(pattern=r"^[0-9a-f]{16}$")]


class PredictedConcentration(Message):
    """A model prediction of concentration. Key: ``twin/<line>/blender/<location>/predicted``."""

    SIGNAL = "predicted"

    model: Ident = Field(description="predicting model, e.g. 'rtd' or 'compartment'")
    component: Ident = Field(description="component predicted")
    concentration_pct_w_w: Finite = Field(description="predicted concentration, % w/w")
    lower_pct_w_w: Finite | None = Field(default=None, description="lower prediction bound")
    upper_pct_w_w: Finite | None = Field(default=None, description="upper prediction bound")
    model_version: ModelVersion | None = Field(
        default=None,
        description="content hash of the model the value was computed with "
        "(twin_core.online.blender.model_version); absent in older recordings",
    )

    @model_validator(mode="after")
    def _bounds_ordered(self) -> PredictedConcentration:
        lo, hi = self.lower_pct_w_w, self.upper_pct_w_w
        if lo is not None and hi is not None and lo > hi:
            raise ValueError(f"lower_pct_w_w must be <= upper_pct_w_w, got {lo} > {hi}")
        return self


class BlenderDrive(Message):
    """Blade drive of a continuous blender, as the plant reports it. Key:
    ``twin/<line>/blender/<blender_id>/drive``.

    The blender and the diverter predict with the blender model of the reported blade speed
    from ``t`` on (``twin_core.compartment.operating_point``).
    """

    SIGNAL = "drive"

    blade_speed_rpm: NonNegative = Field(description="blade (impeller) speed, rev/min")


class BlenderModelUpdate(Message):
    """A compartment model of the blender section at one blade speed, e.g. built by the dem
    service from a DEM run of the section. Key: ``twin/<line>/blender/<source>/model``.

    The blender and the diverter add it to their table of models (replacing one at the same
    blade speed) from plant time ``t`` on.
    """

    SIGNAL = "model"

    model: BlenderModel = Field(description="the section model (rpm_basis: its blade speed)")
    detail: str = Field(
        default="", max_length=4096, description="how it was made (scene, run, job id)"
    )

    @model_validator(mode="after")
    def _has_rpm(self) -> BlenderModelUpdate:
        if self.model.rpm_basis is None:
            raise ValueError("model.rpm_basis must be given, got None")
        return self


class BlenderModelInUse(Message):
    """The blender model the twin predicts with, announced when it starts and whenever the
    operating point or the table of models changes. Key: ``twin/<line>/blender/outlet/model``.
    """

    SIGNAL = "model_in_use"

    kind: Literal["rtd", "compartment"] = Field(description="RTD model or compartment model")
    name: Text = Field(description="model name, or the compartment models it is built from")
    reason: Literal["start", "blade_speed", "throughput", "new_model", "rtd_estimate"] = Field(
        description="what made the twin switch"
    )
    applies_from_s: NonNegative = Field(description="plant time the model applies from")
    blade_speed_rpm: NonNegative | None = Field(default=None, description="operating point")
    throughput_kg_h: NonNegative | None = Field(default=None, description="operating point")
    mean_residence_time_s: NonNegative = Field(description="mean of the model's E(t), s")
    rule: str = Field(
        default="", max_length=4096, description="how the model was obtained for this point"
    )
    model_version: ModelVersion | None = Field(
        default=None,
        description="content hash of the model the value was computed with "
        "(twin_core.online.blender.model_version); absent in older recordings",
    )


EventKind = Literal[
    "refill_start", "refill_stop", "tracer_pulse", "disturbance", "disturbance_end", "note"
]

#: ``detail`` of the ``note`` Event the virtual plant publishes on ``keys.replay_event(line)``
#: after its last sample, at that sample's plant time (the diverter then closes what is open)
END_OF_STREAM = "end-of-stream"


class Event(Message):
    """A discrete plant event. Key: ``twin/<line>/<unit>/<id>/event``.

    ``tracer_pulse``: ``mass_kg`` of tracer ``component`` injected at ``t``;
    ``refill_start``/``refill_stop``: hopper refill of feeder ``source`` (``lot_id``: the
    raw-material lot the refill adds, contract 1.8; ``mass_kg``: its mass if known);
    ``disturbance``: an injected or observed effect described by ``detail`` (and ``magnitude``).
    """

    SIGNAL = "event"

    kind: EventKind = Field(description="event kind")
    source: Ident = Field(description="unit/id the event belongs to, e.g. 'api' or 'tracer'")
    component: Ident | None = Field(default=None, description="material concerned")
    mass_kg: NonNegative | None = Field(default=None, description="mass involved (pulse, refill)")
    duration_s: NonNegative | None = Field(default=None, description="duration if known, s")
    magnitude: Finite | None = Field(default=None, description="size of a disturbance")
    detail: str = Field(default="", max_length=4096, description="free text")
    lot_id: Ident | None = Field(
        default=None, description="raw-material lot a refill adds (refill events), e.g. 'api-L0003'"
    )


class RtdEstimate(Message):
    """A fitted residence time distribution. Key: ``twin/<line>/rtd/estimate``.

    ``params`` holds the model parameters in SI (e.g. ``tau_d``, ``tau``, ``pe`` for
    axial dispersion), ``stderr`` their standard errors.
    """

    SIGNAL = "estimate"

    model: Ident = Field(description="RTD model, e.g. 'axial_dispersion_open'")
    params: dict[Ident, Finite] = Field(description="parameter estimates (SI)")
    stderr: dict[Ident, NonNegative] = Field(default_factory=dict, description="standard errors")
    mean_residence_time_s: NonNegative = Field(description="mean residence time, s")
    pulse_t_s: NonNegative | None = Field(
        default=None, description="plant time of the tracer pulse"
    )
    n_points: int = Field(default=0, ge=0, description="number of points fitted")
    rmse: NonNegative | None = Field(default=None, description="root-mean-square residual")
    applies_from_s: NonNegative | None = Field(
        default=None,
        description="plant time from which the twin predicts with this estimate: the plant "
        "time of the NIR sample that completed it plus blender.adoption_delay_s (None, contract "
        "< 1.5: t + blender.adoption_delay_s)",
    )

    @model_validator(mode="after")
    def _params_nonempty(self) -> RtdEstimate:
        if not self.params:
            raise ValueError("params must not be empty, got {}")
        return self


class RtdSkipped(Message):
    """A tracer pulse the rtd service found but did not turn into an estimate, and why. Key:
    ``twin/<line>/rtd/skipped``.

    ``reason``: ``fit_failed`` (the fit raised: ``detail`` says why) or ``skipped_disturbance``
    (a pulse found by itself while a known feeder disturbance or refill could reach the outlet).
    """

    SIGNAL = "skipped"

    pulse_t_s: NonNegative = Field(description="plant time of the pulse (or its segment start)")
    reason: Literal["fit_failed", "skipped_disturbance"] = Field(description="why no estimate")
    detail: Text = Field(description="what happened")


class AdoptionProgress(Message):
    """How far a producer of model updates (the rtd or closeloop service) has got. Key:
    ``twin/<line>/<unit>/progress`` (``unit``: ``rtd`` or ``closeloop``).

    ``complete_to_s``: every :class:`RtdEstimate` (or ``ModelFinding``) of this producer whose
    ``applies_from_s`` is <= this plant time has been published. The blender predicts a tick,
    and the diverter decides at a plant time, only once every producer it adopts from has got
    that far, so the adopted model at each plant time, and with it every output, is a function
    of the plant data only (not of machine load or restarts). ``last_update_t_s`` lets them
    tell that no update published before the report is still on its way.
    """

    SIGNAL = "progress"

    complete_to_s: NonNegative = Field(description="updates applying up to here are published")
    last_update_t_s: NonNegative | None = Field(
        default=None,
        description="t of the newest update this publisher published before this report (None: "
        "none since it started): a subscriber counts the report once it has that update (the "
        "bus may deliver the two keys out of order)",
    )


class OosAlert(Message):
    """An out-of-specification episode. Key: ``twin/<line>/oos/alert``.

    ``t_start_s``/``t_end_s``: plant times the concentration left/returned to the limits (at the
    sensor); ``peak_deviation_pct_w_w``: largest signed deviation from target; ``limit_pct_w_w``:
    the allowed absolute deviation.
    """

    SIGNAL = "alert"

    alert_id: Ident = Field(description="unique alert id")
    component: Ident = Field(description="component out of specification")
    t_start_s: NonNegative = Field(description="start of the episode, plant time, s")
    t_end_s: NonNegative = Field(description="end of the episode, plant time, s")
    peak_deviation_pct_w_w: Finite = Field(description="peak deviation from target, % w/w")
    limit_pct_w_w: NonNegative = Field(description="allowed absolute deviation, % w/w")
    cause: Text = Field(description="attributed cause, e.g. 'refill api'")
    model_version: ModelVersion | None = Field(
        default=None,
        description="content hash of the model the value was computed with "
        "(twin_core.online.blender.model_version); absent in older recordings",
    )

    @model_validator(mode="after")
    def _ordered(self) -> OosAlert:
        if self.t_end_s < self.t_start_s:
            raise ValueError(
                f"t_end_s must be >= t_start_s, got t_end_s={self.t_end_s} < {self.t_start_s}"
            )
        return self


class DivertCommand(Message):
    """Command to the diversion gate. Key: ``twin/<line>/divert/command``.

    ``divert`` sends material passing the gate between ``t_start_s`` and ``t_end_s`` (plant time
    at the gate) to waste; ``accept`` cancels a diversion in that window.
    """

    SIGNAL = "command"

    command_id: Ident = Field(description="unique command id")
    action: Literal["divert", "accept"] = Field(description="what to do with the window")
    t_start_s: NonNegative = Field(description="window start at the gate, plant time, s")
    t_end_s: NonNegative = Field(description="window end at the gate, plant time, s")
    alert_id: Ident | None = Field(default=None, description="alert that caused the command")
    reason: Text = Field(description="why")
    model_version: ModelVersion | None = Field(
        default=None,
        description="content hash of the model the value was computed with "
        "(twin_core.online.blender.model_version); absent in older recordings",
    )

    @model_validator(mode="after")
    def _ordered(self) -> DivertCommand:
        if self.t_end_s < self.t_start_s:
            raise ValueError(
                f"t_end_s must be >= t_start_s, got t_end_s={self.t_end_s} < {self.t_start_s}"
            )
        return self


ParamValue = Finite | int | bool | str


#: a job id: an identifier that is a safe file name (no leading ``.``, so neither ``.`` nor
#: ``..``): the dem service keeps a job's files in ``<run dir>/dem/<job_id>``
JobId = Annotated[
    str, StringConstraints(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")
]


class DemJobRequest(Message):
    """Request to run a DEM job. Key: ``twin/<line>/dem/<job_id>/request``."""

    SIGNAL = "request"

    job_id: JobId = Field(description="unique job id (a safe file name)")
    scene: Ident = Field(description="scene to run, e.g. 'drawdown', 'feeder', 'blender_section'")
    params: dict[Ident, ParamValue] = Field(default_factory=dict, description="scene parameters")
    duration_s: Positive = Field(description="simulated time to run, s")
    seed: int | None = Field(default=None, ge=0, description="random seed")


JobState = Literal["queued", "running", "done", "failed", "cancelled"]


class DemJobProgress(Message):
    """Progress of a DEM job. Key: ``twin/<line>/dem/<job_id>/progress``."""

    SIGNAL = "progress"

    job_id: Ident = Field(description="job id")
    state: JobState = Field(description="job state")
    fraction: Fraction = Field(description="fraction done, 0..1")
    sim_time_s: NonNegative = Field(default=0.0, description="simulated time reached, s")
    n_particles: int = Field(default=0, ge=0, description="particles in the simulation")
    message: str = Field(default="", max_length=4096, description="free text")


class DemJobResult(Message):
    """Outcome of a DEM job. Key: ``twin/<line>/dem/<job_id>/result``.

    ``outputs`` maps an output name to a file path or URI; ``metrics`` holds scalar results.
    """

    SIGNAL = "result"

    job_id: Ident = Field(description="job id")
    state: Literal["done", "failed", "cancelled"] = Field(description="final state")
    outputs: dict[Ident, str] = Field(default_factory=dict, description="name -> path or URI")
    metrics: dict[Ident, Finite] = Field(default_factory=dict, description="scalar results")
    wall_time_s: NonNegative = Field(default=0.0, description="wall-clock run time, s")
    error: str | None = Field(default=None, description="error text if failed")

    @model_validator(mode="after")
    def _error_iff_failed(self) -> DemJobResult:
        if self.state == "failed" and not self.error:
            raise ValueError(f"error must be given when state is 'failed', got {self.error!r}")
        return self


class ServiceHealth(Message):
    """Periodic health of a service. Key: ``twin/<line>/service/<name>/health``.

    ``t`` is the latest plant time the service has seen (0 before any); ``counters`` hold
    e.g. ``published``, ``received``, ``rejected_json``, ``rejected_schema``, ``rejected_time``.
    """

    SIGNAL = "health"

    service: Ident = Field(description="service name")
    state: Literal["starting", "running", "degraded", "stopping"] = Field(description="state")
    pid: int = Field(ge=0, description="OS process id")
    uptime_s: NonNegative = Field(description="wall-clock time since start, s")
    wall_time_unix_s: NonNegative = Field(description="wall-clock time of this report, s")
    counters: dict[Ident, int] = Field(default_factory=dict, description="event counters")
    last_error: str | None = Field(default=None, description="last rejection or error")

    @model_validator(mode="after")
    def _counters_nonneg(self) -> ServiceHealth:
        for name, value in self.counters.items():
            if value < 0:
                raise ValueError(f"counters[{name!r}] must be >= 0, got {value}")
        return self


#: every message model defined in this module
MESSAGE_MODELS: tuple[type[Message], ...] = (
    FeederFlow,
    MeasuredConcentration,
    PredictedConcentration,
    Event,
    RtdEstimate,
    RtdSkipped,
    AdoptionProgress,
    OosAlert,
    DivertCommand,
    DemJobRequest,
    DemJobProgress,
    DemJobResult,
    ServiceHealth,
)
