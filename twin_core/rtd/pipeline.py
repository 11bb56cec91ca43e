"""The tracer-profile workflow: preprocessing for presentation, the fit on the raw profile.

Preprocessing follows the seed (6.1.3, 6.2.2): the baseline, Hampel outliers, denoising and
truncation give the processed profile, its empirical moments and lot boundaries and the
figure. None of it feeds the fit: the model is fitted to the raw profile by generalised
least squares with an estimated white + 1/f + proportional noise model and its own outlier
screen (``rtd.likelihood``), so that its intervals hold after the whole pipeline
(docs/rtd.md, "Intervals that cover"). The baseline is the one exception: ``auto`` fits it as
a parameter, a number fixes it, ``none`` fixes it at 0.

Every profile must come back to its baseline (``truncation.baseline_windows``): a signal that
does not is refused with an error naming it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from twin_core.rtd.denoise import DenoiseResult, denoise
from twin_core.rtd.derived import Estimate, model_average, model_grid, moment_estimates
from twin_core.rtd.likelihood import (
    TIME_LIMIT_S,
    FitTimeout,
    Ranking,
    RawFit,
    fit_candidates,
    fit_raw,
)
from twin_core.rtd.models import MODELS
from twin_core.rtd.outliers import OutlierResult, hampel
from twin_core.rtd.profiles import Moments, Profile, fill_gaps, moments
from twin_core.rtd.truncation import BaselineWindows, baseline_windows, parse_spec

__all__ = [
    "Preprocessing",
    "Processed",
    "FitSummary",
    "parse_baseline",
    "preprocess",
    "fit_profile",
    "inadequacy_warning",
]

#: a baseline larger than this fraction of the peak height is reported as "does not return
#: to zero"
ZERO_FRACTION = 0.05


def parse_baseline(text: str | float) -> str | float:
    """``auto``, ``none`` or a number (the baseline in % w/w)."""
    if isinstance(text, int | float):
        return float(text)
    key = text.strip().lower()
    if key in ("auto", "none"):
        return key
    try:
        value = float(key)
    except ValueError:
        raise ValueError(f"baseline must be auto, none or a number, got {text!r}") from None
    if not np.isfinite(value):
        raise ValueError(f"baseline must be finite, got {text!r}")
    return value


@dataclass(frozen=True)
class Preprocessing:
    """Preprocessing options: Hampel outliers, a denoise method (or None), a truncation spec
    (``truncation.parse_spec``, or None) and the baseline (auto, none or a value)."""

    outliers: bool = True
    denoise: str | None = "auto"
    truncate: str | None = "pat"
    baseline: str | float = "auto"

    @classmethod
    def none(cls) -> Preprocessing:
        """No preprocessing (a clean profile): no outliers, denoising, truncation, baseline."""
        return cls(False, None, None, "none")

    def __post_init__(self) -> None:
        object.__setattr__(self, "baseline", parse_baseline(self.baseline))
        if self.truncate is not None:
            parse_spec(self.truncate)


@dataclass
class Processed:
    """A preprocessed profile: the raw one, the baseline, the outliers replaced, denoised and
    truncated versions, and what each step did."""

    profile: Profile
    baseline: float
    baseline_source: str
    windows: BaselineWindows
    cleaned: NDArray[np.float64] = field(repr=False)
    y: NDArray[np.float64] = field(repr=False)
    outliers: OutlierResult | None = None
    denoised: DenoiseResult | None = None
    truncation: dict | None = None
    notes: list[str] = field(default_factory=list)
    measured: NDArray[np.bool_] | None = field(default=None, repr=False)
    """samples measured (False: missing in the file, interpolated; ``profiles.fill_gaps``)"""

    @property
    def t(self) -> NDArray[np.float64]:
        return self.profile.t

    @property
    def signal_name(self) -> str:
        return str(self.profile.meta.get("conc_column") or self.profile.name or "signal")

    def moments(self) -> Moments | None:
        """Empirical moments of the processed profile (None when its area is not positive)."""
        try:
            return moments(self.t, self.y)
        except ValueError:
            return None

    def as_dict(self) -> dict:
        out: dict = {
            "baseline": {
                "value": self.baseline,
                "source": self.baseline_source,
                "windows_s": {
                    "before": _span(self.t, self.windows.pre),
                    "after": _span(self.t, self.windows.post),
                },
            },
            "notes": self.notes,
        }
        if self.outliers is not None:
            idx = self.outliers.indices
            out["outliers"] = {
                "count": self.outliers.count,
                "indices": idx.tolist(),
                "times": self.t[idx].tolist(),
                "original": (self.outliers.original + self.baseline).tolist(),
            }
        if self.denoised is not None:
            out["denoise"] = {
                "method": self.denoised.method,
                "params": self.denoised.params,
                "risk": self.denoised.risk,
            }
        if self.truncation is not None:
            out["truncate"] = self.truncation
        m = self.moments()
        out["moments"] = None if m is None else m.__dict__
        return out


def _span(t: NDArray, mask: NDArray) -> list[float] | None:
    return [float(t[mask].min()), float(t[mask].max())] if mask.any() else None


def _uniform(t: NDArray, what: str) -> None:
    steps = np.diff(t)
    if np.ptp(steps) > 0.01 * np.median(steps):
        raise ValueError(f"{what} needs uniformly sampled t (steps vary by more than 1 %)")


def preprocess(profile: Profile, opts: Preprocessing | None = None) -> Processed:
    """Baseline, outliers, denoising and truncation of a profile (module docstring)."""
    opts = opts or Preprocessing()
    profile, measured = fill_gaps(profile)
    t = profile.t
    name = str(profile.meta.get("conc_column") or profile.name or "signal")
    windows = baseline_windows(t, profile.c, name)
    notes = list(profile.meta.get("warnings", []))
    if not measured.all():
        gone = t[~measured]
        notes.append(
            f"{gone.size} missing sample(s) at t = {', '.join(f'{v:g}' for v in gone[:10])}"
            f"{' ...' if gone.size > 10 else ''} s: interpolated in the processed profile, "
            "left out of the fit"
        )
    if windows.short:
        notes.append(windows.short)
    if opts.baseline == "auto":
        base = float(np.mean(profile.c[windows.both]))
        source = "estimated: mean of the samples before and after the tracer"
        if abs(base) > ZERO_FRACTION * windows.height:
            notes.append(
                f"the profile does not return to zero: its baseline {base:.4g} % w/w "
                f"({abs(base) / windows.height:.0%} of the peak height) was subtracted"
            )
    elif opts.baseline == "none":
        base, source = 0.0, "none"
    else:
        base, source = float(opts.baseline), "given"
    y = profile.c - base
    out = None
    if opts.outliers:
        out = hampel(y, t=t)
        y = out.y
    cleaned = y.copy()
    den = None
    if opts.denoise:
        _uniform(t, "denoise")
        den = denoise(y, opts.denoise)
        y = den.y
    trunc = None
    if opts.truncate:
        spec = parse_spec(opts.truncate)
        if spec.kind == "pat" and spec.t_baseline is None and windows.short:
            # a short record's window was judged on the raw profile's noise: the processed
            # profile is smoothed, and its noise estimate with it
            spec = replace(spec, t_baseline=float(t[windows.post][0]))
        y = spec.apply(t, y)
        trunc = {"kind": spec.kind, "value": spec.value, "zeroed": int(np.sum(y == 0))}
        if spec.kind == "pat":
            trunc["baseline_window_s"] = (
                _span(t, windows.post)
                if windows.short or spec.t_baseline is None
                else [spec.t_baseline, None]
            )
    return Processed(
        profile, base, source, windows, cleaned, y, out, den, trunc, notes, measured=measured
    )


@dataclass
class FitSummary:
    """The fit of a profile (the selected model when several were ranked), its derived moments
    with intervals, the model grid and the warnings to show."""

    fit: RawFit
    ranking: Ranking | None
    moments: dict[str, Estimate]
    grid: NDArray[np.float64] = field(repr=False)
    warnings: list[str] = field(default_factory=list)
    averaging: dict | None = None
    """with several candidates that fit: the models, their weights and mean residence times
    whose average is ``moments["mean_residence_time_s"]`` (``derived.model_average``)"""

    def as_dict(self) -> dict:
        out = {
            "fit": self.fit.as_dict(),
            "derived": {k: v.as_dict() for k, v in self.moments.items()},
            "warnings": self.warnings,
        }
        if self.ranking is not None:
            out["model_selection"] = self.ranking.as_dict()
        if self.averaging is not None:
            out["model_averaging"] = self.averaging
        return out


def _fit_baseline(mode: str | float) -> float | None:
    return None if mode == "auto" else 0.0 if mode == "none" else float(mode)


def inadequacy_warning(fit: RawFit) -> str:
    """The warning for a fit the lack-of-fit test rejects."""
    return (
        f"model {fit.model} does not fit the profile: lack-of-fit p = "
        f"{fit.lack_of_fit.p_value:.2g} < {fit.lack_of_fit.alpha:g} (largest deviation: "
        f"{fit.lack_of_fit.worst}); its intervals and derived quantities assume a model the data "
        "reject"
    )


def fit_profile(
    profile: Profile,
    model: str | list[str] = "ad_open",
    baseline: str | float = "auto",
    time_limit_s: float = TIME_LIMIT_S,
) -> FitSummary:
    """Fit ``model`` (a name; ``all`` or a list of names ranks those candidates by BIC) to the
    raw profile; derived moments with intervals; warnings for an inadequate fit, for a model
    the record does not identify, for candidates that failed and for those of lower BIC that
    were not selected.

    Of ranked candidates the one of lowest BIC is selected among those the record identifies
    (``Ranking.best``: no parameter on a bound of ``models.record_bounds``, no degenerate
    interval, mean residence time within the record). When two or more candidates fit
    (selectable and adequate), the mean residence time is their BIC-weighted average with an
    interval that holds the spread between them (``derived.model_average``); the selected
    model's own is kept under ``averaging``."""
    mode = parse_baseline(baseline)
    b = _fit_baseline(mode)
    ranking = None
    warnings = []
    # samples missing from the file (skipped rows) stay out of the likelihood
    profile, measured = fill_gaps(profile)
    given = None if measured.all() else measured
    t = profile.t
    if isinstance(model, str) and model != "all":
        try:
            fit = fit_raw(t, profile.c, model, b, given, time_limit_s=time_limit_s)
        except FitTimeout:
            raise ValueError(
                f"fit of {model} ran past its time limit of {time_limit_s:g} CPU s"
            ) from None
        warnings += [f"model {fit.model}: {w}" for w in fit.selection_problems()]
    else:
        names = list(MODELS) if model == "all" else list(model)
        ranking = fit_candidates(t, profile.c, names, b, given, time_limit_s)
        best = ranking.best
        keep = np.ones(t.size, bool)
        keep[best.excluded] = False
        # its own noise estimate, from the ranking's estimate (the same optimum)
        x0 = [best.params[k] for k in best.names]
        fit = fit_raw(t, profile.c, best.model, b, keep, time_limit_s=time_limit_s, x0=x0)
        for f in ranking.fits:
            if f.model == best.model:
                break
            warnings.append(
                f"candidate {f.model} (BIC {best.bic - f.bic:.3g} below the selected "
                f"{best.model}) was not selected: {ranking.excluded[f.model]}"
            )
        for m, why in ranking.failed.items():
            warnings.append(f"candidate {m} was not fitted: {why}")
    if not fit.adequate:
        warnings.insert(0, inadequacy_warning(fit))
    grid = model_grid(fit, t)
    moments = moment_estimates(fit, grid)
    mrt = moments["mean_residence_time_s"].value
    if not t[0] < mrt < t[-1]:
        warnings.insert(
            0,
            f"model {fit.model}: its mean residence time {mrt:.4g} s lies outside the record "
            f"[{t[0]:.4g}, {t[-1]:.4g}] s, which does not identify it",
        )
    averaging = None
    if ranking is not None:
        averaging = _average_mrt(ranking, fit, moments)
        if averaging is not None:
            moments["mean_residence_time_s"] = averaging.pop("estimate")
    return FitSummary(fit, ranking, moments, grid, warnings, averaging)


def _average_mrt(ranking: Ranking, fit: RawFit, moments: dict[str, Estimate]) -> dict | None:
    """The mean residence time averaged over the candidates that fit (selectable and adequate,
    BIC weights renormalised among them; ``derived.model_average``), the selected model's own
    estimate standing for its candidate. None when fewer than two candidates fit."""
    fits, weights = ranking.averaged()
    if len(fits) < 2:
        return None
    est = [
        moments["mean_residence_time_s"] if f.model == fit.model else ranking.mrt[f.model]
        for f in fits
    ]
    try:
        avg = model_average(est, weights, fit.alpha)
    except ValueError:
        return None
    return {
        "estimate": avg,
        "method": "BIC weights of the candidates that fit (selectable, adequate); "
        "unconditional variance (Burnham & Anderson 2002, Eq. 6.12); model-averaged "
        "tail-area interval (Turek & Fletcher 2012)",
        "models": [
            {"model": f.model, "weight": w, "mean_residence_time_s": e.as_dict()}
            for f, w, e in zip(fits, weights, est)
        ],
        "selected_model_mean_residence_time_s": moments["mean_residence_time_s"].as_dict(),
    }
