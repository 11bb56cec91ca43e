"""Fits on the raw profile by generalised least squares with an estimated noise covariance.

Measurement model of a tracer profile on times t_i (uniform step):

    y_i = b + A E(t_i; theta) + e_i,   Cov(e) = Sigma = s_w^2 I + s_p^2 C + k^2 diag(s_i^2),

with b the baseline (fitted, fixed to 0 or to a given value), A the amplitude (area of the
profile), s = A E the signal, s_w white noise, s_p 1/f (pink) noise of correlation C and k
the proportional coefficient (seed 6.1.3.2; ``rtd.noise``). C is the Toeplitz correlation
of a 1/f spectrum on the frequencies j / (F T), j = 1 .. F N / 2, of a record F = 4 times
the record length T (power below 1/T shows as an offset and a drift, which the baseline and
the correlation carry). Outliers are left out of the likelihood (rows and columns dropped).

The variance components (s_w^2, s_p^2, k^2) are estimated by restricted maximum likelihood
(REML, Patterson & Thompson 1971; Harville 1977, JASA 72, 320) on the residual of the
current fit, with the fixed-effect design X = [J, B]: the model's Jacobian J and a B-spline
basis B spanning the signal region. Projecting out B keeps a systematic misfit (a tail the
model cannot follow) out of the noise estimate; it then shows up in the lack-of-fit test
instead of widening the intervals. Then theta is fitted by generalised least squares
(``scipy.optimize.least_squares`` on the residual whitened by the Cholesky factor L of
Sigma, L^-1 (y - mu)), and the covariance is (J^T Sigma^-1 J)^-1 (Seber & Wild 1989,
"Nonlinear Regression", ch. 2.8; two rounds of estimated GLS, Carroll & Ruppert 1988).

Lack of fit: with e = L^-1 (y - mu_hat) and W = L^-1 [J, B], the drop of the whitened
residual sum of squares when the spline basis is added, D = |P_W e|^2 (a score test against
a smooth alternative; e is orthogonal to L^-1 J at the optimum), is compared with its null
distribution: F = (D / q) / ((|e|^2 - D) / (n - p - q)) ~ F(q, n - p - q), q = rank W - rank
L^-1 J (Seber & Wild 1989, ch. 9.5; Hart 1997, "Nonparametric Smoothing and Lack-of-Fit
Tests"). Because the noise covariance includes the 1/f part, slow noise is not mistaken for a
misfit; a p-value below ``LACK_OF_FIT_ALPHA`` marks the fit inadequate.

A stagnant zone exchanging with the flow (a long, low tail) is tested as follows. For a model
nested in an extension by an exchanging zone (``EXCHANGE_EXTENSION``: AD open-open in AD with
a dead volume of ratio r >= 0 and exchange time tau_x, r = 0 giving AD), the test is the
likelihood ratio LR = chi2(model) - chi2(extension) of two GLS fits under one covariance
Sigma: the REML estimate of the noise under the LARGER model, with the extension's fitted
signal in its proportional part (a covariance that followed each model's own signal would
add ln|Sigma| and variance-function differences that the null below does not hold). With the noise estimated under the model
itself, the exchange tail is partly absorbed by the 1/f component (its misfit is slow) and
the test loses its power; under the extension the tail is in the mean and the noise estimate
is that of the noise. The null distribution is not chi2: r = 0 lies on the boundary (Self &
Liang 1987, JASA 82, 605: a 50:50 mixture of chi2_0 and chi2_1 for a known tau_x) and tau_x
is not identified at r = 0 (Davies 1977, Biometrika 64, 247; 1987, 74, 33). Under both, LR
tends to sup over tau_x of max(0, Z(tau_x))^2 with Z the standardized score process in the
directions dE/dr at r = 0 (``exchange_directions``), whitened and orthogonal to the model's
Jacobian (Andrews 2001, Econometrica 69, 683). Its covariance is known from those directions;
the p-value is the share of ``EXCHANGE_DRAWS`` draws of that Gaussian process on a grid of
``EXCHANGE_SCALES`` exchange times exceeding LR (Hansen 1996, Econometrica 64, 413), the
squared score in each direction j divided by a draw of its estimated noise scale v_j:
chi2_{nu_j} / nu_j with nu_j Satterthwaite's for that direction, joined across directions by
a Gaussian copula from the REML information (a slow exchange leans on the 1/f component,
whose estimate is the least certain, nu_j ~ 10-15 on the benchmark's record; a fast one on
the white and proportional parts, nu_j ~ 50-200; one nu for the whole span made the test
liberal at twice the seed's noise). This test replaces the linearised "tail" F test for such models; the noncentrality
that bounds the power of any test of a given zone is the whitened misfit |L^-1 (mu_ext -
mu_AD)|^2 of the best AD fit to it (docs/rtd.md gives it for the benchmark's zones).

Information criteria use the Gaussian log-likelihood with the same Sigma for every candidate:
-2 ln L = n ln(2 pi) + ln|Sigma| + e^T e; AICc = -2 ln L + 2p + 2p(p+1)/(n - p - 1),
BIC = -2 ln L + p ln n (Burnham & Anderson 2002). Since Sigma holds the correlation, the
likelihood counts correlated samples as the information they carry (no separate effective
sample size is needed).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import linalg, special, stats
from scipy.interpolate import BSpline
from scipy.ndimage import median_filter
from scipy.optimize import least_squares, minimize
from scipy.signal import fftconvolve

from twin_core.rtd.fitting import initial_guess
from twin_core.rtd.models import (
    DELAYS,
    TIME_CONSTANT_MAX_RECORDS,
    TIME_CONSTANT_MIN_STEPS,
    TIME_CONSTANTS,
    ModelSpec,
    get_model,
    record_bounds,
)

__all__ = [
    "NoiseModel",
    "LackOfFit",
    "DeviationTest",
    "exchange_directions",
    "RawFit",
    "Satterthwaite",
    "pink_correlation",
    "spline_basis",
    "estimate_noise",
    "fit_raw",
    "fit_candidates",
    "Ranking",
    "FitTimeout",
    "LACK_OF_FIT_ALPHA",
    "weighted_bonferroni",
    "LACK_OF_FIT_WEIGHTS",
    "lack_of_fit_levels",
    "TIME_LIMIT_S",
    "degenerate_interval",
]

#: significance level of the lack-of-fit test
LACK_OF_FIT_ALPHA = 0.01
#: shares of that level among the tests (weighted Bonferroni: test i has level
#: alpha w_i / sum of the w of the tests present). The exchange test carries the power
#: against a stagnant zone and gets 4/5 (0.8 %), the shape test 1/5 (0.2 %; docs/rtd.md)
LACK_OF_FIT_WEIGHTS = {"shape": 1.0, "tail": 1.0, "exchange": 4.0}
#: default limit of one model's fit, in CPU seconds of the process (``time.process_time``:
#: the same on a loaded and an idle machine)
TIME_LIMIT_S = 30.0
#: record-length factor F of the 1/f correlation (lowest frequency 1 / (F T))
PINK_RECORD_FACTOR = 4
#: falling thresholds of the model-based outlier screen (|z| of the leave-one-out prediction
#: error; 0.27 % of Gaussian samples exceed 3) and the extra rounds at the last one
OUTLIER_STEPS = (6.0, 4.5, 3.0)
OUTLIER_REPEATS = 2
#: number of cubic B-splines of the lack-of-fit alternative
SPLINE_COUNT = 6
#: models nested in an extension by an exchanging stagnant zone (volume ratio r_dead >= 0,
#: exchange time tau_x; the extension's parameters are the model's plus these two, r_dead = 0
#: gives the model): their "tail" test is the likelihood ratio against the extension
EXCHANGE_EXTENSION = {"ad_open": "ad_open_dead"}
#: starts of the extension's fit: (r_dead, tau_x in units of the signal's mean - onset)
EXCHANGE_STARTS = ((0.2, 1.0), (0.2, 3.0))
#: exchange times of the grid of the likelihood ratio's null distribution (units as above)
EXCHANGE_SCALES = tuple(float(x) for x in np.geomspace(0.05, 20.0, 25))
#: Monte Carlo draws of that null distribution and their seed (a reproducible p-value; its
#: Monte Carlo sd at p = 1 % is 0.07 %)
EXCHANGE_DRAWS = 20_000
EXCHANGE_SEED = 20_250_117


#: a parameter within this share of its scale (the sampling step for times, 1 otherwise) of a
#: bound sits on it (``RawFit.on_bound``)
BOUND_TOL = 1e-3
#: a parameter whose Jacobian column holds more than this share of its squared norm in one
#: sample has a derivative taken across a jump of the model (``_spiky``)
SPIKE_SHARE = 0.5
#: bisections that place the end of a profile-likelihood interval between two scan points
PROFILE_BISECTIONS = 12
#: a parameter whose whitened Jacobian column lies this close to the span of the others is
#: not identified to first order (``_unidentified``)
IDENTIFY_TOL = 1e-4
#: relative singular value below which a direction of the REML design is dropped
REML_RANK_TOL = 1e-6
#: profile-likelihood scan: first step (share of the sampling step for times, of max(|value|,
#: 1e-3) otherwise), steps before they grow by PROFILE_GROWTH each, most steps per side
PROFILE_FIRST_STEP = 0.05
PROFILE_LINEAR_STEPS = 20
PROFILE_GROWTH = 1.5
PROFILE_MAX_STEPS = 60


class FitTimeout(RuntimeError):
    """Raised inside a fit that ran past its time limit."""


@dataclass(frozen=True)
class NoiseModel:
    """Variance components of the measurement noise (concentration units squared; k^2)."""

    white_var: float
    pink_var: float
    prop_var: float

    def covariance(self, corr: NDArray, signal: NDArray) -> NDArray[np.float64]:
        """Sigma = s_w^2 I + s_p^2 C + k^2 diag(s^2) (module docstring)."""
        cov = self.pink_var * corr
        cov[np.diag_indices_from(cov)] += self.white_var + self.prop_var * signal**2
        return cov

    def as_dict(self) -> dict[str, float]:
        return {
            "sigma_white": float(np.sqrt(self.white_var)),
            "sigma_pink": float(np.sqrt(self.pink_var)),
            "k_proportional": float(np.sqrt(self.prop_var)),
        }


@dataclass(frozen=True)
class DeviationTest:
    """F test of the residual against one family of deviations (statistic, degrees of freedom,
    p-value)."""

    name: str
    statistic: float
    df: tuple[int, float]
    p_value: float

    def as_dict(self) -> dict:
        return {
            "statistic": self.statistic,
            "df": [self.df[0], self.df[1]],
            "p_value": self.p_value,
        }


def lack_of_fit_levels(names: list[str], alpha: float = LACK_OF_FIT_ALPHA) -> dict[str, float]:
    """Level of each lack-of-fit test of ``names`` in a weighted Bonferroni procedure of
    overall level ``alpha``: alpha w_i / sum_j w_j with the weights ``LACK_OF_FIT_WEIGHTS``
    (1 for a test not listed); the family-wise error is at most alpha (Holm 1979)."""
    w = {k: LACK_OF_FIT_WEIGHTS.get(k, 1.0) for k in names}
    total = sum(w.values())
    return {k: alpha * v / total for k, v in w.items()}


def weighted_bonferroni(
    p_values: Mapping[str, float], alpha: float = LACK_OF_FIT_ALPHA
) -> tuple[float, str | None]:
    """Combined p-value of the named tests, min(1, min_i p_i alpha / level_i) with each test's
    level from :func:`lack_of_fit_levels` (Holm 1979), and the test attaining it (1 and None
    when there is none)."""
    if not p_values:
        return 1.0, None
    levels = lack_of_fit_levels(list(p_values), alpha)
    worst = min(p_values, key=lambda k: p_values[k] / levels[k])
    return float(min(1.0, p_values[worst] * alpha / levels[worst])), worst


@dataclass(frozen=True)
class LackOfFit:
    """Lack-of-fit tests of a fit (module docstring); the fit is adequate when no test's
    p-value is below its share of ``alpha`` (weighted Bonferroni, ``LACK_OF_FIT_WEIGHTS``:
    the combined p-value is min_i p_i W / w_i, W the sum of the weights; Holm 1979,
    Scand. J. Stat. 6, 65)."""

    tests: tuple[DeviationTest, ...]
    alpha: float
    noise: NoiseModel
    """noise estimated with the deviations in the design (free of a misfit)"""

    @property
    def levels(self) -> dict[str, float]:
        """Each test's level: its weight's share of ``alpha``."""
        return lack_of_fit_levels([x.name for x in self.tests], self.alpha)

    @property
    def p_value(self) -> float:
        return weighted_bonferroni({x.name: x.p_value for x in self.tests}, self.alpha)[0]

    @property
    def worst(self) -> str | None:
        """The test with the smallest p-value relative to its level."""
        return weighted_bonferroni({x.name: x.p_value for x in self.tests}, self.alpha)[1]

    @property
    def adequate(self) -> bool:
        return bool(self.p_value >= self.alpha)

    @property
    def method(self) -> str:
        tail = (
            "the likelihood ratio against the model with an exchanging stagnant zone (noise "
            "estimated under it; null: sup of the one-sided score process)"
            if any(x.name == "exchange" for x in self.tests)
            else "F test against a stagnant-zone tail (linearised)"
        )
        return (
            "F test of the GLS residual against smooth deviations (cubic splines) and "
            f"{tail}; white + 1/f + proportional noise, Satterthwaite df, weighted Bonferroni"
        )

    def as_dict(self) -> dict:
        return {
            "adequate": self.adequate,
            "p_value": self.p_value,
            "alpha": self.alpha,
            "levels": self.levels,
            "method": self.method,
            "tests": {x.name: x.as_dict() for x in self.tests},
        }


@dataclass(frozen=True)
class Satterthwaite:
    """Degrees of freedom of a variance c^T Cov c whose Cov = (J^T Sigma^-1 J)^-1 depends on
    estimated noise components phi: nu = 2 v^2 / (g^T I^-1 g), g_j = dv/dphi_j =
    u^T dSigma_j u with u = Sigma^-1 J Cov c, I the REML information of phi (Satterthwaite
    1946; Kenward & Roger 1997, Biometrics 53, 983)."""

    sens: NDArray[np.float64] = field(repr=False)
    corr: NDArray[np.float64] = field(repr=False)
    sig2: NDArray[np.float64] = field(repr=False)
    info_inv: NDArray[np.float64] = field(repr=False)

    def df(self, c: NDArray, cov: NDArray) -> float:
        var = float(c @ cov @ c)
        u = self.sens @ c
        g = np.array([u @ u, u @ (self.corr @ u), np.sum(u**2 * self.sig2)])
        var_v = float(g @ self.info_inv @ g)
        return 2.0 * var**2 / var_v if var_v > 0 else float("inf")


@dataclass
class RawFit:
    """A model fitted to the raw profile: estimates, covariance, noise, adequacy, criteria."""

    model: str
    names: tuple[str, ...]
    params: dict[str, float]
    cov: NDArray[np.float64] = field(repr=False)
    noise: NoiseModel
    lack_of_fit: LackOfFit
    chi2: float
    n: int
    loglik: float
    aicc: float
    bic: float
    success: bool
    message: str
    seconds: float
    fitted: NDArray[np.float64] = field(repr=False)
    dof: Satterthwaite = field(repr=False)
    excluded: NDArray[np.intp] = field(repr=False)
    """samples left out of the likelihood (given outliers and those the fit flagged)"""
    alpha: float = 0.05
    lower: NDArray[np.float64] | None = field(default=None, repr=False)
    """bounds of the fitted parameters (``names`` order; the record's, ``models.record_bounds``)"""
    upper: NDArray[np.float64] | None = field(default=None, repr=False)
    step_s: float = 1.0
    """the record's sampling step"""
    profile_ci: dict[str, tuple[float, float]] = field(default_factory=dict)
    """profile-likelihood intervals of the parameters whose Wald interval is degenerate"""
    wald_ci: dict[str, tuple[float, float]] = field(default_factory=dict)
    """the degenerate Wald intervals that ``profile_ci`` replaced"""

    @property
    def k(self) -> int:
        return len(self.names)

    @property
    def on_bound(self) -> dict[str, float]:
        """The model's parameters that sit on a bound (within ``BOUND_TOL`` of its scale: the
        sampling step for times, 1 otherwise), with that bound: the record does not identify
        them (:func:`models.record_bounds`), or a fraction / volume ratio is at 0 or 1 (the
        model reduces to a smaller one). A delay at 0 (no dead time) is a state of the system,
        not a bound of the record, and is not listed."""
        if self.lower is None or self.upper is None:
            return {}
        out = {}
        for i, name in enumerate(get_model(self.model).params):
            v = self.params[name]
            unit = self.step_s if name in DELAYS or name in TIME_CONSTANTS else 1.0
            for b in (self.lower[i], self.upper[i]):
                if not np.isfinite(b) or abs(v - b) > BOUND_TOL * max(abs(b), unit):
                    continue
                if name in DELAYS and b == 0.0:
                    continue
                out[name] = float(b)
        return out

    @property
    def degenerate(self) -> dict[str, tuple[float, float]]:
        """The model's parameters whose interval (after the profile-likelihood replacement) is
        degenerate (:func:`degenerate_interval`), with it."""
        ci = self.ci
        return {k: ci[k] for k in get_model(self.model).params if degenerate_interval(ci[k])}

    @property
    def identified(self) -> bool:
        """No parameter on a bound and no degenerate interval: the fit may be selected."""
        return not self.on_bound and not self.degenerate

    def identification_notes(self) -> list[str]:
        """Why the fit may not be selected (:meth:`selection_problems`), and which intervals
        come from the profile likelihood, in words."""
        out = self.selection_problems()
        for k, (lo, hi) in self.wald_ci.items():
            plo, phi = self.profile_ci[k]
            out.append(
                f"the Wald interval of {k} was degenerate ([{lo:.6g}, {hi:.6g}], width "
                f"{hi - lo:.2g}); its interval [{plo:.6g}, {phi:.6g}] is the profile likelihood's"
            )
        return out

    def selection_problems(self) -> list[str]:
        """Why the fit may not be selected, in words: parameters on a bound, degenerate
        intervals (empty when :attr:`identified`)."""
        out = []
        for k, b in self.on_bound.items():
            out.append(
                f"{k} = {self.params[k]:.4g} sits on its bound {b:.4g} (the record identifies "
                f"time constants within {TIME_CONSTANT_MIN_STEPS:g} sampling step and "
                f"{TIME_CONSTANT_MAX_RECORDS:g} x its length, delays up to its end)"
            )
        for k, (lo, hi) in self.degenerate.items():
            out.append(f"the interval of {k} is degenerate ([{lo:.6g}, {hi:.6g}])")
        return out

    @property
    def stderr(self) -> dict[str, float]:
        se = np.sqrt(np.clip(np.diag(self.cov), 0.0, None))
        return {k: float(v) for k, v in zip(self.names, se)}

    @property
    def theta(self) -> NDArray[np.float64]:
        """The model's parameters (without amplitude and baseline), in the model's order."""
        return np.array([self.params[k] for k in get_model(self.model).params])

    def theta_cov(self) -> NDArray[np.float64]:
        p = len(get_model(self.model).params)
        return self.cov[:p, :p]

    def interval(
        self, value: float, grad: ArrayLike, log_scale: bool = False
    ) -> tuple[float, float]:
        """Wald interval of a function g of the parameters with gradient ``grad``: value +/-
        t_nu SE, SE^2 = grad^T Cov grad, nu Satterthwaite's; ``log_scale`` (g > 0) builds it
        for ln g, value exp(+/- t_nu SE / value), which stays positive and follows the skew."""
        c = np.asarray(grad, dtype=float)
        se = float(np.sqrt(max(c @ self.cov @ c, 0.0)))
        nu = self.dof.df(c, self.cov)
        level = 1 - self.alpha / 2
        q = float(stats.t.ppf(level, nu)) if np.isfinite(nu) else float(stats.norm.ppf(level))
        if log_scale and value > 0:
            return float(value * np.exp(-q * se / value)), float(value * np.exp(q * se / value))
        return float(value - q * se), float(value + q * se)

    @property
    def ci(self) -> dict[str, tuple[float, float]]:
        """Intervals of the parameters (:meth:`interval`); parameters bounded below by 0 (times,
        Pe, n, amplitude) on the log scale; the profile likelihood's where the Wald interval is
        degenerate (``profile_ci``)."""
        eye = np.eye(self.k)
        return {
            k: self.profile_ci.get(k) or self.interval(self.params[k], eye[i], k in _POSITIVE)
            for i, k in enumerate(self.names)
        }

    @property
    def adequate(self) -> bool:
        return self.lack_of_fit.adequate

    def as_dict(self) -> dict:
        return {
            "model": self.model,
            "params": self.params,
            "stderr": self.stderr,
            "ci": {k: list(v) for k, v in self.ci.items()},
            "confidence": 1 - self.alpha,
            "adequate": self.adequate,
            "lack_of_fit": self.lack_of_fit.as_dict(),
            "noise": self.noise.as_dict(),
            "chi2": self.chi2,
            "n": self.n,
            "excluded": self.excluded.tolist(),
            "loglik": self.loglik,
            "aicc": self.aicc,
            "bic": self.bic,
            "success": self.success,
            "message": self.message,
            "seconds": self.seconds,
            "identified": self.identified,
            "on_bound": self.on_bound,
            "profile_likelihood_ci": {k: list(v) for k, v in self.profile_ci.items()},
            "degenerate_wald_ci": {k: list(v) for k, v in self.wald_ci.items()},
            "identification": self.identification_notes(),
        }


def degenerate_interval(ci: tuple[float, float]) -> bool:
    """An interval is degenerate when it is not finite or has no width."""
    lo, hi = ci
    return bool(not (np.isfinite(lo) and np.isfinite(hi)) or hi <= lo)


#: parameters with a lower bound of 0 whose intervals are built on the log scale
_POSITIVE = frozenset({"tau", "pe", "n", "tau_cstr", "sigma", "tau_e", "b", "c", "scale"})


def pink_correlation(n: int, factor: int | None = None) -> NDArray[np.float64]:
    """Toeplitz correlation (n x n) of 1/f noise sampled at unit step: c(m) proportional to
    sum_j cos(2 pi j m / (F n)) / j over j = 1 .. F n / 2, c(0) = 1 (Wiener-Khinchin)."""
    factor = PINK_RECORD_FACTOR if factor is None else factor
    if n < 2 or factor < 1:
        raise ValueError(f"n must be >= 2 and factor >= 1, got {n!r}, {factor!r}")
    m = factor * n
    spec = np.zeros(m // 2 + 1)
    j = np.arange(1, spec.size)
    spec[1:] = 1.0 / j
    acf = np.fft.irfft(spec, m)[:n]
    return linalg.toeplitz(acf / acf[0])


def spline_basis(
    t: NDArray[np.float64], start: float, stop: float, count: int = SPLINE_COUNT
) -> NDArray[np.float64]:
    """``count`` cubic B-splines with uniform knots on [start, stop], zero outside."""
    if not stop > start or count < 4:
        raise ValueError(f"need stop > start and count >= 4, got {start!r}, {stop!r}, {count!r}")
    inner = np.linspace(start, stop, count - 2)
    h = inner[1] - inner[0]
    knots = np.concatenate(
        [inner[0] - h * np.arange(3, 0, -1), inner, inner[-1] + h * np.arange(1, 4)]
    )
    out = np.empty((t.size, count))
    for i in range(count):
        out[:, i] = BSpline.basis_element(knots[i : i + 5], extrapolate=False)(t)
    out = np.nan_to_num(out)
    out[(t < start) | (t > stop)] = 0.0
    keep = np.any(out != 0, axis=0)
    return out[:, keep]


def _neg2_loglik(
    eta: NDArray,
    r: NDArray,
    x: NDArray,
    corr: NDArray,
    corr_lower: NDArray,
    sig2: NDArray,
    restricted: bool,
) -> tuple[float, NDArray]:
    """-2 x the (restricted, or profile ML) Gaussian log-likelihood of the residual r with
    the columns of x projected out, up to n ln(2 pi), and its gradient in eta = log var:

    -2 l = ln|Sigma| [+ ln|X^T Sigma^-1 X|] + r^T P r,
    P = Sigma^-1 - Sigma^-1 X K X^T Sigma^-1, K = (X^T Sigma^-1 X)^-1,
    d(-2 l)/d var_i = tr(M dSigma_i) - r^T P dSigma_i P r,  M = P (REML) or Sigma^-1 (ML)
    (Harville 1977). ``corr_lower`` is corr with the strict lower triangle doubled and the
    upper zeroed, so that sum(lower(Sigma^-1) * corr_lower) = tr(Sigma^-1 corr)."""
    w, p, k = np.exp(eta)
    cov = p * corr
    cov[np.diag_indices_from(cov)] += w + k * sig2
    try:
        cf = linalg.cho_factor(cov, lower=True, check_finite=False)
        vx = linalg.cho_solve(cf, x, check_finite=False)
        kf = linalg.cho_factor(x.T @ vx, lower=True, check_finite=False)
    except linalg.LinAlgError:
        return 1e300, np.zeros(3)
    inv_low, info = linalg.lapack.dpotri(cf[0], lower=1)  # lower triangle of Sigma^-1
    if info != 0:
        return 1e300, np.zeros(3)
    vxk = linalg.cho_solve(kf, vx.T, check_finite=False).T  # Sigma^-1 X K
    pr = linalg.cho_solve(cf, r, check_finite=False) - vxk @ (vx.T @ r)
    diag_inv = np.diag(inv_low)
    tr_inv = (float(np.sum(diag_inv)), float(np.sum(inv_low * corr_lower)), float(diag_inv @ sig2))
    if restricted:
        # tr(Sigma^-1 X K X^T Sigma^-1 D) for D = I, C, diag(sig2)
        tr_x = (
            float(np.sum(vxk * vx)),
            float(np.sum(vxk * (corr @ vx))),
            float(np.sum(vxk * vx * sig2[:, None])),
        )
        tr_m = np.subtract(tr_inv, tr_x)
    else:
        tr_m = np.array(tr_inv)
    logdet = 2 * np.sum(np.log(np.diag(cf[0])))
    if restricted:
        logdet += 2 * np.sum(np.log(np.diag(kf[0])))
    quad = np.array([pr @ pr, pr @ (corr @ pr), np.sum(pr**2 * sig2)])
    return float(logdet + r @ pr), (tr_m - quad) * np.exp(eta)


def _lower_weights(corr: NDArray) -> NDArray[np.float64]:
    """corr with the strict lower triangle doubled and the upper triangle zeroed."""
    out = np.tril(corr, -1) * 2.0
    out[np.diag_indices_from(out)] = np.diag(corr)
    return out


def estimate_noise(
    r: ArrayLike,
    x: ArrayLike,
    corr: ArrayLike,
    signal: ArrayLike,
    start: NoiseModel | None = None,
    restricted: bool = True,
    tol: float = 1e-9,
) -> tuple[NoiseModel, float]:
    """(noise model, -2 log-likelihood at it): REML (``restricted``) or profile ML estimate of
    (s_w^2, s_p^2, k^2) from the residual ``r`` of a fit with fixed-effect design ``x``
    (columns projected out), 1/f correlation ``corr`` and signal (module docstring). Each
    component is bounded below by 1e-8 of the residual variance; ``tol`` is the relative
    tolerance on -2 ln L (L-BFGS-B ``ftol``)."""
    rr = np.asarray(r, dtype=float)
    # an orthonormal basis of the design's column space (the REML likelihood depends on that
    # space only, up to a constant): a design with nearly collinear columns (a parameter the
    # data do not identify) would make ln|X^T Sigma^-1 X| meaningless
    xx = _span(np.asarray(x, dtype=float), REML_RANK_TOL)
    cc = np.asarray(corr, dtype=float)
    sig2 = np.asarray(signal, dtype=float) ** 2
    v = float(np.var(rr)) or 1e-12
    s2 = float(np.mean(sig2)) or 1.0
    if start is None:
        start = NoiseModel(0.5 * v, 0.3 * v, 1e-3 * v / s2)
    lo = np.log(1e-8 * v) - np.log([1.0, 1.0, s2])
    hi = np.log(100 * v) - np.log([1.0, 1.0, s2])
    # every component starts at >= 1 % of the residual variance: on the log scale a component
    # at its lower bound has a vanishing gradient and would stay there
    eta0 = np.log(
        np.maximum(
            [start.white_var, start.pink_var, start.prop_var], 0.01 * v / np.array([1.0, 1.0, s2])
        )
    )
    res = minimize(
        _neg2_loglik,
        np.clip(eta0, lo, hi),
        args=(rr, xx, cc, _lower_weights(cc), sig2, restricted),
        jac=True,
        method="L-BFGS-B",
        bounds=list(zip(lo, hi)),
        options={"ftol": tol},
    )
    w, p, k = np.exp(res.x)
    return NoiseModel(float(w), float(p), float(k)), float(res.fun) + rr.size * np.log(2 * np.pi)


@dataclass(frozen=True)
class _Mean:
    """mu(x) = b + A E(t; theta), x = (theta, A[, b]); b is fitted when ``baseline`` is None."""

    spec: ModelSpec
    t: NDArray[np.float64]
    baseline: float | None

    @property
    def names(self) -> tuple[str, ...]:
        return self.spec.params + ("scale",) + (("baseline",) if self.baseline is None else ())

    def split(self, x: NDArray) -> tuple[NDArray, float, float]:
        p = len(self.spec.params)
        b = float(x[p + 1]) if self.baseline is None else self.baseline
        return x[:p], float(x[p]), b

    def signal(self, x: NDArray) -> NDArray[np.float64]:
        theta, a, _ = self.split(x)
        return a * self.spec.func(self.t, *theta)

    def __call__(self, x: NDArray) -> NDArray[np.float64]:
        return self.signal(x) + self.split(x)[2]

    def jac(self, x: NDArray) -> NDArray[np.float64]:
        theta, a, _ = self.split(x)
        e = self.spec.func(self.t, *theta)
        if self.spec.jac is not None:
            je = self.spec.jac(self.t, *theta)
        else:
            je = np.empty((self.t.size, theta.size))
            upper = self.bounds()[1]
            for i, v in enumerate(theta):
                h = 1e-6 * max(abs(v), 1e-3)
                if v + h > upper[i]:  # backward difference at an upper bound
                    h = -h
                tp = theta.copy()
                tp[i] = v + h
                je[:, i] = (self.spec.func(self.t, *tp) - e) / h
        cols = [a * je, e[:, None]]
        if self.baseline is None:
            cols.append(np.ones((self.t.size, 1)))
        return np.hstack(cols)

    def bounds(self) -> tuple[NDArray, NDArray]:
        """The model's parameters within what the record identifies (``models.record_bounds``),
        amplitude >= 0, baseline free."""
        plo, phi = record_bounds(self.spec, self.t)
        lo = list(plo) + [0.0] + ([-np.inf] if self.baseline is None else [])
        hi = list(phi) + [np.inf] + ([np.inf] if self.baseline is None else [])
        return np.array(lo, float), np.array(hi, float)


def _least_squares(
    resid,
    jac,
    x0: NDArray,
    bounds: tuple[NDArray, NDArray],
    deadline: float,
    robust_scale: float | None = None,
) -> object:
    """``least_squares`` (TRF) that raises FitTimeout past ``deadline`` (process_time); with
    ``robust_scale`` the Cauchy loss of that scale (outliers lose their pull)."""

    def guarded(x: NDArray) -> NDArray:
        if time.process_time() > deadline:
            raise FitTimeout("time limit")
        return resid(x)

    lo, hi = bounds
    pad = 1e-9 * np.maximum(1.0, np.abs(np.where(np.isfinite(lo), lo, 0.0)))
    x0 = np.clip(x0, lo + pad, hi - np.where(np.isfinite(hi), pad, 0.0))
    if robust_scale is None:
        return least_squares(guarded, x0, jac=jac, bounds=bounds, method="trf", x_scale="jac")
    return least_squares(
        guarded,
        x0,
        jac=jac,
        bounds=bounds,
        method="trf",
        x_scale="jac",
        loss="cauchy",
        f_scale=robust_scale,
    )


def _whitener(cov: NDArray) -> NDArray[np.float64]:
    return linalg.cholesky(cov, lower=True, check_finite=False)


def _signal_window(t: NDArray, s: NDArray) -> tuple[float, float]:
    """[start, stop] of the spline alternative: the 0.1-99.9 % mass range w of the fitted
    signal, widened by w/4 before and w after (a longer tail than the model's), clipped to t."""
    pos = np.clip(s, 0.0, None)
    f = np.concatenate([[0.0], np.cumsum(0.5 * (pos[1:] + pos[:-1]) * np.diff(t))])
    if not f[-1] > 0:
        return float(t[0]), float(t[-1])
    f /= f[-1]
    a = float(np.interp(0.001, f, t))
    b = float(np.interp(0.999, f, t))
    w = max(b - a, 3 * float(np.median(np.diff(t))))
    return max(float(t[0]), a - 0.25 * w), min(float(t[-1]), b + w)


def exchange_directions(
    t: NDArray[np.float64], signal: NDArray[np.float64], scales: tuple[float, ...] = (0.5, 1.0, 2.0)
) -> NDArray[np.float64]:
    """Directions in which a small stagnant zone (volume ratio r -> 0, exchange time tau_x)
    changes a fitted signal s(t): with the mobile-immobile substitution s -> s (1 + r / (1 +
    s tau_x)) of the transfer function (van Genuchten & Wierenga 1976),
    dE/dr at r = 0 is d/dt[(-t s) * exp(-t / tau_x) / tau_x] (convolution). One column per
    tau_x = scale x (mean of s - its onset); t uniform."""
    dt = float(np.median(np.diff(t)))
    if not np.any(signal > 0):
        return np.zeros((t.size, 0))
    span = _signal_span(t, signal)
    cols = []
    for scale in scales:
        lag = np.arange(t.size) * dt
        kernel = np.exp(-lag / (scale * span)) / (scale * span)
        conv = fftconvolve(-t * signal, kernel)[: t.size] * dt
        cols.append(np.gradient(conv, t))
    return np.column_stack(cols)


def _deviation_test(
    name: str, e: NDArray, uj: NDArray, bw: NDArray, lsolve, d_sigma, info_inv: NDArray
) -> DeviationTest:
    """F = |U^T e|^2 / q for the whitened deviations bw orthogonal to the model's span uj, with
    Satterthwaite df nu = 2 / Var(v), v(phi) = tr(U^T L^-1 Sigma(phi) L^-T U) / q the noise
    scale in the tested subspace (1 at the estimate; Var by the REML information)."""
    perp = bw - uj @ (uj.T @ bw)
    u = _span(perp)
    q = u.shape[1]
    if q < 1:
        return DeviationTest(name, 0.0, (0, float("inf")), 1.0)
    stat = float(np.sum((u.T @ e) ** 2)) / q
    nu = _scale_df(lsolve(u), d_sigma, info_inv)
    p = float(stats.f.sf(stat, q, nu)) if np.isfinite(nu) else float(stats.chi2.sf(stat * q, q))
    return DeviationTest(name, stat, (q, float(nu)), p)


def _scale_gradients(lu: NDArray, d_sigma) -> NDArray[np.float64]:
    """g_jc = u_j^T L^-1 dSigma_c L^-T u_j for each whitened unit column u_j (``lu`` = L^-T U)
    and noise component c: the gradient of the noise scale v_j(phi) = u_j^T L^-1 Sigma(phi)
    L^-T u_j in direction j (v_j = 1 at the estimate; Sigma linear in phi). Shape (q, 3)."""
    return np.column_stack([np.sum(lu * (d @ lu), axis=0) for d in d_sigma])


def _scale_df(lu: NDArray, d_sigma, info_inv: NDArray) -> float:
    """Satterthwaite df nu = 2 / Var(v) of the noise scale v(phi) = tr(U^T L^-1 Sigma(phi)
    L^-T U) / q in the subspace of the q orthonormal whitened columns U (``lu`` = L^-T U;
    v = 1 at the estimate), Var(v) = g^T I^-1 g with g the mean of :func:`_scale_gradients`
    over the columns and ``info_inv`` the inverse REML information of the noise components."""
    g = np.mean(_scale_gradients(lu, d_sigma), axis=0)
    var_v = float(g @ info_inv @ g)
    return 2.0 / var_v if var_v > 0 else float("inf")


def _alternatives(t: NDArray, signal: NDArray, mask: NDArray) -> dict[str, NDArray]:
    """The deviation families of the lack-of-fit test for a fitted signal (rows kept)."""
    return {
        "shape": spline_basis(t, *_signal_window(t, signal))[mask],
        "tail": exchange_directions(t, signal)[mask],
    }


def _reml_information_inverse(
    chol: NDArray,
    design: NDArray,
    corr: NDArray,
    sig: NDArray,
    noise: NoiseModel,
    bound_known: bool = True,
) -> NDArray[np.float64]:
    """Inverse REML information of (s_w^2, s_p^2, k^2), I_jk = tr(P dSigma_j P dSigma_k) / 2
    with P the projection of the design. With ``bound_known`` components estimated at their
    lower bound carry no sampling variance (rows and columns zero: the intervals); without,
    every component keeps the variance of its information (the lack-of-fit tests: a 1/f
    component that REML put at its bound under the spline alternative is not known to be 0,
    and its uncertainty is the noise scale's in the smooth directions the tests look at)."""
    d_sigma = (np.eye(sig.size), corr, np.diag(sig**2))
    inv = linalg.cho_solve((chol, True), np.eye(sig.size), check_finite=False)
    vx = inv @ design
    proj = inv - vx @ np.linalg.pinv(design.T @ vx) @ vx.T
    pd = [proj @ d for d in d_sigma]
    info = 0.5 * np.array([[np.sum(a * b.T) for b in pd] for a in pd])
    share = np.array([noise.white_var, noise.pink_var, noise.prop_var * np.mean(sig**2)])
    active = share > 1e-3 * share.sum() if bound_known else np.ones(3, bool)
    out = np.zeros((3, 3))
    out[np.ix_(active, active)] = np.linalg.pinv(info[np.ix_(active, active)])
    return out


def _lack_of_fit(
    e: NDArray,
    chol: NDArray,
    jac: NDArray,
    alternatives: dict[str, NDArray],
    corr: NDArray,
    sig: NDArray,
    noise: NoiseModel,
) -> tuple[DeviationTest, ...]:
    """F tests of the whitened residual e (Cholesky factor ``chol`` of Sigma) of a fit with
    Jacobian ``jac`` against each family of deviations; the REML information of the noise
    components is taken with every family in the design, as the noise was estimated (module
    docstring)."""
    d_sigma = (np.eye(e.size), corr, np.diag(sig**2))
    design = np.hstack([jac, *alternatives.values()])

    def white(a: NDArray) -> NDArray:
        return linalg.solve_triangular(chol, a, lower=True, check_finite=False)

    def lsolve(a: NDArray) -> NDArray:
        return linalg.solve_triangular(chol.T, a, lower=False, check_finite=False)

    info_inv = _reml_information_inverse(chol, design, corr, sig, noise, bound_known=False)
    uj = _span(white(jac))
    return tuple(
        _deviation_test(name, e, uj, white(b), lsolve, d_sigma, info_inv)
        for name, b in alternatives.items()
        if b.shape[1]
    )


def _signal_span(t: NDArray, signal: NDArray) -> float:
    """Mean of the positive signal minus its onset (first sample above 5 % of the peak), at
    least two steps: the time unit of the exchange times; t uniform."""
    pos = np.clip(signal, 0.0, None)
    if not pos.max() > 0:
        return float(t[-1] - t[0])
    mean = float(np.sum(t * pos) / np.sum(pos))
    onset = float(t[np.argmax(pos > 0.05 * pos.max())])
    return max(mean - onset, 2.0 * float(np.median(np.diff(t))))


def _fit_extension(
    ext: _Mean,
    x_base: NDArray,
    y: NDArray,
    mask: NDArray,
    corr_full: NDArray,
    noise: NoiseModel,
    signal: NDArray,
    deadline: float,
) -> tuple[NDArray, NoiseModel]:
    """The extension fitted from the base estimates (fitted ``signal``) with each of
    ``EXCHANGE_STARTS`` under the base noise model, then from the best with its own noise
    estimate (one REML + GLS round). Returns (parameters, noise model of the extension)."""
    p = len(ext.spec.params) - 2
    span = _signal_span(ext.t, signal)
    best, best_cost = None, np.inf
    for r0, k in EXCHANGE_STARTS:
        x0 = np.concatenate([x_base[:p], [r0, k * span], x_base[p:]])
        x, _, _, res = _gls_round(ext, y, mask, corr_full, x0, noise, False, deadline, tol=1e-6)
        if res.cost < best_cost:
            best, best_cost = x, res.cost
    x, nm, _, _ = _gls_round(ext, y, mask, corr_full, best, noise, True, deadline)
    return x, nm


def _direction_scales(
    grad: NDArray, info_inv: NDArray, rng: np.random.Generator
) -> NDArray[np.float64]:
    """Draws (q x ``EXCHANGE_DRAWS``) of the estimated noise scales v_j of q directions:
    chi2_{nu_j} / nu_j marginals (Satterthwaite, nu_j = 2 / s_j^2, s_j^2 = g_j^T I^-1 g_j with
    g_j the rows of ``grad``, :func:`_scale_gradients`) joined by a Gaussian copula whose
    correlation is that of g_j^T delta, delta ~ N(0, I^-1) the error of the REML estimate of
    the noise components (``info_inv`` = I^-1): directions that lean on the same component
    move together. v_j = 1 where s_j = 0 (a known scale)."""
    evals, evecs = np.linalg.eigh(info_inv)
    half = evecs * np.sqrt(np.clip(evals, 0.0, None))
    lin = grad @ half  # g_j^T delta = lin_j . h, h ~ N(0, I)
    sd = np.linalg.norm(lin, axis=1)
    h = rng.standard_normal((lin.shape[1], EXCHANGE_DRAWS))
    out = np.ones((grad.shape[0], EXCHANGE_DRAWS))
    var = sd > 1e-12
    nu = 2.0 / sd[var] ** 2
    w = (lin[var] @ h) / sd[var, None]
    out[var] = special.chdtri(nu[:, None], special.ndtr(-w)) / nu[:, None]
    return np.clip(out, 1e-12, None)


def _sup_null_pvalue(
    stat: float, dirs: NDArray, grad: NDArray | None = None, info_inv: NDArray | None = None
) -> float:
    """P(sup_j max(0, z_j)^2 / v_j >= stat) for z = N^T g, g ~ N(0, I), N the unit columns
    ``dirs``, and v_j the estimated noise scale in direction j, independent of z
    (:func:`_direction_scales` from ``grad`` and ``info_inv``; v_j = 1 when not given), by
    ``EXCHANGE_DRAWS`` Monte Carlo draws with a fixed seed. Each direction has its own scale
    because they lean on different noise components: a slow exchange on the 1/f part, whose
    estimate is the least certain, a fast one on the white and proportional parts."""
    u, sv, vt = np.linalg.svd(dirs, full_matrices=False)
    keep = sv > 1e-10 * sv[0]
    rng = np.random.default_rng(EXCHANGE_SEED)
    w = rng.standard_normal((int(keep.sum()), EXCHANGE_DRAWS))
    z = np.clip(vt[keep].T @ (sv[keep, None] * w), 0.0, None) ** 2
    if grad is not None and info_inv is not None:
        z /= _direction_scales(grad, info_inv, rng)
    sup = np.max(z, axis=0)
    return float((1 + np.count_nonzero(sup >= stat)) / (1 + EXCHANGE_DRAWS))


def _exchange_test(
    mean: _Mean,
    x_base: NDArray,
    y: NDArray,
    mask: NDArray,
    corr_full: NDArray,
    noise: NoiseModel,
    deadline: float,
) -> DeviationTest:
    """Likelihood-ratio test of ``mean`` against its extension by an exchanging stagnant zone
    (module docstring): noise estimated under the extension, one covariance Sigma for both
    models (that noise model with the extension's fitted signal in its proportional part),
    both refitted by GLS under it, LR = chi2_model - chi2_extension (>= 0); the p-value from
    the null distribution sup over tau_x of max(0, Z(tau_x))^2 / v_j of the score process Z
    along the r_dead -> 0 directions (:func:`exchange_directions`) at the model's estimate,
    whitened by the same Sigma, with each direction's estimated noise scale v_j
    (:func:`_sup_null_pvalue`). Returns LR with the Satterthwaite df of the span."""
    ext = _Mean(get_model(EXCHANGE_EXTENSION[mean.spec.name]), mean.t, mean.baseline)
    x_e, nm = _fit_extension(ext, x_base, y, mask, corr_full, noise, mean.signal(x_base), deadline)
    corr = corr_full[np.ix_(mask, mask)]
    sig = ext.signal(x_e)[mask]
    chol = _whitener(nm.covariance(corr, sig))
    fit_e = _gls_whitened(ext, y, mask, chol, x_e, deadline)
    fit_b = _gls_whitened(mean, y, mask, chol, x_base, deadline)
    stat = max(0.0, 2.0 * (float(fit_b.cost) - float(fit_e.cost)))
    x_b, x_e = fit_b.x, fit_e.x
    jm = mean.jac(x_b)[mask]
    dirs = exchange_directions(mean.t, mean.signal(x_b), EXCHANGE_SCALES)[mask]

    def white(a: NDArray) -> NDArray:
        return linalg.solve_triangular(chol, a, lower=True, check_finite=False)

    uj = _span(white(jm))
    dw = white(dirs)
    perp = dw - uj @ (uj.T @ dw)
    norm = np.linalg.norm(perp, axis=0)
    perp = perp[:, norm > 1e-8 * norm.max()] / norm[norm > 1e-8 * norm.max()]
    lu = linalg.solve_triangular(chol.T, perp, lower=False, check_finite=False)
    d_sigma = (np.eye(sig.size), corr, np.diag(sig**2))
    info_inv = _reml_information_inverse(chol, ext.jac(x_e)[mask], corr, sig, nm, bound_known=False)
    nu = _scale_df(linalg.solve_triangular(chol.T, _span(perp), lower=False), d_sigma, info_inv)
    p = _sup_null_pvalue(stat, perp, _scale_gradients(lu, d_sigma), info_inv)
    return DeviationTest("exchange", stat, (1, float(nu)), p)


def _span(a: NDArray, rtol: float = 1e-8) -> NDArray[np.float64]:
    """Orthonormal basis of the column space of ``a`` (SVD, relative tolerance ``rtol``)."""
    u, sv, _ = np.linalg.svd(a, full_matrices=False)
    return u[:, sv > rtol * sv[0]] if sv.size and sv[0] > 0 else u[:, :0]


def _spiky(jac: NDArray, count: int) -> list[int]:
    """Indices among the first ``count`` columns of the Jacobian ``jac`` that hold more than
    ``SPIKE_SHARE`` of their squared norm in a single sample: the derivative was taken across
    a jump of the model (a delay before a CSTR or a bypass moves a sample from 0 to the jump's
    height), so the Wald interval claims a precision no record has."""
    sq = jac[:, :count] ** 2
    total = sq.sum(axis=0)
    return [i for i in range(count) if total[i] > 0 and sq[:, i].max() > SPIKE_SHARE * total[i]]


def _unidentified(jw: NDArray, count: int) -> list[int]:
    """Indices among the first ``count`` columns of the whitened Jacobian ``jw`` that lie in
    the span of the other columns to within ``IDENTIFY_TOL`` (relative norm of the part
    orthogonal to them): the likelihood does not tell that parameter from the others to
    first order (e.g. a plug-flow delay before a CSTR shifts the exponential exactly as its
    amplitude scales it; only the jump's position carries the delay), so its Wald interval
    means nothing."""
    out = []
    for i in range(count):
        col = jw[:, i]
        norm = float(np.linalg.norm(col))
        others = _span(np.delete(jw, i, axis=1))
        rest = col - others @ (others.T @ col)
        if not norm > 0 or float(np.linalg.norm(rest)) < IDENTIFY_TOL * norm:
            out.append(i)
    return out


def _criteria(chi2: float, logdet: float, n: int, p: int) -> tuple[float, float, float]:
    """(log-likelihood, AICc, BIC) of a GLS fit (module docstring)."""
    ll = -0.5 * (n * np.log(2 * np.pi) + logdet + chi2)
    aicc = -2 * ll + 2 * p + 2 * p * (p + 1) / max(n - p - 1, 1)
    bic = -2 * ll + p * np.log(n)
    return float(ll), float(aicc), float(bic)


def _difference_scale(y: NDArray) -> float:
    """Robust scale of the sample-to-sample noise: 1.4826 MAD of the first differences / sqrt 2
    (the signal changes little between samples; Rice 1984)."""
    d = np.diff(y)
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


def _gls_round(
    mean: _Mean,
    y: NDArray,
    mask: NDArray,
    corr_full: NDArray,
    x: NDArray,
    noise: NoiseModel | None,
    estimate: bool,
    deadline: float,
    tol: float = 1e-9,
) -> tuple[NDArray, NoiseModel, NDArray, object]:
    """One round: the noise re-estimated by REML at x (when ``estimate``), then the GLS fit.
    Returns (x, noise, Cholesky factor of Sigma at the start x, least-squares result)."""
    corr = corr_full[np.ix_(mask, mask)]
    ym = y[mask]
    sig = mean.signal(x)[mask]
    if estimate:
        noise, _ = estimate_noise(ym - mean(x)[mask], mean.jac(x)[mask], corr, sig, noise, tol=tol)
    chol = _whitener(noise.covariance(corr, sig))
    res = _gls_whitened(mean, y, mask, chol, x, deadline)
    return res.x, noise, chol, res


def _gls_whitened(
    mean: _Mean, y: NDArray, mask: NDArray, chol: NDArray, x: NDArray, deadline: float
) -> object:
    """GLS fit from x under the fixed covariance L L^T (``chol``): least squares of the
    whitened residual L^-1 (mu(x) - y) over the kept samples; ``res.cost`` is chi2 / 2."""
    ym = y[mask]

    def resid(v: NDArray) -> NDArray:
        return linalg.solve_triangular(chol, mean(v)[mask] - ym, lower=True, check_finite=False)

    def jac(v: NDArray) -> NDArray:
        return linalg.solve_triangular(chol, mean.jac(v)[mask], lower=True, check_finite=False)

    return _least_squares(resid, jac, x, mean.bounds(), deadline)


def _conditional_outliers(chol: NDArray, r: NDArray, z_crit: float) -> NDArray[np.intp]:
    """Indices whose residual, given all the others, is improbable: z_i = (Sigma^-1 r)_i /
    sqrt((Sigma^-1)_ii) is the standardized leave-one-out prediction error of a Gaussian
    vector (Haslett & Hayes 1998, Int. Stat. Rev. 66, 1); flagged when |z_i| > ``z_crit``."""
    inv_low, info = linalg.lapack.dpotri(chol, lower=1)
    if info != 0:
        return np.zeros(0, dtype=np.intp)
    pr = linalg.cho_solve((chol, True), r, check_finite=False)
    z = pr / np.sqrt(np.diag(inv_low))
    return np.nonzero(np.abs(z) > z_crit)[0].astype(np.intp)


def _profile_interval(
    mean: _Mean,
    y: NDArray,
    mask: NDArray,
    chol: NDArray,
    x: NDArray,
    i: int,
    level: float,
    step_s: float,
    deadline: float,
) -> tuple[float, float]:
    """Profile-likelihood interval of parameter ``i``: {v : chi2_p(v) - min chi2_p <= q},
    q = chi2_1 quantile at ``level``, chi2_p(v) the GLS chi2 under the fixed covariance L L^T
    (``chol``) with x_i = v and every other parameter refitted (Venzon & Moolgavkar 1988;
    Seber & Wild 1989, ch. 5.4). Scanned outwards from x_i, in steps of
    ``PROFILE_FIRST_STEP`` (of the sampling step for a time) that grow by ``PROFILE_GROWTH``
    after ``PROFILE_LINEAR_STEPS``, each fit starting from its neighbour's; the end is placed
    between the last point inside and the first outside by ``PROFILE_BISECTIONS`` bisections
    (a model with a jump at its delay has a profile with steps at the sample times), or is
    the bound reached."""
    ym = y[mask]
    lo_b, hi_b = mean.bounds()
    free = np.arange(x.size) != i
    q = float(stats.chi2.ppf(level, 1))
    name = mean.names[i]
    unit = step_s if name in DELAYS or name in TIME_CONSTANTS else max(abs(x[i]), 1e-3)

    def full(v: NDArray, value: float) -> NDArray:
        z = np.empty_like(x)
        z[free] = v
        z[i] = value
        return z

    def chi2_at(value: float, start: NDArray) -> tuple[float, NDArray]:
        def resid(v: NDArray) -> NDArray:
            return linalg.solve_triangular(
                chol, mean(full(v, value))[mask] - ym, lower=True, check_finite=False
            )

        def jac(v: NDArray) -> NDArray:
            return linalg.solve_triangular(
                chol, mean.jac(full(v, value))[mask][:, free], lower=True, check_finite=False
            )

        res = _least_squares(resid, jac, start, (lo_b[free], hi_b[free]), deadline)
        return 2.0 * float(res.cost), res.x

    c0, _ = chi2_at(x[i], x[free])
    ends = []
    for sign in (-1.0, 1.0):
        start, last_in = x[free], float(x[i])
        step, offset, end = PROFILE_FIRST_STEP * unit, 0.0, None
        for k in range(PROFILE_MAX_STEPS):
            if k >= PROFILE_LINEAR_STEPS:
                step *= PROFILE_GROWTH
            offset += step
            value = float(np.clip(x[i] + sign * offset, lo_b[i], hi_b[i]))
            c, nxt = chi2_at(value, start)
            c0 = min(c0, c)
            if c - c0 > q:
                inside, outside = last_in, value
                for _ in range(PROFILE_BISECTIONS):
                    mid = 0.5 * (inside + outside)
                    cm, xm = chi2_at(mid, start)
                    if cm - c0 > q:
                        outside = mid
                    else:
                        inside, start = mid, xm
                end = 0.5 * (inside + outside)
                break
            last_in, start = value, nxt
            if value in (lo_b[i], hi_b[i]):
                end = value
                break
        ends.append(last_in if end is None else end)
    return float(min(ends)), float(max(ends))


def _check_uniform(t: NDArray) -> None:
    steps = np.diff(t)
    if np.ptp(steps) > 0.01 * np.median(steps):
        raise ValueError(
            "t must be uniformly sampled for the noise model (steps vary by "
            f"{np.ptp(steps) / np.median(steps):.1%}), got steps {steps.min():g}-{steps.max():g} s"
        )


def _starts(mean: _Mean, y: NDArray, keep: NDArray) -> list[NDArray]:
    """Initial vectors: the model's moment-based starts from a median-smoothed copy above the
    baseline guess (median of the last quarter of the record) with the samples below 5 % of
    its peak zeroed (noise in the tail would inflate the moments), the amplitude its area, and
    the baseline guess."""
    t = mean.t
    b0 = (
        float(np.median(y[keep][-max(keep.sum() // 4, 3) :]))
        if mean.baseline is None
        else mean.baseline
    )
    above = median_filter(np.where(keep, y, np.median(y)) - b0, size=5, mode="nearest")
    above[above < 0.05 * above.max()] = 0.0
    area = float(np.trapezoid(above, t))
    out = []
    for x in initial_guess(mean.spec, t, above):
        v = np.append(x, area)
        out.append(np.append(v, b0) if mean.baseline is None else v)
    return out


def _check_converged(mean: _Mean, x: NDArray, y: NDArray, mask: NDArray) -> None:
    """ValueError when the fitted curve lost the profile: its area on the record is below
    1 % of the area of the data above the baseline, or a parameter is not finite."""
    sig = mean.signal(x)
    data = np.clip(y - mean.split(x)[2], 0.0, None)
    a_fit = float(np.trapezoid(np.where(mask, sig, 0.0), mean.t))
    a_data = float(np.trapezoid(np.where(mask, data, 0.0), mean.t))
    if not (np.all(np.isfinite(x)) and a_fit >= 0.01 * a_data):
        raise ValueError(
            f"fit of {mean.spec.name} did not converge: its curve holds {a_fit:.3g} of the "
            f"profile's area {a_data:.3g} (parameters {np.round(x, 4).tolist()})"
        )


def fit_raw(
    t: ArrayLike,
    y: ArrayLike,
    model: str | ModelSpec = "ad_open",
    baseline: float | None = None,
    keep: ArrayLike | None = None,
    noise: NoiseModel | None = None,
    alpha: float = 0.05,
    lack_of_fit_alpha: float = LACK_OF_FIT_ALPHA,
    time_limit_s: float = TIME_LIMIT_S,
    x0: ArrayLike | None = None,
    screen: bool = True,
    extension: bool = True,
) -> RawFit:
    """Fit ``model`` to the raw concentration profile (t, y) by GLS with the noise model of the
    module docstring; ``baseline`` None fits b, a number fixes it; ``keep`` (bool mask) drops
    outliers from the likelihood and ``screen`` adds those the fit finds (module docstring);
    ``noise`` given skips its estimation (a common noise model for comparing candidates);
    ``extension`` tests a model of ``EXCHANGE_EXTENSION`` against its extension by a
    stagnant zone (another ``time_limit_s``; if that fit fails, the linearised tail test
    stays). Raises FitTimeout past ``time_limit_s`` CPU seconds."""
    t0 = time.perf_counter()
    deadline = time.process_time() + time_limit_s
    spec = model if isinstance(model, ModelSpec) else get_model(model)
    tt = np.asarray(t, dtype=float)
    yy = np.asarray(y, dtype=float)
    if tt.ndim != 1 or tt.shape != yy.shape:
        raise ValueError(f"t and y must be 1-D of equal shape, got {tt.shape} and {yy.shape}")
    if not (np.all(np.isfinite(tt)) and np.all(np.isfinite(yy))):
        raise ValueError("t and y must be finite, got NaN or inf")
    _check_uniform(tt)
    mask = np.ones(tt.size, bool) if keep is None else np.asarray(keep, bool)
    mean = _Mean(spec, tt, baseline)
    p = len(mean.names)
    n = int(mask.sum())
    if n <= p + SPLINE_COUNT + 2:
        raise ValueError(
            f"need more than {p + SPLINE_COUNT + 2} points to fit {spec.name}, got {n}"
        )
    corr_full = pink_correlation(tt.size)
    bounds = mean.bounds()

    # 1. unweighted robust fit (multi-start, Cauchy loss at the white-noise scale) to start from
    if x0 is None:
        best = None
        scale = max(_difference_scale(yy[mask]), 1e-12 * float(np.ptp(yy)))
        for x in _starts(mean, yy, mask):
            r = _least_squares(
                lambda v: mean(v)[mask] - yy[mask],
                lambda v: mean.jac(v)[mask],
                x,
                bounds,
                deadline,
                scale,
            )
            if best is None or r.cost < best.cost:
                best = r
        x = best.x
    else:
        x = np.asarray(x0, dtype=float)
    # 2. noise estimation (REML) and GLS, screening outliers at falling thresholds (a large
    # outlier inflates the first noise estimate and would hide the smaller ones)
    nm = noise
    for z in (*OUTLIER_STEPS, *(OUTLIER_STEPS[-1],) * OUTLIER_REPEATS) if screen else ():
        x, nm, chol, res = _gls_round(
            mean, yy, mask, corr_full, x, nm, noise is None, deadline, tol=1e-6
        )
        flagged = _conditional_outliers(chol, yy[mask] - mean(x)[mask], z)
        if flagged.size:
            mask = mask.copy()
            mask[np.nonzero(mask)[0][flagged]] = False
        elif z == OUTLIER_STEPS[-1]:
            break
    x, nm, chol, res = _gls_round(mean, yy, mask, corr_full, x, nm, noise is None, deadline)
    corr = corr_full[np.ix_(mask, mask)]
    ym = yy[mask]
    n = int(mask.sum())
    _check_converged(mean, x, yy, mask)
    # 3. covariance, lack of fit, criteria at the final estimate
    sig = mean.signal(x)[mask]
    jm = mean.jac(x)[mask]
    chol = _whitener(nm.covariance(corr, sig))
    e = linalg.solve_triangular(chol, ym - mean(x)[mask], lower=True, check_finite=False)
    jw = linalg.solve_triangular(chol, jm, lower=True, check_finite=False)
    cov = np.linalg.pinv(jw.T @ jw)
    sens = linalg.solve_triangular(chol.T, jw, lower=False, check_finite=False) @ cov
    dof = Satterthwaite(sens, corr, sig**2, _reml_information_inverse(chol, jm, corr, sig, nm))
    chi2 = float(e @ e)
    logdet = 2.0 * float(np.sum(np.log(np.diag(chol))))
    ll, aicc, bic = _criteria(chi2, logdet, n, p)
    alternatives = _alternatives(tt, mean.signal(x), mask)
    noise_alt = nm
    if noise is None:
        design = np.hstack([jm, *alternatives.values()])
        noise_alt, _ = estimate_noise(ym - mean(x)[mask], design, corr, sig, nm)
    chol_alt = _whitener(noise_alt.covariance(corr, sig))
    e_alt = linalg.solve_triangular(chol_alt, ym - mean(x)[mask], lower=True, check_finite=False)
    lof = _lack_of_fit(e_alt, chol_alt, jm, alternatives, corr, sig, noise_alt)
    if extension and spec.name in EXCHANGE_EXTENSION:
        try:
            exchange = _exchange_test(
                mean, x, yy, mask, corr_full, noise_alt, time.process_time() + time_limit_s
            )
            lof = (*(d for d in lof if d.name != "tail"), exchange)
        except (FitTimeout, ValueError, np.linalg.LinAlgError, FloatingPointError):
            pass  # the extension could not be fitted: the linearised tail test stays
    out = RawFit(
        model=spec.name,
        names=mean.names,
        params={k: float(v) for k, v in zip(mean.names, x)},
        cov=cov,
        noise=nm,
        lack_of_fit=LackOfFit(lof, lack_of_fit_alpha, noise_alt),
        chi2=chi2,
        n=n,
        loglik=ll,
        aicc=aicc,
        bic=bic,
        success=bool(res.success),
        message=str(res.message),
        seconds=time.perf_counter() - t0,
        fitted=mean(x),
        dof=dof,
        excluded=np.nonzero(~mask)[0].astype(np.intp),
        alpha=alpha,
        lower=bounds[0],
        upper=bounds[1],
        step_s=float(np.median(np.diff(tt))),
    )
    # 4. a Wald interval from a derivative across a jump of the model (``_spiky``), degenerate,
    # or of a parameter not identified to first order gets the profile likelihood's interval;
    # in the covariance that parameter gets the variance (half its width / z)^2 and no
    # covariance with the others (its Jacobian column tells nothing of them), for derived
    # quantities; not for a fit on a bound (it is not selected)
    if not out.on_bound:
        _profile_degenerate(out, mean, yy, mask, chol, jw, deadline + time_limit_s)
    return out


def _profile_degenerate(
    fit: RawFit,
    mean: _Mean,
    y: NDArray,
    mask: NDArray,
    chol: NDArray,
    jw: NDArray,
    deadline: float,
) -> None:
    """Step 4 of :func:`fit_raw` (its comment), in place on ``fit``."""
    level = 1 - fit.alpha / 2
    z = float(stats.norm.ppf(level))
    x = np.array([fit.params[k] for k in fit.names])
    count = len(mean.spec.params)
    flat = set(_unidentified(jw, count)) | set(_spiky(mean.jac(x)[mask], count))
    cov = fit.cov
    for i, name in enumerate(mean.spec.params):
        se = float(np.sqrt(max(cov[i, i], 0.0)))
        ci = (x[i] - z * se, x[i] + z * se)
        if i not in flat and not degenerate_interval(ci):
            continue
        try:
            pci = _profile_interval(mean, y, mask, chol, x, i, 1 - fit.alpha, fit.step_s, deadline)
        except (FitTimeout, ValueError, np.linalg.LinAlgError, FloatingPointError):
            continue
        fit.wald_ci[name], fit.profile_ci[name] = ci, pci
        cov = cov.copy()
        cov[i, :] = cov[:, i] = 0.0
        cov[i, i] = ((pci[1] - pci[0]) / (2.0 * z)) ** 2
    fit.cov = cov


@dataclass
class Ranking:
    """Candidate models fitted with one noise model on the same samples, ranked by BIC, with
    BIC weights w_i = exp(-dBIC_i / 2) / sum_j exp(-dBIC_j / 2) (Burnham & Anderson 2002,
    ch. 6.4) and the candidates that failed or ran out of time."""

    fits: list[RawFit]
    weights: list[float]
    failed: dict[str, str]
    excluded: dict[str, str] = field(default_factory=dict)
    """candidates fitted but not selectable, with the reason: a parameter on a bound of what
    the record identifies, a degenerate interval, a mean residence time outside the record"""
    mrt: dict = field(default_factory=dict)
    """each fitted candidate's mean residence time (``derived.Estimate``), by model"""

    @property
    def best(self) -> RawFit:
        """The candidate of lowest BIC that is not ``excluded``."""
        if not self.fits:
            raise ValueError(f"no candidate model could be fitted: {self.failed!r}")
        for f in self.fits:
            if f.model not in self.excluded:
                return f
        raise ValueError(
            "no candidate model is identified by the record: "
            + "; ".join(f"{k}: {v}" for k, v in self.excluded.items())
        )

    def averaged(self) -> tuple[list[RawFit], list[float]]:
        """The candidates that may be averaged (selectable and adequate) with their BIC
        weights renormalised among them (Burnham & Anderson 2002, ch. 4.2)."""
        keep = [
            (f, w)
            for f, w in zip(self.fits, self.weights)
            if f.model not in self.excluded and f.adequate
        ]
        if not keep:
            return [], []
        total = sum(w for _, w in keep)
        if not total > 0:
            return [keep[0][0]], [1.0]
        return [f for f, _ in keep], [w / total for _, w in keep]

    def as_dict(self) -> dict:
        b0 = self.fits[0].bic if self.fits else 0.0
        return {
            "criterion": "BIC of the GLS likelihood (white + 1/f + proportional noise, common "
            "to all candidates)",
            "ranking": [
                {
                    "model": f.model,
                    "parameters": f.k,
                    "bic": f.bic,
                    "delta_bic": f.bic - b0,
                    "aicc": f.aicc,
                    "weight": w,
                    "adequate": f.adequate,
                    "lack_of_fit_p": f.lack_of_fit.p_value,
                    "seconds": f.seconds,
                    "selectable": f.model not in self.excluded,
                    "not_selected_because": self.excluded.get(f.model),
                    "mean_residence_time_s": (
                        self.mrt[f.model].as_dict() if f.model in self.mrt else None
                    ),
                }
                for f, w in zip(self.fits, self.weights)
            ],
            "failed": self.failed,
            "selection_rule": "lowest BIC among the candidates whose parameters are inside what "
            "the record identifies (none on a bound), whose intervals are not degenerate and "
            "whose mean residence time and its interval lie within the record",
        }


def fit_candidates(
    t: ArrayLike,
    y: ArrayLike,
    models: list[str],
    baseline: float | None = None,
    keep: ArrayLike | None = None,
    time_limit_s: float = TIME_LIMIT_S,
) -> Ranking:
    """Fit every model of ``models`` and rank them by BIC. The first model that fits is the
    reference: its outlier screen fixes the samples and its noise estimate with the deviation
    families projected out (free of its own misfit) is the noise model of every candidate, so
    that the likelihoods compare the same data under the same covariance. Each candidate has
    ``time_limit_s``; a candidate that fails or runs out of time is listed in ``failed``."""
    if not models:
        raise ValueError("models must name at least one model, got []")
    failed: dict[str, str] = {}
    ref = None
    fits = []
    for m in models:
        try:
            if ref is None:
                ref = fit_raw(t, y, m, baseline, keep, time_limit_s=time_limit_s)
                mask = np.ones(np.size(t), bool)
                mask[ref.excluded] = False
                fits.append(ref)
            else:
                fits.append(
                    fit_raw(
                        t,
                        y,
                        m,
                        baseline,
                        mask,
                        noise=ref.lack_of_fit.noise,
                        time_limit_s=time_limit_s,
                        screen=False,
                    )
                )
        except FitTimeout:
            failed[m] = f"time limit of {time_limit_s:g} CPU s"
        except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
            failed[m] = str(exc)
    if ref is not None and len(fits) > 1:
        # the reference too with the common noise, so that all criteria share it
        fits[0] = fit_raw(
            t, y, ref.model, baseline, mask, noise=ref.lack_of_fit.noise, screen=False
        )
    fits.sort(key=lambda f: f.bic)
    if fits:
        d = np.array([f.bic - fits[0].bic for f in fits])
        w = np.exp(-0.5 * d)
        weights = list(w / w.sum())
    else:
        weights = []
    excluded, mrt = _identification(fits, np.asarray(t, dtype=float))
    return Ranking(fits, [float(x) for x in weights], failed, excluded, mrt)


def _identification(fits: list[RawFit], t: NDArray) -> tuple[dict[str, str], dict]:
    """(reasons a candidate may not be selected, by model; each candidate's mean residence
    time): a parameter on a bound or a degenerate interval (``RawFit.selection_problems``),
    a mean residence time or its interval outside the record [t_0, t_end]
    (``derived.mean_residence_time``)."""
    from twin_core.rtd.derived import mean_residence_time  # derived builds on this module

    excluded, mrt = {}, {}
    for f in fits:
        why = f.selection_problems()
        try:
            m = mean_residence_time(f, t)
            mrt[f.model] = m
            if not t[0] < m.value < t[-1]:
                why.append(
                    f"its mean residence time {m.value:.4g} s lies outside the record "
                    f"[{t[0]:.4g}, {t[-1]:.4g}] s"
                )
            elif not (t[0] <= m.ci[0] and m.ci[1] <= t[-1]):
                why.append(
                    f"the interval of its mean residence time [{m.ci[0]:.4g}, {m.ci[1]:.4g}] s "
                    f"reaches outside the record [{t[0]:.4g}, {t[-1]:.4g}] s"
                )
        except (ValueError, FloatingPointError) as exc:
            why.append(f"its mean residence time could not be computed: {exc}")
        if why:
            excluded[f.model] = "; ".join(why)
    return excluded, mrt
