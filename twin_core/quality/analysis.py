"""Analysis of measured tracer profiles as one library call each (``twin rtd analyze`` and
``twin rtd funnel``): the RTD processing of ``twin_core.rtd`` carried on to lot boundaries and
funnels, hence in this package (``twin_core.rtd`` imports nothing from it).

:func:`analyze_profile`: raw moments (seed Eqs. 3-4); Hampel outliers
(``twin_core.rtd.outliers.hampel``); denoising (``twin_core.rtd.denoise``, with the seed's
metrics); truncation (``twin_core.rtd.truncation``); E(t), moments, height, FWHM, lot boundaries
(``twin_core.quality.lots``); model fits compared by AIC (``twin_core.rtd.fitting``) and the
noise of the residual (``twin_core.rtd.noise.characterize``).

:func:`profile_funnels`: the funnel plot of each profile's E(t)
(``twin_core.quality.funnel.funnel``: max outlet deviation of rectangular disturbances, seed
6.1.4.3.2) and, for two, their comparison.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["ProfileAnalysis", "analyze_profile", "json_default", "profile_funnels"]


@dataclass
class ProfileAnalysis:
    """The report of :func:`analyze_profile` (JSON-able with numpy values) and its curves."""

    report: dict[str, Any]
    processed: np.ndarray
    e: np.ndarray
    outliers: list[int] = field(default_factory=list)
    fits: list[Any] = field(default_factory=list)


def analyze_profile(
    prof: Any,
    *,
    outliers: bool = False,
    denoise: str | None = None,
    truncate: str | None = None,
    fit: str | None = None,
    scale: str = "free",
    weighted: bool = False,
) -> ProfileAnalysis:
    """Outliers, denoising, truncation, E(t) and its figures of merit, fits (module docstring).

    ``prof``: a ``twin_core.rtd.profiles.Profile``; ``denoise``: a method name or ``auto``;
    ``truncate``: ``time:S | level:C | rel:F | pat:K[@T]``; ``fit``: a model name or ``all``;
    ``scale``: ``free`` amplitude or ``fixed`` to 1; ``weighted``: two-stage fit with the
    variance model a + b y^2. Bad options raise ValueError naming them.
    """
    from twin_core.quality.lots import lot_boundaries
    from twin_core.rtd import denoise as D
    from twin_core.rtd.fitting import compare_models
    from twin_core.rtd.fitting import fit as fit_model
    from twin_core.rtd.metrics import denoise_metrics, fwhm
    from twin_core.rtd.models import MODELS
    from twin_core.rtd.noise import characterize
    from twin_core.rtd.outliers import hampel
    from twin_core.rtd.profiles import e_curve, moments
    from twin_core.rtd.truncation import parse_spec

    t, y0 = prof.t, prof.c
    report: dict[str, Any] = {"n": int(t.size), "conc_unit": prof.conc_unit}
    report["moments_raw"] = moments(t, y0).__dict__
    y = y0.copy()
    idx: list[int] = []
    if outliers:
        r = hampel(y, t=t)
        y, idx = r.y, list(r.indices)
        report["outliers"] = {
            "count": r.count,
            "indices": r.indices,
            "times": t[r.indices],
            "original": r.original,
        }
    y_clean = y.copy()
    if denoise:
        steps = np.diff(t)
        if np.ptp(steps) > 0.01 * np.median(steps):
            raise ValueError("denoise needs uniformly sampled t (steps vary by more than 1 %)")
        d = D.denoise(y, denoise)
        y = d.y
        report["denoise"] = {
            "method": d.method,
            "params": d.params,
            "risk": d.risk,
            "metrics": denoise_metrics(t, y_clean, y),
        }
    if truncate:
        spec = parse_spec(truncate)
        y = spec.apply(t, y)
        report["truncate"] = {"kind": spec.kind, "value": spec.value, "zeroed": int(np.sum(y == 0))}
    e = e_curve(t, y)
    report["moments"] = moments(t, y).__dict__
    if not report["moments"]["variance"] > 0 or np.min(y) < -0.01 * np.max(y):
        report["moments_note"] = (
            "negative values (baseline noise/offset) distort the moments and the area; "
            "consider --truncate pat:3"
        )
    report["height"] = float(np.max(y))
    report["fwhm_s"] = fwhm(t, y)
    report["lot_boundaries_s"] = list(lot_boundaries(t, np.clip(y, 0, None)))
    fits: list[Any] = []
    if fit:
        names = list(MODELS) if fit == "all" else [fit]
        sig = "auto" if weighted else None
        fits = (
            compare_models(t, e, names, scale=scale, sigma=sig)
            if len(names) > 1
            else [fit_model(t, e, names[0], scale=scale, sigma=sig)]
        )
        report["fits"] = [f.as_dict() for f in fits]
        if fits:
            resid_fit = fits[0].fitted * np.trapezoid(y, t)  # back to concentration units
            report["noise"] = characterize(t, y_clean, resid_fit).as_dict()
    return ProfileAnalysis(report, y, e, idx, fits)


def profile_funnels(
    profiles: Sequence[Any],
    durations: np.ndarray,
    intensities: np.ndarray,
    limit: float = 5.0,
    denoise: str | None = None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The funnel of each profile's E(t) by label (its name, else ``profile i``) and the
    summary: each funnel's figures of merit and, for two profiles, their comparison."""
    from twin_core.quality.funnel import compare_funnels, funnel
    from twin_core.rtd import denoise as D
    from twin_core.rtd.profiles import e_curve

    funnels: dict[str, Any] = {}
    for i, prof in enumerate(profiles):
        y = prof.c if not denoise else D.denoise(prof.c, denoise).y
        label = prof.name or f"profile {i + 1}"
        if label in funnels:
            label = f"{label} ({i + 1})"
        funnels[label] = funnel(prof.t, e_curve(prof.t, y), durations, intensities, limit)
    res: dict[str, Any] = {"funnels": {k: v.as_dict() for k, v in funnels.items()}}
    if len(funnels) == 2:
        res["comparison"] = compare_funnels(*funnels.values())
    return funnels, res


def json_default(o: object) -> object:
    """``json.dumps`` fallback for the numpy values of the RTD reports (arrays, scalars)."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(type(o))
