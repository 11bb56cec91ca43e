"""Close the loop on a recording: residual, diagnosis, fix, and the before/after proof.

``close_loop(run_data, declared_model, options)`` runs :func:`identify` and returns a
:class:`CloseLoopResult` whose ``to_dict()`` is the JSON report (validated by
``schemas.closeloop.CloseLoopReport``): the effects found with parameters and uncertainties,
RMSE / MAE before and after on the training and held-out windows, the candidates tried, the
decision rule, residual diagnostics before and after, and the augmented model.
``online_finding`` is the same on a window of arrays, for the live twin.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from twin_core.closeloop.data import RunData
from twin_core.closeloop.diagnostics import pulse_responses, residual_diagnostics
from twin_core.closeloop.identify import FitResult, Identification, IdentifyOptions, identify
from twin_core.plant.model import LineInputs, LineModel

REPORT_VERSION = 1


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


def _effect_entries(fr: FitResult, prev: FitResult | None) -> list[dict[str, Any]]:
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
        out.append({"name": e.name, "target": e.target, "label": e.label(), "params": params})
    return out


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


@dataclass
class CloseLoopResult:
    """Result of :func:`close_loop`: the identification plus the series behind the figures."""

    data: RunData
    model: LineModel
    ident: Identification
    diagnostics_before: dict[str, Any]
    diagnostics_after: dict[str, Any]
    recording: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def status(self) -> str:
        return self.ident.status

    @property
    def effects_found(self) -> list[str]:
        """Labels of the effects claimed (empty: none)."""
        return list(self.ident.final.labels) if self.ident.accepted else []

    @property
    def predicted_before(self) -> np.ndarray:
        return self.ident.base.pred

    @property
    def predicted_after(self) -> np.ndarray:
        return self.ident.final.pred

    def augmented_model(self) -> LineModel:
        """The declared model with the claimed effects (fitted parameters) added."""
        return self.model.augmented(self.ident.final.effects if self.ident.accepted else [])

    def errors(self) -> dict[str, dict[str, dict[str, float]]]:
        y = self.ident.measured
        sp = self.ident.split
        out = {}
        for key, pred in (("before", self.predicted_before), ("after", self.predicted_after)):
            out[key] = {
                "train": _errors(y, pred, sp.train),
                "heldout": _errors(y, pred, sp.heldout),
            }
        return out

    def to_dict(self) -> dict[str, Any]:
        """The JSON report (``schemas.closeloop.CloseLoopReport``)."""
        idn = self.ident
        t = self.data.t_s
        sp = idn.split
        o = idn.options
        final = idn.final
        effects = []
        if idn.accepted:
            per_effect = _effect_entries(final, None)
            # scores of the step that accepted each effect
            for i, ent in enumerate(per_effect):
                step = idn.accepted[i] if i < len(idn.accepted) else final
                ent.update(
                    {
                        "delta_bic": step.delta_bic,
                        "heldout_rel_improvement": step.rel_improvement,
                        "lr_z": step.lr_z,
                        "p_value": step.p_value,
                        "alternatives": list(step.alternatives),
                    }
                )
                effects.append(ent)
        aug = self.augmented_model()
        return _clean(
            {
                "version": REPORT_VERSION,
                "recording": self.recording or self.data.name,
                "line": self.model.config.name,
                "sensor_component": self.model.config.sensor.component,
                "status": idn.status,
                "effects": effects,
                "errors": self.errors(),
                "windows": {
                    "split": sp.kind,
                    "description": sp.description,
                    "train_s": [float(t[sp.train].min()), float(t[sp.train].max())],
                    "heldout_s": [float(t[sp.heldout].min()), float(t[sp.heldout].max())],
                    "n_train": int(sp.train.sum()),
                    "n_heldout": int(sp.heldout.sum()),
                },
                "decision": {
                    "alpha": o.alpha,
                    "min_improvement": o.min_improvement,
                    "max_effects": o.max_effects,
                    "test": "held-out Gaussian likelihood ratio under the declared NIR noise "
                    "(white + proportional + 1/f), one-sided, Bonferroni over the candidates of a "
                    "step; plus BIC < current and held-out weighted MSE drop >= min_improvement",
                    "unexplained_nmse": o.unexplained_nmse,
                    "outliers_removed": int(idn.outliers.sum()),
                },
                "candidates": [[_candidate_row(fr) for fr in step] for step in idn.steps],
                "diagnostics_before": self.diagnostics_before,
                "diagnostics_after": self.diagnostics_after,
                "augmented_model": {
                    "config": self.model.config.line_dict(),
                    "effects": [e.to_dict() for e in aug.effects],
                },
                "n_model_evaluations": idn.n_eval,
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
        mask=ident.split.train | ident.split.heldout,
        inputs=data.inputs,
        events=data.events,
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


def close_loop(
    run_data: RunData,
    declared_model: LineModel,
    options: IdentifyOptions | Mapping[str, Any] | None = None,
    recording: str = "",
) -> CloseLoopResult:
    """Find where the declared model is wrong on ``run_data``, fix it, and prove the fix.

    ``options``: :class:`IdentifyOptions` or a dict of its fields (candidates, max_effects,
    alpha, min_improvement, split, train_fraction, ...). See ``twin_core.closeloop.identify``.
    """
    if isinstance(options, Mapping):
        options = IdentifyOptions(**options)
    ident = identify(declared_model, run_data, options)
    before = _diag(run_data, declared_model, ident, ident.base.pred)
    after = (
        _diag(run_data, declared_model, ident, ident.final.pred, ident.final.effects)
        if ident.accepted
        else before
    )
    return CloseLoopResult(run_data, declared_model, ident, before, after, recording)


@dataclass
class Finding:
    """What the online twin gets from a window: status, effects (dict form with parameters and
    standard errors), the augmented model's effect list and the errors before/after."""

    status: str
    effects: list[dict[str, Any]]
    augmented_effects: list[dict[str, Any]]
    errors: dict[str, Any]
    t_start_s: float
    t_end_s: float


def online_finding(
    t_s: np.ndarray,
    measured: np.ndarray,
    inputs: LineInputs,
    declared_model: LineModel,
    events: Sequence[Mapping[str, Any]] = (),
    options: IdentifyOptions | Mapping[str, Any] | None = None,
) -> Finding:
    """Close the loop on one window of arrays (the live twin's periodic check).

    ``inputs`` must be on ``t_s``. The model assumes the line at steady state (first flows)
    before ``t_s[0]``: pass a window that starts with some history and exclude it from the
    fit with ``skip_s`` (default here: 150 s, about 4.5 mean residence times of the Table 6.2
    blender). Returns a :class:`Finding`; ``augmented_effects`` are the model's effects plus
    the ones found, ready for ``LineModel(config, augmented_effects)``.
    """
    if options is None:
        options = IdentifyOptions(skip_s=150.0)
    data = RunData(t_s, measured, inputs, [dict(e) for e in events], name="window")
    res = close_loop(data, declared_model, options)
    rep = res.to_dict()
    return Finding(
        status=res.status,
        effects=rep["effects"],
        augmented_effects=rep["augmented_model"]["effects"],
        errors=rep["errors"],
        t_start_s=float(t_s[0]),
        t_end_s=float(t_s[-1]),
    )
