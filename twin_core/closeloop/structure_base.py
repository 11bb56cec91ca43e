"""What the structure searches share: the finding type, the options, the residual they search
and the evidence rules (``twin_core.closeloop.structure`` runs them).

A structure finding is a departure from the model that the candidate library cannot express:
a parameter that changes with the operating point or with time, periodic content in the
residual, or a blender response of another shape. Each is *empirical* (a description of the
data usable for prediction, not a named mechanism) and is reported only with evidence against
the declared coloured NIR noise (white + proportional + 1/f, ``twin_core.plant.nir``):

1. a search statistic on the training window, with its null distribution under that noise
   (Bonferroni over what the search tried);
2. the held-out test of the library (``twin_core.closeloop.identify.heldout_lr_test``) on
   innovations (``twin_core.closeloop.noise.NoiseWhitener``, as the library's tests): with e0
   the held-out innovations of the residual and d those of the change of prediction the
   finding makes (its numbers from the training window only), T = d'e0 / |d| is N(0, 1)
   without structure (causal whitening: e0 on the held-out window is independent of the
   training data); one-sided p = 1 - Phi(T);
3. a held-out innovation MSE drop of at least ``min_improvement`` (a finding must make the
   prediction better, not only point in the right direction).

Standard errors of linear estimates use the sandwich covariance under the declared noise,
Var(A'r) = A'CA (``NoiseWhitener.gram``: C the covariance the innovations whiten): the 1/f
part correlates the windows of a record, so estimates of different windows are not independent
and their spread is not the white-noise one.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from schemas.line import NIRNoise
from twin_core.closeloop.data import RunData
from twin_core.closeloop.identify import heldout_lr_test
from twin_core.closeloop.noise import NoiseWhitener
from twin_core.plant.model import LineModel
from twin_core.plant.nir import noise_sd
from twin_core.rtd.outliers import hampel

StructureKind = Literal["parameter_dependence", "periodic", "kernel_correction"]
KINDS: tuple[str, ...] = ("parameter_dependence", "periodic", "kernel_correction")

#: two-sided 95 % normal quantile
Z95 = 1.959963984540054


@dataclass
class StructureOptions:
    """Settings of :func:`twin_core.closeloop.structure.find_structure`.

    ``kinds``: the searches to run. ``alpha``: family-wise level of the held-out tests (split
    equally over the searches, and over the sinusoids of the periodic search);
    ``search_alpha``: level of the training-window search statistic (Bonferroni over what a
    search tries); ``min_improvement``: held-out innovation MSE drop a finding needs.
    Parameter dependence: ``groups`` windows per covariate, ``min_rel_spread`` the relative
    spread (5-95 %) a flow or screw speed needs on the training window to be a covariate,
    ``min_time_span_s`` the training span for a time dependence, ``max_laws`` the strongest
    parameter x covariate pairs (search-significant) tried on the held-out window. Periodic: multitaper
    time-bandwidth ``nw`` (2 nw - 1 tapers), ``max_sinusoids``, ``min_cycles`` in the training
    window, ``max_order``: pulses per screw revolution searched for a screw-locked pulsation
    (1..``max_order`` for every feeder with a screw speed; 0: no screw-locked search).
    Kernel: length ``kernel_s`` (None: 6 mean residence times of the model's E(t),
    120-600 s), knot spacing ``knot_s``, smoothing weights ``n_lambda``, ``cv_folds`` of
    contiguous blocks ``cv_block_s``, ``bootstrap`` replicates with blocks of
    ``bootstrap_block_s``, ``seed`` of the bootstrap.
    """

    kinds: tuple[str, ...] = KINDS
    alpha: float = 0.01
    search_alpha: float = 0.01
    min_improvement: float = 0.01
    groups: int = 4
    min_rel_spread: float = 0.05
    min_time_span_s: float = 1800.0
    max_laws: int = 3
    nw: float = 4.0
    max_sinusoids: int = 2
    min_cycles: float = 12.0
    max_order: int = 3
    kernel_s: float | None = None
    knot_s: float = 3.0
    n_lambda: int = 7
    cv_folds: int = 4
    cv_block_s: float = 300.0
    bootstrap: int = 60
    bootstrap_block_s: float = 120.0
    seed: int = 0

    def __post_init__(self) -> None:
        bad = [k for k in self.kinds if k not in KINDS]
        if bad:
            raise ValueError(f"kinds must be among {list(KINDS)}, got {bad}")
        for name in ("alpha", "search_alpha"):
            v = getattr(self, name)
            if not 0 < v < 1:
                raise ValueError(f"{name} must be in (0, 1), got {v!r}")
        if not 0 <= self.min_improvement < 1:
            raise ValueError(f"min_improvement must be in [0, 1), got {self.min_improvement!r}")
        if self.max_laws < 1:
            raise ValueError(f"max_laws must be >= 1, got {self.max_laws!r}")
        if self.groups < 3:
            raise ValueError(f"groups must be >= 3, got {self.groups!r}")
        if self.nw < 1.5:
            raise ValueError(f"nw must be >= 1.5, got {self.nw!r}")
        if self.max_order < 0:
            raise ValueError(f"max_order must be >= 0, got {self.max_order!r}")
        if self.bootstrap < 0:
            raise ValueError(f"bootstrap must be >= 0, got {self.bootstrap!r}")

    def heldout_level(self, kind: str) -> float:
        """Level of one held-out test of a search of ``kind`` (Bonferroni, see class: over
        the searches, and over the sinusoids or parameter laws a search may try)."""
        level = self.alpha / max(len(self.kinds), 1)
        tries = {"periodic": self.max_sinusoids, "parameter_dependence": self.max_laws}
        return level / tries.get(kind, 1)


@dataclass
class StructureFinding:
    """Structure beyond the candidate library, found with evidence (see module docstring).

    ``summary``: one line for a process engineer; ``evidence``: statistics, p-values,
    effective sizes, held-out improvement; ``estimates``: name -> (value, ci95_lo, ci95_hi);
    ``alternatives``: descriptions the data cannot tell apart from this one (e.g. a covariate
    moving together with the one named). ``correction(data, model)`` is the change of the
    model's predicted probe reading of the outlet that the finding implies (% w/w, on
    ``data.t_s``: add it to ``model.predict(data.inputs)``), or None.
    """

    kind: StructureKind
    summary: str
    evidence: dict[str, float]
    estimates: dict[str, tuple[float, float, float]]
    empirical: bool = True
    alternatives: list[str] = field(default_factory=list)
    #: the arrays behind the finding's figure (plots.py)
    curves: dict[str, Any] = field(default_factory=dict, repr=False)
    predictor: Callable[[RunData, LineModel], np.ndarray] | None = field(
        default=None, repr=False, compare=False
    )

    def correction(self, data: RunData, model: LineModel) -> np.ndarray | None:
        """Correction of the predicted probe reading on ``data.t_s`` (% w/w), or None."""
        return None if self.predictor is None else np.asarray(self.predictor(data, model))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (``schemas.closeloop.StructureEntry``): non-finite numbers dropped."""
        ev = {k: float(v) for k, v in self.evidence.items() if math.isfinite(float(v))}
        est = {
            k: [float(x) for x in v]
            for k, v in self.estimates.items()
            if all(math.isfinite(float(x)) for x in v)
        }
        return {
            "kind": self.kind,
            "summary": self.summary,
            "evidence": ev,
            "estimates": est,
            "empirical": bool(self.empirical),
            "alternatives": list(self.alternatives),
        }


def as_noise(noise: Any, model: LineModel) -> NIRNoise:
    """The NIR noise to test against: a ``NIRNoise``, anything with a ``.noise`` one (a
    ``twin_core.closeloop.noise.NoiseEstimate``), or None (the model's declared noise)."""
    if noise is None:
        return model.config.sensor.noise
    if isinstance(noise, NIRNoise):
        return noise
    inner = getattr(noise, "noise", None)
    if isinstance(inner, NIRNoise):
        return inner
    raise ValueError(
        f"noise must be a NIRNoise, a NoiseEstimate or None, got {type(noise).__name__}"
    )


@dataclass
class ResidualContext:
    """The residual the searches look at, with its windows and the declared noise.

    ``y``: the measurement with Hampel outliers replaced (local scale floored at the noise's
    sd, as in the identification; 0 where missing); ``train`` /
    ``held``: the windows restricted to finite samples; ``pred``: the model's prediction;
    ``sigma``: the noise standard deviation per sample (weights 1 / sigma^2); ``whiten``: the
    innovations of r / sigma under the noise, and its covariance (``NoiseWhitener.gram``).
    """

    data: RunData
    model: LineModel
    noise: NIRNoise
    y: np.ndarray
    finite: np.ndarray
    train: np.ndarray
    held: np.ndarray
    pred: np.ndarray
    sigma: np.ndarray
    whiten: NoiseWhitener

    @property
    def t(self) -> np.ndarray:
        return self.data.t_s

    @property
    def dt(self) -> float:
        return float(self.data.t_s[1] - self.data.t_s[0])

    @property
    def resid(self) -> np.ndarray:
        """measured - predicted, 0 where no sample."""
        return np.where(self.finite, self.y - self.pred, 0.0)

    @property
    def weight(self) -> np.ndarray:
        return 1.0 / self.sigma**2


def residual_context(
    data: RunData, model: LineModel, train: np.ndarray, heldout: np.ndarray, noise: Any
) -> ResidualContext:
    """Build the :class:`ResidualContext` (bad masks: ValueError naming the field)."""
    n = data.t_s.size
    masks = {}
    for name, m in (("train", train), ("heldout", heldout)):
        m = np.asarray(m, dtype=bool)
        if m.shape != (n,):
            raise ValueError(f"{name} must be a boolean mask of shape ({n},), got {m.shape}")
        masks[name] = m
    if np.any(masks["train"] & masks["heldout"]):
        raise ValueError("train and heldout must not overlap")
    nz = as_noise(noise, model)
    pred = model.predict(data.inputs)
    sigma = np.maximum(noise_sd(pred, nz), 1e-6)
    # the local scale floored at the noise's sd, as the identification cleans: without the
    # floor the 7-point MAD flags ~2.6 % of the seed noise's samples and their replacement by
    # the running median low-passes the residual (the cumulative periodogram of effect-free
    # innovations then rejects ~12 % at the 1 % level)
    cleaned = hampel(data.measured, variant="pearson", min_scale=sigma)
    finite = np.isfinite(cleaned.y)
    y = np.where(finite, cleaned.y, 0.0)
    tr, ho = masks["train"] & finite, masks["heldout"] & finite
    if tr.sum() < 60 or ho.sum() < 30:
        raise ValueError(
            f"train and heldout must hold >= 60 and >= 30 samples, got {int(tr.sum())} "
            f"and {int(ho.sum())}"
        )
    whiten = NoiseWhitener(sigma, nz, data.noise_record_n())
    return ResidualContext(data, model, nz, y, finite, tr, ho, pred, sigma, whiten)


def weighted_fit(
    ctx: ResidualContext, x: np.ndarray, target: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares of ``target`` on the columns of ``x`` over ``mask`` (weights
    1 / sigma^2): beta = (X'WX)^-1 X'W y, with its sandwich covariance under the declared
    noise, (X'WX)^-1 (WX)'C(WX) (X'WX)^-1 (White 1980; C coloured). Returns (beta, cov)."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    wx = np.where(mask[:, None], x * ctx.weight[:, None], 0.0)
    m = wx.T @ x
    minv = np.linalg.pinv(m)
    beta = minv @ (wx.T @ np.where(mask, target, 0.0))
    cov = minv @ ctx.whiten.gram(wx) @ minv
    return beta, 0.5 * (cov + cov.T)


@dataclass
class HeldoutEvidence:
    """Held-out score of a correction delta against the residual e0 (see module)."""

    z: float
    p_value: float
    rel_improvement: float
    passed: bool

    def as_dict(self) -> dict[str, float]:
        return {
            "heldout_z": self.z,
            "heldout_p_value": self.p_value,
            "heldout_rel_improvement": self.rel_improvement,
        }


def heldout_evidence(
    ctx: ResidualContext,
    delta: np.ndarray,
    level: float,
    min_improvement: float,
    e0: np.ndarray | None = None,
) -> HeldoutEvidence:
    """Held-out LR test (``heldout_lr_test``) and innovation MSE drop of the correction
    ``delta`` on the residual ``e0`` (default: the context's residual), passed when
    p < ``level`` and the drop >= ``min_improvement``. Both are whitened over the whole record
    (samples left out enter as 0) and read on the held-out window."""
    h = ctx.held
    r = ctx.resid if e0 is None else e0
    inn0 = ctx.whiten(np.where(ctx.finite, r / ctx.sigma, 0.0))[h]
    d = ctx.whiten(np.where(ctx.finite, delta / ctx.sigma, 0.0))[h]
    inn1 = inn0 - d
    z, p = heldout_lr_test(inn0, inn1)
    mse0 = float(np.mean(inn0**2))
    mse1 = float(np.mean(inn1**2))
    rel = 1.0 - mse1 / mse0 if mse0 > 0 else 0.0
    return HeldoutEvidence(float(z), float(p), rel, bool(p < level and rel >= min_improvement))


def interval(value: float, se: float, lo: float = -math.inf, hi: float = math.inf) -> tuple:
    """(value, value - 1.96 se, value + 1.96 se), the bounds clipped to [lo, hi] but never
    past the value."""
    return (
        float(value),
        float(min(value, max(lo, value - Z95 * se))),
        float(max(value, min(hi, value + Z95 * se))),
    )


def contiguous_span(mask: np.ndarray) -> slice:
    """The slice from the first to the last True of ``mask``."""
    idx = np.flatnonzero(mask)
    return slice(int(idx[0]), int(idx[-1]) + 1)
