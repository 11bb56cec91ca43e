"""The calibration workflows as library calls (``twin calibrate design / fit / solve``, ``twin
feeder simulate / fit-ff``), each writing its tables and figures to the directory it is given.

- :func:`design_study`: a definitive screening design (Jones & Nachtsheim 2011/2013; seed
  3.2.1), its correlation map (seed Fig. 3.4) and the largest |r| per class of terms.
- :func:`fit_study`: two-step stepwise response surfaces (or given terms) of a results table,
  their reports, parity and prediction profiles (seed Figs. 3.5-3.6), optional prediction
  intervals of new runs.
- :func:`inverse_study`: DEM parameters from bulk measurements through the fitted surfaces
  (multi-start / differential evolution; seed ch. 3 and 8.1), contours and profiles.
- :func:`feeder_study`: a loss-in-weight feeder run (PID, refills; seed Eq. 2 feed factor).
- :func:`feed_factor_study`: seed Eq. (2) fitted to feed factor vs hopper mass data.

Bad input raises ValueError naming the field or response.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

__all__ = [
    "design_study",
    "feed_factor_study",
    "feeder_study",
    "fit_models",
    "fit_study",
    "inverse_study",
]

#: resolution of the saved figures
DPI = 130


def _dir(path: str | Path) -> Path:
    p = Path(path)
    p.mkdir(parents=True, exist_ok=True)
    return p


def design_study(
    factors: Any,
    out_dir: str | Path,
    *,
    extra_runs: bool = True,
    randomize: bool = False,
    seed: int = 0,
) -> tuple[Any, dict[str, float]]:
    """The DSD of ``factors`` (factor -> levels, or a number of coded factors) written to
    ``out_dir`` (``design_coded.csv``, ``design_physical.csv``, ``correlation_map.csv/png``,
    ``design.json``); returns the design and its largest |r| per class of terms."""
    from twin_core.calibration import correlation_map, definitive_screening_design, dsd_properties
    from twin_core.calibration.plots import plot_correlation_map

    d = definitive_screening_design(factors, extra_runs=extra_runs, randomize=randomize, seed=seed)
    out = _dir(out_dir)
    d.coded.to_csv(out / "design_coded.csv")
    d.physical.to_csv(out / "design_physical.csv")
    corr = correlation_map(d.coded)
    corr.to_csv(out / "correlation_map.csv")
    plot_correlation_map(corr).savefig(out / "correlation_map.png", dpi=DPI)
    props = dsd_properties(d.coded)
    summary = {
        "runs": d.n_runs,
        "conference_order": d.conference_order,
        "fake_factors": d.n_fake,
        "max_abs_r": props,
    }
    (out / "design.json").write_text(json.dumps(summary, indent=2))
    return d, props


def fit_models(
    table: pd.DataFrame,
    factors: Sequence[str],
    responses: Sequence[str],
    *,
    terms: Sequence[str] | None = None,
    criterion: str = "aicc",
    direction: str = "both",
) -> dict[str, Any]:
    """A response surface per response: the given ``terms``, or the two-step stepwise model of
    ``factors`` (``TwoStepRSM``, by ``criterion`` and ``direction``)."""
    from twin_core.calibration import ResponseSurface, TwoStepRSM

    models: dict[str, Any] = {}
    for r in responses:
        try:
            if terms:
                models[r] = ResponseSurface(terms=list(terms)).fit(table, r)
            else:
                rsm = TwoStepRSM(list(factors), criterion=criterion, direction=direction)
                models[r] = rsm.fit(table, r).model_
        except ValueError as exc:
            raise ValueError(f"{r}: {exc}") from None
    return models


@dataclass
class FitStudy:
    """Fitted surfaces by response, their summary table, predictions of new runs (or None)."""

    models: dict[str, Any]
    summary: pd.DataFrame
    predictions: pd.DataFrame | None


def _predict(models: Mapping[str, Any], new: pd.DataFrame) -> pd.DataFrame:
    """95 % prediction intervals of every surface on new runs (``run`` column kept)."""
    parts = [new[["run"]] if "run" in new.columns else pd.DataFrame(index=new.index)]
    for k, m in models.items():
        try:
            iv = m.predict_interval(new)
        except ValueError as exc:
            raise ValueError(f"predict: {exc}") from None
        parts.append(iv.add_prefix(f"{k}:").set_index(new.index))
    return pd.concat(parts, axis=1)


def _write_fit(
    study: FitStudy, table: pd.DataFrame, factors: Sequence[str], out: Path, figures: bool
) -> None:
    from twin_core.calibration.plots import plot_parity, plot_prediction_profiles

    models = study.models
    study.summary.to_csv(out / "summary.csv", index=False)
    (out / "models.json").write_text(
        json.dumps({k: m.to_dict() for k, m in models.items()}, indent=2)
    )
    (out / "report.txt").write_text("\n\n".join(m.report() for m in models.values()))
    if figures:
        plot_parity(models).savefig(out / "parity.png", dpi=DPI)
        ranges = {f: (float(table[f].min()), float(table[f].max())) for f in factors}
        for k, m in models.items():
            if m.factors_:
                fig = plot_prediction_profiles(m, ranges)
                fig.savefig(out / f"profiler_{k}.png", dpi=DPI)
    effects = pd.concat(
        [m.effect_summary().reset_index().assign(response=k) for k, m in models.items()],
        ignore_index=True,
    )
    effects.to_csv(out / "effect_summary.csv", index=False)
    if study.predictions is not None:
        study.predictions.to_csv(out / "predictions.csv", index=False)


def fit_study(
    table: pd.DataFrame,
    factors: Sequence[str],
    responses: Sequence[str],
    out_dir: str | Path | None = None,
    *,
    terms: Sequence[str] | None = None,
    criterion: str = "aicc",
    direction: str = "both",
    predict: pd.DataFrame | None = None,
    figures: bool = True,
) -> FitStudy:
    """Surfaces of ``responses`` (:func:`fit_models`), their summary (terms, R^2, adjusted R^2,
    RMSE, SSE), predictions of ``predict``'s runs; written to ``out_dir`` when given
    (``summary.csv``, ``models.json``, ``report.txt``, ``parity.png``, ``profiler_*.png``,
    ``effect_summary.csv``, ``predictions.csv``)."""
    models = fit_models(
        table, factors, responses, terms=terms, criterion=criterion, direction=direction
    )
    summary = pd.DataFrame(
        [
            {
                "response": k,
                "terms": " + ".join("*".join(t) for t in m.terms_),
                "r2": m.r2_,
                "r2_adj": m.r2_adj_,
                "rmse": m.rmse_,
                "sse": m.sse_,
            }
            for k, m in models.items()
        ]
    )
    study = FitStudy(models, summary, None if predict is None else _predict(models, predict))
    if out_dir is not None:
        _write_fit(study, table, factors, _dir(out_dir), figures)
    return study


@dataclass
class InverseStudy:
    """The inverse calibration, its result, the fixed factors and the files written."""

    calibration: Any
    result: Any
    fixed: dict[str, float]
    files: list[str]


def inverse_study(
    table: pd.DataFrame,
    factors: Sequence[str],
    targets: Mapping[str, float],
    unknowns: Sequence[str],
    out_dir: str | Path | None = None,
    *,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    fixed: Mapping[str, float] | None = None,
    criterion: str = "aicc",
    starts: int = 64,
    method: str = "both",
    rule: str = "min_variance",
    seed: int = 0,
    contour: Sequence[str] = (),
) -> InverseStudy:
    """The ``unknowns`` that reproduce the measured ``targets`` through the surfaces fitted to
    ``table`` (bounds default to the design range, the other factors of the surfaces to their
    design mean); written to ``out_dir`` when given (``solutions.csv``, ``diagnosis.txt``,
    ``contours.png`` of the two ``contour`` unknowns, ``profiles.png``)."""
    from twin_core.calibration import InverseCalibration
    from twin_core.calibration.plots import plot_contours, plot_profiles

    models = fit_models(table, factors, list(targets), criterion=criterion)
    bnds = dict(bounds or {})
    for u in unknowns:
        if u not in table.columns:
            raise ValueError(f"unknowns: {u!r} is not a column of the table")
        bnds.setdefault(u, (float(table[u].min()), float(table[u].max())))
    used = {f for m in models.values() for f in m.factors_}
    fix = dict(fixed or {})
    for f in used - set(unknowns) - set(fix):
        fix[f] = float(table[f].mean())
    ic = InverseCalibration(models, {u: bnds[u] for u in unknowns}, fixed=fix)
    res = ic.solve(targets, n_starts=starts, method=method, seed=seed, rule=rule)
    files: list[str] = []
    if out_dir is not None:
        out = _dir(out_dir)
        res.table().to_csv(out / "solutions.csv", index=False)
        (out / "diagnosis.txt").write_text(res.diagnosis + "\n" + res.rule + "\n")
        files = ["solutions.csv", "diagnosis.txt"]
        if res.recommended is not None:
            if len(contour) == 2 and all(c in unknowns for c in contour):
                sols = [s.params for s in res.solutions]
                fig = plot_contours(
                    ic, contour[0], contour[1], res.recommended.params, targets, sols
                )
                fig.savefig(out / "contours.png", dpi=DPI)
                files.append("contours.png")
            profiles = {
                u: ic.profile(targets, u, n_points=15, n_starts=2, seed=seed) for u in unknowns
            }
            plot_profiles(profiles).savefig(out / "profiles.png", dpi=DPI)
            files.append("profiles.png")
    return InverseStudy(ic, res, fix, files)


def feeder_study(
    config: Mapping[str, Any], duration_s: float, dt_s: float, seed: int, out_dir: str | Path
) -> dict[str, Any]:
    """A LIW feeder (``schemas.feeder.FeederConfig`` fields) run for ``duration_s``: its trace
    (``trace.csv``), figure (``feeder.png``) and summary (``summary.json``: refills,
    gravimetric mean and sd of the flow, largest flow, mass dispensed), returned."""
    from schemas.feeder import FeederConfig
    from twin_core.calibration.plots import plot_feeder_trace
    from twin_core.feeder import LossInWeightFeeder

    cfg = FeederConfig(**config)  # a pydantic ValidationError is a ValueError naming the field
    trace = LossInWeightFeeder(cfg).simulate(duration_s, dt_s, seed=seed)
    out = _dir(out_dir)
    trace.to_frame().to_csv(out / "trace.csv", index=False)
    plot_feeder_trace(trace).savefig(out / "feeder.png", dpi=DPI)
    grav = ~trace.volumetric
    q = trace.mass_flow_kg_h
    summary = {
        "config": cfg.model_dump(),
        "refills": trace.refills,
        "mean_flow_kg_h_gravimetric": float(q[grav].mean()) if grav.any() else None,
        "std_flow_kg_h_gravimetric": float(q[grav].std()) if grav.any() else None,
        "max_flow_kg_h": float(q.max()),
        "dispensed_kg": trace.dispensed_kg(),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def feed_factor_study(
    data: pd.DataFrame, weight_col: str, ff_col: str, out_dir: str | Path | None = None
) -> Any:
    """Seed Eq. (2) fitted to ``ff_col`` against ``weight_col`` (``fit_feed_factor``); with
    ``out_dir``: ``fit.json`` and ``feed_factor_fit.png``. Returns the fit."""
    from twin_core.calibration.plots import plot_feed_factor_fit
    from twin_core.feeder import fit_feed_factor

    for c in (weight_col, ff_col):
        if c not in data.columns:
            raise ValueError(f"data lacks column {c!r}; it has {list(data.columns)}")
    try:
        fit = fit_feed_factor(data[weight_col], data[ff_col])
    except RuntimeError as exc:
        raise ValueError(f"fit failed: {exc}") from None
    if out_dir is not None:
        out = _dir(out_dir)
        (out / "fit.json").write_text(json.dumps(fit.as_dict(), indent=2))
        fig = plot_feed_factor_fit(
            np.asarray(data[weight_col]), np.asarray(data[ff_col]), fit, weight_col, ff_col
        )
        fig.savefig(out / "feed_factor_fit.png", dpi=DPI)
    return fit
