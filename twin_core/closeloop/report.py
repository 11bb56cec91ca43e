"""Close the loop on a recording: data quality, residual, diagnosis, fix, the before/after proof,
and an honest account of what is and is not explained.

``close_loop(run_data, declared_model, options)``:

1. data quality first (``twin_core.closeloop.quality``): flagged samples are left out;
2. identification (``twin_core.closeloop.identify``): effects, their equivalent explanations,
   the honest status (a record left unexplained by a candidate the forward split cannot test,
   :func:`untestable_by_tail`, is identified again on alternating blocks); a record whose flagged faults are all that is wrong (no effect claimed,
   the rest the noise) gets status ``data_quality``, never a process effect;
3. product-safe attribution (``twin_core.closeloop.attribution``) and, when the product is at
   risk, the measurement that would separate the readings (``twin_core.closeloop.discriminate``);
4. structure beyond the effect library (``twin_core.closeloop.structure``: parameters that change
   with the operating point or time, periodic content, a blender-response correction) in what
   the library left;
5. residual diagnostics before and after.

Returns a :class:`CloseLoopResult` whose ``to_dict()`` is the JSON report (validated by
``schemas.closeloop.CloseLoopReport``). ``online_finding`` is the same on a window of arrays,
for the live twin.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from twin_core.closeloop.attribution import (
    Attribution,
    attribute,
    out_of_spec_spans,
    outlet_summary,
)
from twin_core.closeloop.data import RunData, StreamStamps
from twin_core.closeloop.diagnostics import pulse_responses, residual_diagnostics
from twin_core.closeloop.discriminate import Design, DesignOptions, design_measurement
from twin_core.closeloop.identify import (
    FitResult,
    Identification,
    IdentifyOptions,
    effect_side,
    identify,
)
from twin_core.closeloop.quality import DataQuality, QualityOptions, check_data_quality
from twin_core.plant.model import LineInputs, LineModel

REPORT_VERSION = 3


def _clean(x: Any) -> Any:
    """JSON-safe copy: numpy scalars to Python, non-finite floats to None."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if np.isfinite(v) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    return x


def _errors(y: np.ndarray, pred: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    r = (y - pred)[mask & np.isfinite(y)]
    return {
        "rmse": float(np.sqrt(np.mean(r**2))),
        "mae": float(np.mean(np.abs(r))),
        "n": int(r.size),
    }


def _effect_entries(fr: FitResult) -> list[dict[str, Any]]:
    out = []
    for e, se in zip(fr.effects, fr.stderr or [np.full(len(x.params), np.nan) for x in fr.effects]):
        params = []
        for p, s in zip(e.params, se):
            v = e.values[p.name]
            s = float(s) if np.isfinite(s) else None
            params.append(
                {
                    "name": p.name,
                    "value": v,
                    "stderr": s,
                    "ci95_low": max(p.lower, v - 1.96 * s) if s is not None else None,
                    "ci95_high": min(p.upper, v + 1.96 * s) if s is not None else None,
                    "unit": p.unit,
                    "lower": p.lower,
                    "upper": p.upper,
                }
            )
        out.append(
            {
                "name": e.name,
                "target": e.target,
                "label": e.label(),
                "side": e.side,
                "params": params,
            }
        )
    return out


def _explanation_entry(f: FitResult, delta_bic: float) -> dict[str, Any]:
    """An alternative explanation's last effect with its scores (``schemas.closeloop.
    Equivalent`` / ``PossibleExplanation``)."""
    e = f.effects[-1]
    return {
        "label": f.labels[-1],
        "name": e.name,
        "target": e.target,
        "side": effect_side(f.labels[-1]),
        "params": dict(e.values),
        "delta_bic": delta_bic,
        "heldout_rel_improvement": f.rel_improvement,
        "p_value": f.p_value,
    }


def _equivalent_entries(step: FitResult) -> list[dict[str, Any]]:
    """The equivalents of an accepted step with their scores (``schemas.closeloop.Equivalent``):
    ``delta_bic`` against the step's whole-record BIC."""
    return [_explanation_entry(f, f.bic_all - step.bic_all) for f in step.equivalents]


def _possible_entries(attribution: Attribution | None) -> list[dict[str, Any]]:
    """The possible explanations of an unexplained record (``schemas.closeloop.
    PossibleExplanation``; ``twin_core.closeloop.attribution``): ``delta_bic`` against the
    declared model's training BIC, and the held-out LR z."""
    if attribution is None:
        return []
    return [{**_explanation_entry(f, f.delta_bic), "lr_z": f.lr_z} for f in attribution.possible]


def _candidate_row(fr: FitResult) -> dict[str, Any]:
    e = fr.effects[-1]
    return {
        "label": fr.labels[-1],
        "params": dict(e.values),
        "delta_bic": fr.delta_bic,
        "heldout_rel_improvement": fr.rel_improvement,
        "lr_z": fr.lr_z,
        "p_value": fr.p_value,
        "dm_stat": fr.dm_stat,
        "dm_p_value": fr.dm_p_value,
        "claimable": bool(fr.claimable),
        "converged": bool(fr.converged),
    }


def remaining_text(ident: Identification, structure: Sequence[Mapping[str, Any]]) -> str:
    """What the model leaves unexplained, in words (empty when its innovations are the noise)."""
    nt = ident.noise_tests
    if nt.get("consistent", True) and not structure:
        return ""
    where = "held-out" if ident.accepted else "training and held-out"
    parts = []
    p = nt.get("p", {})
    if "scale" in nt.get("failed", []):
        parts.append(
            f"the {where} residual is {nt['mse']:.2f} x the noise variance (noise band <= "
            f"{nt['mse_band']:.2f})"
        )
    if "level_trend" in nt.get("failed", []):
        z = nt.get("level_trend_z", [0.0, 0.0])
        parts.append(f"a level (z {z[0]:+.1f}) or trend (z {z[1]:+.1f}) is left")
    if "ljung_box" in nt.get("failed", []):
        parts.append(f"short-lag structure is left (Ljung-Box p {p['ljung_box']:.1e})")
    if "cumulative_periodogram" in nt.get("failed", []):
        parts.append(
            "the residual spectrum is not the noise's (cumulative periodogram p "
            f"{p['cumulative_periodogram']:.1e})"
        )
    parts += [str(s.get("summary", "")) for s in structure]
    return "; ".join(x for x in parts if x)


@dataclass
class CloseLoopResult:
    """Result of :func:`close_loop`: the identification, the quality check, the attribution, and
    the series behind the figures."""

    data: RunData
    model: LineModel
    ident: Identification
    diagnostics_before: dict[str, Any]
    diagnostics_after: dict[str, Any]
    recording: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    quality: DataQuality | None = None
    attribution: Attribution | None = None
    design: Design | None = None
    structure: list[dict[str, Any]] = field(default_factory=list)
    timing_s: dict[str, float] = field(default_factory=dict)

    @property
    def status(self) -> str:
        if self.quality is not None and self.quality.flags and self.ident.status == "consistent":
            return "data_quality"
        return self.ident.status

    @property
    def effects_found(self) -> list[str]:
        """Labels of the effects claimed (empty: none)."""
        return list(self.ident.final.labels) if self.ident.accepted else []

    @property
    def product_at_risk(self) -> bool:
        return bool(self.attribution is not None and self.attribution.product_at_risk)

    @property
    def predicted_before(self) -> np.ndarray:
        return self.ident.base.pred

    @property
    def predicted_after(self) -> np.ndarray:
        return self.ident.final.pred

    def augmented_model(self) -> LineModel:
        """The declared model with the claimed effects (fitted parameters) added."""
        return self.model.augmented(self.ident.final.effects if self.ident.accepted else [])

    def acted_on_model(self) -> LineModel:
        """The model the twin acts on: the product-side reading when the product is at risk,
        else the augmented model."""
        if self.product_at_risk and self.attribution.reading is not None:
            return self.model.augmented(self.attribution.reading.effects)
        return self.augmented_model()

    def errors(self) -> dict[str, dict[str, dict[str, float]]]:
        y = self.ident.measured
        out = {}
        for key, pred in (("before", self.predicted_before), ("after", self.predicted_after)):
            out[key] = {
                "train": _errors(y, pred, self.ident.train),
                "heldout": _errors(y, pred, self.ident.heldout),
            }
        return out

    def product_reading(self, limits: tuple[float, float] | None = None) -> dict[str, Any] | None:
        """The product-side reading (``schemas.closeloop.ProductReading``) when the product is
        at risk; with the specification ``limits`` (lower, upper, % w/w) of the measured
        component, the stretches it puts out of specification (``out_of_spec_s``)."""
        if not self.product_at_risk or self.attribution.reading is None:
            return None
        fr = self.attribution.reading
        model = self.model.augmented(fr.effects)
        comp = self.model.config.sensor.component
        outlet = model.outlet(self.data.inputs)[comp]
        mask = self.ident.train | self.ident.heldout
        t = self.data.t_s[mask]
        out = {
            "effects": [e.to_dict() for e in fr.effects],
            "labels": list(fr.labels),
            **outlet_summary(outlet, mask),
            "t_start_s": float(t[0]),
            "t_end_s": float(t[-1]),
        }
        if limits is not None:
            out["out_of_spec_s"] = [
                list(span) for span in out_of_spec_spans(t, outlet[mask], *limits)
            ]
        return out

    def effect_entries(self) -> list[dict[str, Any]]:
        """The claimed effects with their step scores and equivalents."""
        idn = self.ident
        if not idn.accepted:
            return []
        effects = []
        for i, ent in enumerate(_effect_entries(idn.final)):
            step = idn.accepted[i] if i < len(idn.accepted) else idn.final
            ent.update(
                {
                    "delta_bic": step.delta_bic,
                    "heldout_rel_improvement": step.rel_improvement,
                    "lr_z": step.lr_z,
                    "p_value": step.p_value,
                    "alternatives": list(step.alternatives),
                    "equivalents": _equivalent_entries(step),
                }
            )
            effects.append(ent)
        return effects

    def to_dict(self) -> dict[str, Any]:
        """The JSON report (``schemas.closeloop.CloseLoopReport``)."""
        idn = self.ident
        t = self.data.t_s
        sp = idn.split
        o = idn.options
        aug = self.augmented_model()
        return _clean(
            {
                "version": REPORT_VERSION,
                "recording": self.recording or self.data.name,
                "line": self.model.config.name,
                "sensor_component": self.model.config.sensor.component,
                "status": self.status,
                "data_quality": self.quality.to_list() if self.quality is not None else [],
                "clock_offsets": [c.to_dict() for c in self.quality.clock_offsets]
                if self.quality is not None
                else [],
                "effects": self.effect_entries(),
                "possible_explanations": _possible_entries(self.attribution),
                "product_at_risk": self.product_at_risk,
                "product_reading": self.product_reading(),
                "discriminating_measurement": (
                    self.design.to_dict() if self.design is not None else None
                ),
                "structure": self.structure,
                "remaining": remaining_text(idn, self.structure),
                "noise_tests": idn.noise_tests,
                "errors": self.errors(),
                "windows": {
                    "split": sp.kind,
                    "description": sp.description,
                    "train_s": [float(t[sp.train].min()), float(t[sp.train].max())],
                    "heldout_s": [float(t[sp.heldout].min()), float(t[sp.heldout].max())],
                    "n_train": int(idn.train.sum()),
                    "n_heldout": int(idn.heldout.sum()),
                },
                "decision": {
                    "alpha": o.alpha,
                    "min_improvement": o.min_improvement,
                    "max_effects": o.max_effects,
                    "test": "held-out likelihood ratio on the innovations of the declared NIR "
                    "noise (white + proportional + 1/f), one-sided, Bonferroni over the "
                    "candidates of a step; plus BIC < current and held-out innovation MSE drop "
                    ">= min_improvement; status from the innovation tests at noise_alpha",
                    "noise_alpha": o.noise_alpha,
                    "ambiguity_bic": o.ambiguity_bic,
                    "outliers_removed": int(idn.outliers.sum()),
                    "samples_left_out": (
                        int(self.quality.exclude.sum()) if self.quality is not None else 0
                    ),
                },
                "candidates": [[_candidate_row(fr) for fr in step] for step in idn.steps],
                "diagnostics_before": self.diagnostics_before,
                "diagnostics_after": self.diagnostics_after,
                "augmented_model": {
                    "config": self.model.config.line_dict(),
                    "effects": [e.to_dict() for e in aug.effects],
                },
                "n_model_evaluations": idn.n_eval,
                "timing_s": self.timing_s,
            }
        )


def _diag(
    data: RunData,
    model: LineModel,
    ident: Identification,
    pred: np.ndarray,
    effects: list | None = None,
) -> dict[str, Any]:
    """Residual diagnostics and pulse responses of the model (declared + ``effects``)."""
    r = ident.measured - pred
    d = residual_diagnostics(
        data.t_s,
        r,
        sigma=ident.sigma,
        mask=ident.usable,
        inputs=data.inputs,
        events=data.events,
        whitener=ident.whitener,
    )
    aug = model.augmented(effects or [])
    inp = data.inputs
    backgrounds = []
    for i in range(len(inp.tracers)):
        without = LineInputs(
            t_s=inp.t_s,
            flows_kg_h=inp.flows_kg_h,
            components=inp.components,
            refilling=inp.refilling,
            tracers=[p for j, p in enumerate(inp.tracers) if j != i],
        )
        backgrounds.append(aug.predict(without))
    d["pulse_responses"] = pulse_responses(
        data.t_s, ident.measured, pred, inp, backgrounds=backgrounds
    )
    # keep the report compact: the spectrum at most 64 points
    sp = d["spectrum"]
    if len(sp["frequency_hz"]) > 64:
        idx = np.unique(np.linspace(0, len(sp["frequency_hz"]) - 1, 64).astype(int))
        sp["frequency_hz"] = [sp["frequency_hz"][i] for i in idx]
        sp["psd"] = [sp["psd"][i] for i in idx]
    return d


def find_library_structure(
    data: RunData, model: LineModel, ident: Identification
) -> list[dict[str, Any]]:
    """Structure beyond the effect library in what the (augmented) model leaves, as
    ``schemas.closeloop.StructureEntry`` dicts: ``twin_core.closeloop.structure.find_structure``
    (``StructureFinding.to_dict``) on the identification's windows and noise. Without that
    module installed there is no structure search and the list is empty."""
    try:
        from twin_core.closeloop.structure import find_structure
    except ImportError:
        return []
    found = find_structure(
        data,
        model,
        train=ident.train,
        heldout=ident.heldout,
        noise=model.config.sensor.noise,
    )
    return [f.to_dict() for f in found]


#: share of a candidate's change of prediction (innovation energy) below which the held-out
#: window cannot test it
UNTESTABLE_SHARE = 0.05


def untestable_by_tail(ident: Identification) -> bool:
    """Whether a forward (``tail``) split left the record unexplained because its best
    candidate acts where the held-out window cannot see it: nothing claimed, and less than
    ``UNTESTABLE_SHARE`` of the best-BIC candidate's change of prediction (squared, on the usable
    samples) falls in the held-out window -- a start-up transient such as a hold-up filling
    over the first minutes. Then the record is identified again on alternating blocks, whose
    held-out samples interleave with the training ones (``twin_core.closeloop.data.make_split``)."""
    if ident.accepted or ident.status != "unexplained" or ident.options.split != "tail":
        return False
    fits = [f for f in (ident.steps[0] if ident.steps else []) if f.converged]
    if not fits:
        return False
    best = min(fits, key=lambda f: f.delta_bic)
    if not best.delta_bic < 0:
        return False
    change = (best.pred - ident.base.pred) ** 2
    total = float(np.sum(change[ident.usable]))
    return total > 0 and float(np.sum(change[ident.heldout])) < UNTESTABLE_SHARE * total


def close_loop(
    run_data: RunData,
    declared_model: LineModel,
    options: IdentifyOptions | Mapping[str, Any] | None = None,
    recording: str = "",
    quality_options: QualityOptions | None = None,
    design_options: DesignOptions | None = None,
) -> CloseLoopResult:
    """Find where the declared model is wrong on ``run_data``, fix it, prove the fix, and say
    what is left (see the module docstring).

    ``options``: :class:`IdentifyOptions` or a dict of its fields (candidates, max_effects,
    alpha, min_improvement, split, train_fraction, ...). See ``twin_core.closeloop.identify``.
    """
    if isinstance(options, Mapping):
        options = IdentifyOptions(**options)
    clock = time.process_time
    timing: dict[str, float] = {}
    t0 = clock()
    quality = check_data_quality(run_data, declared_model, quality_options)
    t1 = clock()
    ident = identify(declared_model, run_data, options, exclude=quality.exclude)
    if untestable_by_tail(ident):
        ident = identify(
            declared_model, run_data, replace(ident.options, split="blocks"), quality.exclude
        )
    t2 = clock()
    attribution = attribute(ident)
    design = None
    if attribution.product_at_risk:
        probe, product = attribution.probe_reading, attribution.reading
        design = design_measurement(
            run_data,
            declared_model,
            probe.effects,
            product.effects,
            ident.heldout,
            labels=["+".join(probe.labels), "+".join(product.labels)],
            options=design_options,
        )
    t3 = clock()
    aug = declared_model.augmented(ident.final.effects if ident.accepted else [])
    structure = find_library_structure(run_data, aug, ident)
    t4 = clock()
    before = _diag(run_data, declared_model, ident, ident.base.pred)
    after = (
        _diag(run_data, declared_model, ident, ident.final.pred, ident.final.effects)
        if ident.accepted
        else before
    )
    t5 = clock()
    timing = {
        "data_quality": t1 - t0,
        "identification": t2 - t1,
        "fits": t2 - t1 - ident.tests_s,
        "tests": ident.tests_s,
        "attribution": t3 - t2,
        "structure": t4 - t3,
        "diagnostics": t5 - t4,
        "total": t5 - t0,
    }
    return CloseLoopResult(
        run_data,
        declared_model,
        ident,
        before,
        after,
        recording,
        quality=quality,
        attribution=attribution,
        design=design,
        structure=structure,
        timing_s=timing,
    )


@dataclass
class Finding:
    """What the online twin gets from a window: status, effects (dict form with parameters,
    standard errors and equivalents), the model's effect list to adopt (the product-side
    reading when the product is at risk), the errors before/after, and the rest of the report's
    honest account (data quality, product reading, discriminating measurement, structure)."""

    status: str
    effects: list[dict[str, Any]]
    augmented_effects: list[dict[str, Any]]
    errors: dict[str, Any]
    t_start_s: float
    t_end_s: float
    data_quality: list[dict[str, Any]] = field(default_factory=list)
    product_at_risk: bool = False
    product_reading: dict[str, Any] | None = None
    discriminating_measurement: dict[str, Any] | None = None
    structure: list[dict[str, Any]] = field(default_factory=list)
    remaining: str = ""
    possible_explanations: list[dict[str, Any]] = field(default_factory=list)


def online_finding(
    t_s: np.ndarray,
    measured: np.ndarray,
    inputs: LineInputs,
    declared_model: LineModel,
    events: Sequence[Mapping[str, Any]] = (),
    options: IdentifyOptions | Mapping[str, Any] | None = None,
    stamps: Mapping[str, StreamStamps] | None = None,
    *,
    noise_span_s: float | None = None,
    limits: tuple[float, float] | None = None,
) -> Finding:
    """Close the loop on one window of arrays (the live twin's periodic check).

    ``inputs`` must be on ``t_s``. The model assumes the line at steady state (first flows)
    before ``t_s[0]``: pass a window that starts with some history and exclude it from the
    fit with ``skip_s`` (default here: 150 s, about 4.5 mean residence times of the Table 6.2
    blender). ``stamps``: the raw message stamps of the window's streams (data quality).
    Returns a :class:`Finding`; ``augmented_effects`` are the model's effects plus the ones
    found (or their product-side reading), ready for ``LineModel(config, augmented_effects)``.
    ``noise_span_s``: the run the window is a segment of (``RunData.noise_span_s``).
    ``limits``: the measured component's specification (lower, upper, % w/w): the product-side
    reading then names the stretches it puts out of specification (what the diverter diverts).
    """
    if options is None:
        options = IdentifyOptions(skip_s=150.0)
    data = RunData(
        t_s,
        measured,
        inputs,
        [dict(e) for e in events],
        name="window",
        stamps=dict(stamps or {}),
        noise_span_s=noise_span_s,
    )
    res = close_loop(data, declared_model, options)
    rep = res.to_dict()
    return Finding(
        status=res.status,
        effects=rep["effects"],
        augmented_effects=[e.to_dict() for e in res.acted_on_model().effects],
        errors=rep["errors"],
        t_start_s=float(t_s[0]),
        t_end_s=float(t_s[-1]),
        data_quality=rep["data_quality"],
        product_at_risk=rep["product_at_risk"],
        product_reading=res.product_reading(limits)
        if limits is not None
        else rep["product_reading"],
        discriminating_measurement=rep["discriminating_measurement"],
        structure=rep["structure"],
        remaining=rep["remaining"],
        possible_explanations=rep["possible_explanations"],
    )
