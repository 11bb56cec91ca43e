"""Open-world benchmark cases: a 2-hour scenario, effects outside the candidate library, data
faults, product/probe look-alike pairs, and the scoring of a close-loop report against a
case's known truth.

Scenario (:func:`openworld_scenario`): the seed line (10 % API at 12 kg/h, Table 6.2 blender,
the seed's NIR noise times ``noise``), 2 h at 1 Hz; API set-point steps (7.4 to 11.8 % API)
and a line-rate step 12 -> 15 -> 12 kg/h (excipient set point), three API hopper refills
(volumetric mode while the load cell is frozen) and two excipient refills; with ``tracers``,
API pulses of 10 / 7.5 / 6 / 5 g every 900 s from 450 s. The close-loop's default split trains
on the first 60 % (to 4320 s): set-point steps, refills and pulses fall in both windows.

Cases (:class:`Case`): ``none`` (effect-free), ``inlist`` (a candidate of
``twin_core.plant.effects.EFFECTS``), ``outlist`` (an effect of :data:`OUT_OF_LIST`,
``twin_core.plant.openworld``), ``fault`` (data faults of :data:`FAULT_CASES` on an
effect-free run, ``twin_core.plant.faults``) and ``lookalike`` (:data:`LOOKALIKE_PAIRS`: a
product-side effect, or the probe-side effect fitted to give the same noise-free reading).
Every run but those with an in-list rtd effect (defined on E(t)) goes through the
finite-volume blender, the plant's code path independent of the twin's convolution.

Scoring (:func:`score_report`) reads the report as a dict (``schemas.closeloop``) and takes
what is there: ``status`` (``consistent | explained | partly_explained | unexplained |
data_quality``), ``effects`` (``name``, ``target``; per effect ``equivalents``, else
``alternatives``), ``data_quality`` ({kind, t_start_s, t_end_s, n_samples}),
``product_at_risk`` and ``discriminating_measurement`` (top level or per effect). A field the
report lacks counts as a failure of what needs it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize
from scipy.stats import beta

from schemas.line import LineConfig
from twin_core.plant.effects import EFFECTS
from twin_core.plant.faults import DataFault, apply_faults
from twin_core.plant.messages import run_messages
from twin_core.plant.model import sensor_signal
from twin_core.plant.nir import noise_sd, scaled_noise
from twin_core.plant.openworld import OPEN_WORLD, open_world_line
from twin_core.plant.seed import seed_line
from twin_core.plant.simulate import LineRun, simulate_line

__all__ = [
    "FAULT_CASES",
    "LOOKALIKE_PAIRS",
    "OUT_OF_LIST",
    "Case",
    "CaseRun",
    "LookalikePair",
    "Setting",
    "clopper_pearson_upper",
    "match_probe",
    "openworld_scenario",
    "run_case",
    "score_report",
    "side_of",
]

DURATION_S = 7200.0
#: API set points (t_s, kg/h) after 1.2 kg/h at the start
API_SCHEDULE = (
    (900.0, 1.44),
    (1800.0, 1.2),
    (3000.0, 1.5),
    (4500.0, 1.08),
    (5100.0, 1.35),
    (6300.0, 1.2),
)
#: excipient set points (t_s, kg/h) after 10.8 kg/h: the line rate 12 -> 15 -> 12 kg/h
EXCIPIENT_SCHEDULE = ((2400.0, 13.5), (5700.0, 10.8))
TRACER_G = (10.0, 7.5, 6.0, 5.0)
TRACER_EVERY_S = 900.0
TRACER_FIRST_S = 450.0
#: margin around a fault's interval within which a data-quality flag counts as finding it, s
FLAG_MARGIN_S = 60.0


@dataclass(frozen=True)
class Setting:
    """Excitation and noise of a benchmark setting: tracer pulses or not, noise x seed."""

    tracers: bool
    noise: float

    @property
    def label(self) -> str:
        return f"{'tracers' if self.tracers else 'no tracers'}, noise x{self.noise:g}"


def openworld_scenario(setting: Setting, duration_s: float = DURATION_S) -> LineConfig:
    """The 2-hour scenario of the module docstring for one setting."""
    times = np.arange(TRACER_FIRST_S, duration_s - 300.0, TRACER_EVERY_S) if setting.tracers else []
    cfg = seed_line(
        tracer_g=tuple(TRACER_G[i % len(TRACER_G)] for i in range(len(times))),
        tracer_times_s=tuple(float(t) for t in times),
        api_liw=dict(
            initial_mass_kg=0.9,
            refill_low_kg=0.3,
            refill_high_kg=1.1,
            setpoint_schedule=[s for s in API_SCHEDULE if s[0] < duration_s],
        ),
        excipient_liw=dict(
            initial_mass_kg=12.0,
            refill_low_kg=3.0,
            refill_high_kg=12.0,
            setpoint_schedule=[s for s in EXCIPIENT_SCHEDULE if s[0] < duration_s],
        ),
    )
    cfg.sensor.noise = scaled_noise(cfg.sensor.noise, setting.noise)
    return cfg


#: out-of-list effects of the benchmark (dict form, ``twin_core.plant.openworld``), sized to
#: change the noise-free reading by about one to three times the seed's NIR noise
OUT_OF_LIST: dict[str, dict[str, Any]] = {
    "load_cell_span_error": {
        "name": "load_cell_span_error",
        "target": "api",
        "params": {"bias": 0.05},
    },
    "screw_pulsation": {
        "name": "screw_pulsation",
        "target": "api",
        "params": {"amplitude": 0.35, "pulses_per_rev": 1.0},
    },
    "chute_clogging": {
        "name": "chute_clogging",
        "target": "api",
        "params": {"rate_per_h": 4.0, "min_s": 4.0, "max_s": 15.0, "slug_s": 3.0},
    },
    "api_wall_loss": {"name": "api_wall_loss", "params": {"loss_fraction": 0.05}},
    "api_buildup_release": {
        "name": "api_buildup_release",
        "params": {
            "deposition_per_s": 0.003,
            "capacity_g": 8.0,
            "release_s": 5000.0,
            "release_tau_s": 60.0,
        },
    },
    "throughput_holdup": {"name": "throughput_holdup", "params": {"alpha": 0.8}},
    "two_zone_exchange": {
        "name": "two_zone_exchange",
        "params": {"volume_ratio": 0.8, "exchange_tau_s": 120.0},
    },
    "probe_fouling": {
        "name": "probe_fouling",
        "params": {"t_start_s": 1800.0, "growth_s": 3600.0, "loss_max": 0.08, "lag_max_s": 15.0},
    },
    "nonlinear_calibration": {
        "name": "nonlinear_calibration",
        "params": {"curvature": 0.04, "centre": 10.0},
    },
    "humidity_step": {
        "name": "humidity_step",
        "params": {"t_s": 3000.0, "offset": 0.45, "tau_s": 300.0},
    },
}


def _stuck(stream: str, field: str, starts: Iterable[float], lengths: Iterable[float]) -> tuple:
    return tuple(
        DataFault("stuck", stream, field, t_s=a, duration_s=d) for a, d in zip(starts, lengths)
    )


#: data-fault cases (each on an effect-free run): times chosen so that most faults hide a change
FAULT_CASES: dict[str, tuple[DataFault, ...]] = {
    "nir_stuck": _stuck("nir", "flow", (1850.0, 4480.0, 6280.0), (90.0, 150.0, 180.0)),
    "nir_gap": (DataFault("gap", "nir", t_s=5000.0, duration_s=300.0),),
    "nir_clip": (DataFault("clip", "nir", low=0.0, high=11.0),),
    "nir_spike_burst": (
        DataFault(
            "spike_burst", "nir", t_s=5300.0, duration_s=60.0, size=3.0, fraction=0.4, seed=1
        ),
    ),
    "nir_time_jump": (DataFault("time_jump", "nir", t_s=3600.0, size=-600.0),),
    "nir_duplicate_stamps": (DataFault("duplicate_stamps", "nir", t_s=2000.0, duration_s=300.0),),
    "api_flow_stuck": _stuck("api", "flow", (4450.0,), (180.0,)),
    "api_flow_gap": (DataFault("gap", "api", t_s=4400.0, duration_s=240.0),),
    "api_flow_clip": (DataFault("clip", "api", "flow", low=0.0, high=1.4),),
    "api_flow_spike_burst": (
        DataFault(
            "spike_burst",
            "api",
            "flow",
            t_s=5000.0,
            duration_s=60.0,
            size=0.6,
            fraction=0.4,
            seed=2,
        ),
    ),
    "api_time_jump": (DataFault("time_jump", "api", t_s=3600.0, size=-300.0),),
    "api_duplicate_stamps": (DataFault("duplicate_stamps", "api", t_s=2000.0, duration_s=300.0),),
    "api_screw_stuck": _stuck("api", "screw_speed", (4450.0,), (180.0,)),
    "api_screw_spike_burst": (
        DataFault(
            "spike_burst",
            "api",
            "screw_speed",
            t_s=5000.0,
            duration_s=60.0,
            size=3.0,
            fraction=0.4,
            seed=3,
        ),
    ),
    "excipient_flow_stuck": _stuck("excipient", "flow", (2350.0,), (180.0,)),
    "excipient_flow_gap": (DataFault("gap", "excipient", t_s=5650.0, duration_s=240.0),),
    "excipient_time_jump": (DataFault("time_jump", "excipient", t_s=3600.0, size=120.0),),
}


@dataclass(frozen=True)
class LookalikePair:
    """A product-side effect (in-list or open-world dict form) and the probe-side candidate
    (an in-list sensor effect) fitted to give the same noise-free reading."""

    product: dict[str, Any]
    probe: str


LOOKALIKE_PAIRS: dict[str, LookalikePair] = {
    "api_wall_loss~sensor_gain": LookalikePair(
        {"name": "api_wall_loss", "params": {"loss_fraction": 0.05}}, "sensor_gain"
    ),
    "load_cell_span_error~sensor_offset": LookalikePair(
        {"name": "load_cell_span_error", "target": "api", "params": {"bias": 0.05}},
        "sensor_offset",
    ),
    "excipient_span_error~sensor_gain": LookalikePair(
        {"name": "load_cell_span_error", "target": "excipient", "params": {"bias": 0.06}},
        "sensor_gain",
    ),
    "feed_factor_drift~sensor_drift": LookalikePair(
        {"name": "feed_factor_drift", "target": "api", "params": {"rate_per_h": -0.04}},
        "sensor_drift",
    ),
}


def side_of(name: str) -> str | None:
    """``"probe"`` for sensor-stage candidates and probe-side open-world effects, ``"product"``
    for the other known effects, None for an unknown name."""
    if name in EFFECTS:
        return "probe" if EFFECTS[name].stage == "sensor" else "product"
    if name in OPEN_WORLD:
        return OPEN_WORLD[name].side
    return None


def _aliases(name: str) -> tuple[str, ...]:
    return OPEN_WORLD[name].aliases if name in OPEN_WORLD else ()


@dataclass(frozen=True)
class Case:
    """One benchmark case (module docstring). ``effects``: in-list specs; ``open_world``:
    open-world specs; ``faults``: data faults; ``pair``/``role``: look-alike pair and side."""

    family: str
    name: str
    effects: tuple[dict[str, Any], ...] = ()
    open_world: tuple[dict[str, Any], ...] = ()
    faults: tuple[DataFault, ...] = ()
    pair: str = ""
    role: str = ""

    def __post_init__(self) -> None:
        if self.family not in ("none", "inlist", "outlist", "fault", "lookalike"):
            raise ValueError(
                f"case family must be none/inlist/outlist/fault/lookalike, got {self.family!r}"
            )
        if self.family == "lookalike" and (
            self.pair not in LOOKALIKE_PAIRS or self.role not in ("product", "probe")
        ):
            raise ValueError(
                f"look-alike case needs a pair of LOOKALIKE_PAIRS and a role, got {self.pair!r}/{self.role!r}"
            )

    @classmethod
    def lookalike(cls, pair: str, role: str) -> Case:
        p = LOOKALIKE_PAIRS[pair]
        spec = p.product
        in_list = spec["name"] in EFFECTS
        if role == "product":
            return cls(
                "lookalike",
                f"{pair}:product",
                effects=(spec,) if in_list else (),
                open_world=() if in_list else (spec,),
                pair=pair,
                role=role,
            )
        return cls("lookalike", f"{pair}:probe", pair=pair, role=role)

    @property
    def blender(self) -> str:
        """``convolution`` when an in-list rtd effect is hidden (it is defined on E(t)), else
        the independent finite-volume blender."""
        rtd = any(EFFECTS[e["name"]].stage == "rtd" for e in self.effects if e["name"] in EFFECTS)
        return "convolution" if rtd else "fv"

    def truth_name(self) -> str:
        """The hidden mechanism's name (``none`` for effect-free and fault cases)."""
        if self.family == "lookalike":
            p = LOOKALIKE_PAIRS[self.pair]
            return p.product["name"] if self.role == "product" else p.probe
        specs = [*self.effects, *self.open_world]
        return "+".join(e["name"] for e in specs) or "none"

    def truth_names(self) -> set[str]:
        """Names that name the truth: the mechanism and its aliases among the candidates."""
        names = set(self.truth_name().split("+"))
        return names | {a for n in names for a in _aliases(n)}


@dataclass
class CaseRun:
    """A simulated case: the run, its (faulted) bus messages, and the truth dict."""

    case: Case
    setting: Setting
    seed: int
    run: LineRun
    messages: list[tuple[str, Any]]
    truth: dict[str, Any] = field(default_factory=dict)


def _base_outlet(run: LineRun) -> np.ndarray:
    """Effect-free noise-free outlet of the sensor's component on the run's reported flows
    (same blender code path as the run)."""
    cfg = run.config
    line = open_world_line(cfg, run.t_s, run.feeders, blender=run.blender)
    return line.outlet_pct_w_w[cfg.sensor.component]


def match_probe(product: LineRun, probe: str) -> tuple[dict[str, Any], float]:
    """The probe-side in-list effect ``probe`` (a sensor effect) whose noise-free reading is
    closest (least squares) to the product-side run's: (its dict form, RMS difference % w/w)."""
    if probe not in EFFECTS or EFFECTS[probe].stage != "sensor":
        raise ValueError(f"probe must be a sensor-stage effect of EFFECTS, got {probe!r}")
    cls = EFFECTS[probe]
    t = product.t_s
    base = _base_outlet(product)
    offset = product.config.sensor.noise.baseline_offset
    target = product.sensor_true_pct_w_w
    lo, hi = cls.bounds()

    def reading(x: np.ndarray) -> np.ndarray:
        e = cls(**{p.name: float(v) for p, v in zip(cls.params, x)})
        return sensor_signal(t, base, [e], offset)

    sol = optimize.least_squares(lambda x: reading(x) - target, cls.defaults(), bounds=(lo, hi))
    spec = {
        "name": probe,
        "target": None,
        "params": {p.name: float(v) for p, v in zip(cls.params, sol.x)},
    }
    rms = float(np.sqrt(np.mean((reading(sol.x) - target) ** 2)))
    return spec, rms


def _rms(x: np.ndarray) -> float:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")


#: feeder records of recent (configuration, duration, seed): the LIW simulation is the slow part
#: of a run and does not depend on the case or the setting
_FEEDER_CACHE: dict[tuple[str, float, int], dict[str, Any]] = {}


def _simulate(cfg: LineConfig, duration_s: float, seed: int, **kwargs: Any) -> LineRun:
    """``simulate_line`` reusing the feeders of an earlier run with the same feeders and seed."""
    key = (json.dumps([f.model_dump(mode="json") for f in cfg.feeders]), duration_s, seed)
    run = simulate_line(cfg, duration_s, seed=seed, feeder_records=_FEEDER_CACHE.get(key), **kwargs)
    if key not in _FEEDER_CACHE:
        if len(_FEEDER_CACHE) >= 4:
            _FEEDER_CACHE.pop(next(iter(_FEEDER_CACHE)))
        _FEEDER_CACHE[key] = run.feeders
    return run


def run_case(
    case: Case,
    setting: Setting,
    seed: int,
    duration_s: float = DURATION_S,
    timing: Sequence[DataFault] = (),
) -> CaseRun:
    """Simulate a case in a setting with a seed: the run, its messages (faults applied) and the
    truth (mechanism, side, sizes: ``effect_rms`` of the noise-free reading against the declared
    model, ``product_rms`` / ``product_mean`` of the true outlet against it, the NIR
    ``noise_sd``; fault intervals; for a look-alike probe the fitted ``match_rms``).
    ``timing``: a timing fault (``twin_core.plant.faults.TIMING_KINDS``, with a refill flag's
    shift the feeder's ``refill_hold`` before it) applied to the messages after the case's
    faults, in the truth as ``timing`` (its last fault's truth; not among the ``faults``)."""
    cfg = openworld_scenario(setting, duration_s)
    extra: dict[str, Any] = {}
    effects, open_world = list(case.effects), list(case.open_world)
    if case.family == "lookalike" and case.role == "probe":
        pc = Case.lookalike(case.pair, "product")
        product = _simulate(
            cfg,
            duration_s,
            seed,
            effects=list(pc.effects),
            open_world=list(pc.open_world),
            blender=pc.blender,
        )
        spec, extra["match_rms"] = match_probe(product, LOOKALIKE_PAIRS[case.pair].probe)
        effects, open_world = [spec], []
        extra["params"] = spec["params"]
    run = _simulate(
        cfg, duration_s, seed, effects=effects, open_world=open_world, blender=case.blender
    )
    messages = run_messages(run, cfg)
    if case.faults:
        messages, run.faults = apply_faults(messages, case.faults, cfg)
    if timing:
        messages, timing_truth = apply_faults(messages, list(timing), cfg)
        extra["timing"] = timing_truth[-1] if timing_truth else {}
    declared_outlet = run.predicted_declared() - cfg.sensor.noise.baseline_offset
    product_dev = run.outlet_true_pct_w_w[cfg.sensor.component] - declared_outlet
    name = case.truth_name()
    truth = {
        "family": case.family,
        "case": case.name,
        "truth": name,
        "truth_names": sorted(case.truth_names()),
        "side": side_of(name) if "+" not in name else None,
        "pair": case.pair,
        "role": case.role,
        "setting": setting.label,
        "tracers": setting.tracers,
        "noise": setting.noise,
        "seed": seed,
        "blender": run.blender,
        "effect_rms": _rms(run.sensor_true_pct_w_w - run.predicted_declared()),
        "product_rms": _rms(product_dev),
        "product_mean": float(np.mean(product_dev)),
        "noise_sd": float(np.mean(noise_sd(run.sensor_true_pct_w_w, cfg.sensor.noise))),
        "faults": list(run.faults),
        **extra,
    }
    return CaseRun(case, setting, seed, run, messages, truth)


# ---------------------------------------------------------------------------------------------
# scoring a report
# ---------------------------------------------------------------------------------------------
def _name(entry: Any) -> str:
    """Registry name of an effect or equivalent entry: a label ``name[target]`` or a dict with
    ``name`` / ``label`` / ``effect``."""
    if isinstance(entry, Mapping):
        for k in ("name", "label", "effect", "mechanism"):
            if entry.get(k):
                return str(entry[k]).split("[")[0]
        return ""
    return str(entry).split("[")[0]


def _equivalents(effect: Mapping[str, Any]) -> tuple[list[str], str]:
    """Names an effect entry lists as explanations the data cannot tell apart, and the field
    read (``equivalents``, else ``alternatives``, else none)."""
    for key in ("equivalents", "alternatives"):
        if key in effect and effect[key] is not None:
            return [n for n in (_name(x) for x in effect[key]) if n], key
    return [], ""


def _flag(report: Mapping[str, Any], key: str) -> Any:
    """A report field at the top level, else the first effect entry that has it (None: none)."""
    if key in report:
        return report[key]
    for e in report.get("effects") or []:
        if isinstance(e, Mapping) and key in e:
            return e[key]
    return None


def _present(value: Any) -> bool:
    if isinstance(value, Mapping):
        return any(_present(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return any(_present(v) for v in value)
    return bool(value)


def _overlaps(entry: Mapping[str, Any], truth: Mapping[str, Any], margin: float) -> bool:
    try:
        a, b = float(entry["t_start_s"]), float(entry["t_end_s"])
    except (KeyError, TypeError, ValueError):
        return False
    return a - margin <= float(truth["t_end_s"]) and b + margin >= float(truth["t_start_s"])


def _faults_flagged(report: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    """The report's ``data_quality`` entries that are faults (``action`` ``left_out``, or none
    given), not repairs of the messages' timing."""
    return [
        d
        for d in (report.get("data_quality") or [])
        if isinstance(d, Mapping) and d.get("action", "left_out") == "left_out"
    ]


def _effect_outcome(status: str, claimed: Sequence[str], listed: set[str], names: set[str]) -> str:
    if any(c in names for c in claimed):
        return "right"
    if claimed and listed & names:
        return "right_equivalent"
    if claimed:
        return "wrong_confident" if status == "explained" else "wrong_partial"
    return "dont_know"


def score_report(report: Mapping[str, Any], truth: Mapping[str, Any]) -> dict[str, Any]:
    """Score a close-loop report (dict) against a case's truth (:func:`run_case`).

    Returns ``status``, ``claimed`` (names), ``listed`` (claimed and their equivalents, and an
    unexplained record's ``possible_explanations``),
    ``equivalents_field``, ``outcome`` and the fields of the family:

    - every family: ``outcome`` ``right`` (the truth, or one of its aliases, claimed),
      ``right_equivalent`` (listed among the equivalents), ``wrong_confident`` (another
      mechanism claimed with status ``explained``), ``wrong_partial`` (claimed with another
      status), ``dont_know`` (no claim); ``none`` and ``fault`` cases: ``claim`` or
      ``no_claim``;
    - ``fault``: ``flagged`` (a ``data_quality`` fault entry, not a timing repair, within
      ``FLAG_MARGIN_S`` of a fault interval), ``status_data_quality``;
    - ``lookalike``: ``both_listed`` (a product-side and a probe-side mechanism among the
      listed), ``product_at_risk`` (True / False / None when the report lacks it),
      ``discriminating`` (a measurement named), ``lookalike_ok`` (all three).
    """
    status = str(report.get("status", ""))
    effects = [e for e in (report.get("effects") or []) if isinstance(e, Mapping)]
    claimed = [_name(e) for e in effects]
    listed = set(claimed)
    eq_field = ""
    for e in effects:
        names, key = _equivalents(e)
        listed.update(names)
        eq_field = eq_field or key
    listed.update(
        _name(e) for e in (report.get("possible_explanations") or []) if isinstance(e, Mapping)
    )
    family = truth["family"]
    names = set(truth.get("truth_names") or [truth["truth"]])
    out: dict[str, Any] = {
        "status": status,
        "claimed": claimed,
        "listed": sorted(listed),
        "equivalents_field": eq_field,
        "n_data_quality": len(_faults_flagged(report)),
    }
    if family in ("none", "fault"):
        out["outcome"] = "claim" if claimed else "no_claim"
    else:
        out["outcome"] = _effect_outcome(status, claimed, listed, names)
    risk = _flag(report, "product_at_risk")
    out["product_at_risk"] = None if risk is None else bool(risk)
    out["discriminating"] = _present(_flag(report, "discriminating_measurement"))
    if family == "fault":
        dq = _faults_flagged(report)
        out["flagged"] = any(
            _overlaps(d, f, FLAG_MARGIN_S) for d in dq for f in truth.get("faults") or []
        )
        out["status_data_quality"] = status == "data_quality"
    if family == "lookalike":
        sides = {side_of(n) for n in listed}
        out["both_listed"] = {"product", "probe"} <= sides
        out["lookalike_ok"] = bool(
            out["both_listed"] and out["product_at_risk"] and out["discriminating"]
        )
    return out


def clopper_pearson_upper(k: int, n: int, level: float = 0.95) -> float:
    """One-sided upper confidence bound of a binomial rate, k of n (Clopper & Pearson 1934)."""
    if n <= 0:
        return math.nan
    return 1.0 if k >= n else float(beta.ppf(level, k + 1, n - k))
