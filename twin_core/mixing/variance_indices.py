"""Variance (grid) based mixing indices of seed section 4.3.1.

Every function takes per-cell amounts of the *kept* cells (see :mod:`twin_core.mixing.grid`):
``a`` the tracer amount and ``n`` the total amount of each cell (binary indices), or a
``(cells, types)`` amount matrix (multi-component indices). Amounts are particle counts
(the seed's number fractions) or particle volumes (volume fractions, polydisperse beds).
``p`` is the overall tracer fraction ``sum(a) / sum(n)``.

``weights=None`` gives the seed's forms: every cell counts once (sample variances over the
cells). ``weights=n`` (volume weighting) weights each cell by its particle volume,
``S^2 = sum V_i (x_i - p)^2 / sum V_i``: the likelihood of sampling a particle is proportional
to its volume (Kristensen, Powder Technol. 7 (1973) 249; Fan et al., Powder Technol. 24
(1979) 73; Chandratilleke et al., AIChE J. 58 (2012) 1099-1118).

Bounds used in the tests (expected values for a random type assignment, binomial sampling
with ``n`` particles per cell): variance of a cell fraction ``p (1 - p) / n``; for volume
fractions of a polydisperse bed, :func:`random_mixture_variance`.
"""

from __future__ import annotations

import numpy as np


def _fractions(a: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    a = np.asarray(a, float)
    n = np.asarray(n, float)
    if a.shape != n.shape or a.ndim != 1:
        raise ValueError(f"a and n must be 1-D of equal shape, got {a.shape} and {n.shape}")
    if a.size < 2:
        raise ValueError(f"need at least 2 occupied cells, got {a.size}")
    if np.any(n <= 0) or np.any(a < 0) or np.any(a > n * (1 + 1e-12)):
        raise ValueError("amounts must satisfy 0 <= a <= n and n > 0 in every cell")
    p = a.sum() / n.sum()
    if not 0.0 < p < 1.0:
        raise ValueError(f"tracer fraction must be strictly between 0 and 1, got {p}")
    return a, n, float(p)


def _spread(x: np.ndarray, centre: float, weights: np.ndarray | None, ddof: int) -> float:
    """Mean squared deviation of the cell fractions from ``centre``: over the cells with
    ``ddof`` (``weights=None``), or weighted by ``weights`` (no degrees-of-freedom correction,
    as in the volume-weighted form)."""
    if weights is None:
        return float(np.sum((x - centre) ** 2) / (x.size - ddof))
    w = np.asarray(weights, float)
    if w.shape != x.shape or np.any(w < 0) or not w.sum() > 0:
        raise ValueError(f"weights must be {x.shape[0]} non-negative numbers with a positive sum")
    return float(np.sum(w * (x - centre) ** 2) / w.sum())


def random_mixture_variance(
    p: float, sample_amount: float, kappa_tracer: float = 1.0, kappa_other: float = 1.0
) -> float:
    """Variance of the tracer fraction of a sample of a random mixture.

    ``Sr^2 = p (1 - p) / S [(1 - p) kappa_A + p kappa_B]`` with ``S`` the mean sample amount
    and ``kappa = <v^2> / <v>`` of each species' particle sizes (amount per particle: 1 for
    counts, ``4/3 pi r^3`` for volumes). Monodisperse or counted: ``p (1 - p) / n`` (Lacey).
    Reference: Stange, Chem. Ing. Tech. 26 (1954) 331; Poole, Taylor & Wall, Trans. Inst. Chem.
    Eng. 42 (1964) T305 (random mixtures of particles of unequal size).
    """
    if not sample_amount > 0:
        raise ValueError(f"sample_amount must be > 0, got {sample_amount}")
    return p * (1 - p) / sample_amount * ((1 - p) * kappa_tracer + p * kappa_other)


def lacey(
    a: np.ndarray,
    n: np.ndarray,
    weights: np.ndarray | None = None,
    random_variance: float | None = None,
) -> float:
    """Lacey's mixing index.

    ``M = (S0^2 - S^2) / (S0^2 - Sr^2)``, ``S^2 = sum (x_i - p)^2 / (N - 1)`` (or the
    ``weights``-weighted mean square, see the module docstring), ``S0^2 = p (1 - p)``
    (segregated), ``Sr^2 = p (1 - p) / n`` (random, ``n`` = mean particles per sample) unless
    ``random_variance`` is given (:func:`random_mixture_variance` for volume fractions of a
    polydisperse bed). 0 segregated, 1 random.

    Reference: Lacey, J. Appl. Chem. 4 (1954) 257. The seed's Eq. (1) swaps the numerator
    and its Eq. (3) divides by the number of cells; docs/seed.md gives the form used here.
    """
    a, n, p = _fractions(a, n)
    s2 = _spread(a / n, p, weights, 1)
    s0 = p * (1 - p)
    sr = s0 / n.mean() if random_variance is None else random_variance
    return float((s0 - s2) / (s0 - sr))


def relative_standard_deviation(
    a: np.ndarray, n: np.ndarray, weights: np.ndarray | None = None
) -> float:
    """RSD = sigma / C_av of the cell concentrations (seed Eqs. 9-10, sample std, N - 1; with
    ``weights`` the weighted std about the weighted mean, which is the overall fraction ``p``).

    Random bound ~ sqrt((1 - p) / (p n)); segregated ~ sqrt((1 - p) / p).
    Reference: seed Eq. (9)-(10); e.g. Sarkar & Wassgren, Chem. Eng. Sci. 64 (2009) 2672.
    """
    a, n, p = _fractions(a, n)
    c = a / n
    if weights is None:
        return float(np.std(c, ddof=1) / c.mean())
    return float(np.sqrt(_spread(c, p, weights, 0)) / p)


def cell_variance(a: np.ndarray, n: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Population variance of the cell fractions, ``(1/N) sum (X_i - X_av)^2`` (seed Eq. 6;
    with ``weights``, the weighted variance about the weighted mean ``p``)."""
    a, n, p = _fractions(a, n)
    x = a / n
    return _spread(x, x.mean() if weights is None else p, weights, 0)


def variance_reduction_ratio(
    a: np.ndarray,
    n: np.ndarray,
    a_ref: np.ndarray,
    n_ref: np.ndarray,
    weighted: bool = False,
) -> float:
    """VRR = sigma_ref^2 / sigma^2 (seed Eqs. 5-6).

    In the periodic section the "inlet" (reference) state is the initial, segregated frame and
    the "outlet" the current frame, so VRR grows from 1 as mixing proceeds.
    Reference: Danckwerts, Appl. Sci. Res. A3 (1952) 279; Williams, Powder Technol. 2 (1968) 13.
    """
    s = cell_variance(a, n)
    s_ref = cell_variance(a_ref, n_ref)
    if s == 0.0:
        return float("inf")
    return float(s_ref / s)


def vbbc_variance(counts_a: np.ndarray, counts_b: np.ndarray) -> float:
    """Variance amongst bimodal bin counts (seed Eq. 7), before normalisation.

    ``sigma^2 = (1/N) sum_i (C_a,i - (C_a / C_b) C_b,i)^2`` with ``C_a, C_b`` the mean amounts
    (counts, or volumes for a polydisperse bed) per cell. The normalised index (Eq. 8) divides
    by the maximum over the time series (see :func:`twin_core.mixing.series.compute_indices`).
    Random bound ~ ``n p / (1 - p)``; segregated (pure cells, p = 0.5) ~ ``n^2``.
    Reference: seed 4.3.1.3, Eqs. (7)-(8) (its reference [29]).
    """
    ca = np.asarray(counts_a, float)
    cb = np.asarray(counts_b, float)
    if ca.shape != cb.shape or ca.size < 2:
        raise ValueError(
            f"counts_a and counts_b must have equal shape >= 2, got {ca.shape}, {cb.shape}"
        )
    if cb.mean() == 0:
        raise ValueError("counts_b is zero in every cell")
    return float(np.mean((ca - ca.mean() / cb.mean() * cb) ** 2))


def mixing_segregation_index(
    a: np.ndarray, n: np.ndarray, weights: np.ndarray | None = None
) -> float:
    """MSI = sqrt(sum (X_i - X_av)^2 / (N - 1)), X_i = phi_i / phi_av, phi_i = a_i / (a_i + b_i).

    Seed Eqs. (11)-(12). Note ``X_av = 1`` so MSI equals the RSD of the cell fractions
    (the seed's Table 8.2 shows identical gamma and R^2 for MSI and RSD, as it must); with
    ``weights``, ``phi_av`` is the weighted mean ``p`` and the spread is weighted.
    Reference: seed 4.3.1.5, Eqs. (11)-(12) (its reference [51]).
    """
    a, n, p = _fractions(a, n)
    phi = a / n
    if weights is None:
        x = phi / phi.mean()
        return float(np.sqrt(np.sum((x - x.mean()) ** 2) / (x.size - 1)))
    return float(np.sqrt(_spread(phi / p, 1.0, weights, 0)))


def intensity_of_segregation(
    a: np.ndarray, n: np.ndarray, weights: np.ndarray | None = None
) -> float:
    """ESI = sigma / sqrt(p (1 - p)) with sigma the (population) std of tracer cell fractions
    (weighted about ``p`` with ``weights``).

    Seed Eq. (18). Its square is Danckwerts' intensity of segregation
    (Danckwerts, Appl. Sci. Res. A3 (1952) 279). 1 segregated, ~ 1/sqrt(n) random.
    """
    a, n, p = _fractions(a, n)
    x = a / n
    sigma2 = _spread(x, x.mean() if weights is None else p, weights, 0)
    return float(np.sqrt(sigma2 / (p * (1 - p))))


def mixing_entropy(counts: np.ndarray) -> float:
    """Normalised mixing entropy, 0 segregated, 1 fully mixed.

    ``e(k) = -sum_i x_i(k) ln x_i(k)``, ``ME = sum_k n(k) e(k) / (N_total e_mix)`` with
    ``e_mix = -sum_i p_i ln p_i`` of the overall composition; with volume amounts, ``x`` are
    volume fractions and each cell counts by its volume.
    Reference: Lai & Fan, Powder Technol. 12 (1975) 195 (entropy of mixing). The seed's
    Eq. (13) drops the minus sign (docs/seed.md); its Eq. (14) normalises by N cells.
    """
    c = np.asarray(counts, float)
    if c.ndim != 2 or c.shape[1] < 2:
        raise ValueError(f"counts must be (cells, types>=2), got shape {c.shape}")
    n = c.sum(axis=1)
    keep = n > 0
    c, n = c[keep], n[keep]
    x = c / n[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        e = -np.where(x > 0, x * np.log(x), 0.0).sum(axis=1)
    p = c.sum(axis=0) / n.sum()
    p = p[p > 0]
    e_mix = -np.sum(p * np.log(p))
    if e_mix <= 0:
        raise ValueError("only one type present: mixing entropy undefined")
    return float(np.sum(n * e) / (n.sum() * e_mix))


def degree_of_mixedness(a: np.ndarray, n: np.ndarray, weights: np.ndarray | None = None) -> float:
    """DM = 1 - sqrt( (sum (x_i - x_c)^2 / N) / (x_c (1 - x_c)) ) (weighted mean square with
    ``weights``).

    Seed Eq. (16) with the square restored (docs/seed.md); x_c the overall fraction.
    Reference: Rhodes et al., Powder Technol. 115 (2001) (degree of mixedness of
    fluidised beds), following Danckwerts' intensity. 0 segregated, 1 - 1/sqrt(n) random.
    """
    a, n, p = _fractions(a, n)
    return float(1.0 - np.sqrt(_spread(a / n, p, weights, 0) / (p * (1 - p))))
