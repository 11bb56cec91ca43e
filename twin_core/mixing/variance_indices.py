"""Variance (grid) based mixing indices of seed section 4.3.1.

Every function takes per-cell counts of the *kept* cells (see :mod:`twin_core.mixing.grid`):
``a`` the tracer-type count and ``n`` the total count of each cell (binary indices), or a
``(cells, types)`` count matrix (multi-component indices). ``p`` is the overall tracer
number fraction ``sum(a) / sum(n)``.

Bounds used in the tests (expected values for a random type assignment, binomial sampling
with ``n`` particles per cell): variance of a cell fraction ``p (1 - p) / n``.
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
    if np.any(n <= 0) or np.any(a < 0) or np.any(a > n):
        raise ValueError("counts must satisfy 0 <= a <= n and n > 0 in every cell")
    p = a.sum() / n.sum()
    if not 0.0 < p < 1.0:
        raise ValueError(f"tracer fraction must be strictly between 0 and 1, got {p}")
    return a, n, float(p)


def lacey(a: np.ndarray, n: np.ndarray) -> float:
    """Lacey's mixing index.

    ``M = (S0^2 - S^2) / (S0^2 - Sr^2)``, ``S^2 = sum (x_i - p)^2 / (N - 1)``,
    ``S0^2 = p (1 - p)`` (segregated), ``Sr^2 = p (1 - p) / n`` (random, ``n`` = mean
    particles per sample). 0 segregated, 1 random.

    Reference: Lacey, J. Appl. Chem. 4 (1954) 257. The seed's Eq. (1) swaps the numerator
    and its Eq. (3) divides by the number of cells; docs/seed.md gives the form used here.
    """
    a, n, p = _fractions(a, n)
    x = a / n
    s2 = np.sum((x - p) ** 2) / (x.size - 1)
    s0 = p * (1 - p)
    sr = s0 / n.mean()
    return float((s0 - s2) / (s0 - sr))


def relative_standard_deviation(a: np.ndarray, n: np.ndarray) -> float:
    """RSD = sigma / C_av of the cell concentrations (seed Eqs. 9-10, sample std, N - 1).

    Random bound ~ sqrt((1 - p) / (p n)); segregated ~ sqrt((1 - p) / p).
    Reference: seed Eq. (9)-(10); e.g. Sarkar & Wassgren, Chem. Eng. Sci. 64 (2009) 2672.
    """
    a, n, _ = _fractions(a, n)
    c = a / n
    return float(np.std(c, ddof=1) / c.mean())


def cell_variance(a: np.ndarray, n: np.ndarray) -> float:
    """Population variance of the cell fractions, ``(1/N) sum (X_i - X_av)^2`` (seed Eq. 6)."""
    a, n, _ = _fractions(a, n)
    return float(np.var(a / n))


def variance_reduction_ratio(
    a: np.ndarray, n: np.ndarray, a_ref: np.ndarray, n_ref: np.ndarray
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

    ``sigma^2 = (1/N) sum_i (C_a,i - (C_a / C_b) C_b,i)^2`` with ``C_a, C_b`` the mean counts per
    cell. The normalised index (Eq. 8) divides by the maximum over the time series
    (see :func:`twin_core.mixing.series.compute_indices`). Random bound ~ ``n p / (1 - p)``;
    segregated (pure cells, p = 0.5) ~ ``n^2``.
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


def mixing_segregation_index(a: np.ndarray, n: np.ndarray) -> float:
    """MSI = sqrt(sum (X_i - X_av)^2 / (N - 1)), X_i = phi_i / phi_av, phi_i = a_i / (a_i + b_i).

    Seed Eqs. (11)-(12). Note ``X_av = 1`` so MSI equals the RSD of the cell fractions
    (the seed's Table 8.2 shows identical gamma and R^2 for MSI and RSD, as it must).
    """
    a, n, _ = _fractions(a, n)
    phi = a / n
    x = phi / phi.mean()
    return float(np.sqrt(np.sum((x - x.mean()) ** 2) / (x.size - 1)))


def intensity_of_segregation(a: np.ndarray, n: np.ndarray) -> float:
    """ESI = sigma / sqrt(p (1 - p)) with sigma the (population) std of tracer cell fractions.

    Seed Eq. (18). Its square is Danckwerts' intensity of segregation
    (Danckwerts, Appl. Sci. Res. A3 (1952) 279). 1 segregated, ~ 1/sqrt(n) random.
    """
    a, n, p = _fractions(a, n)
    return float(np.std(a / n) / np.sqrt(p * (1 - p)))


def mixing_entropy(counts: np.ndarray) -> float:
    """Normalised mixing entropy, 0 segregated, 1 fully mixed.

    ``e(k) = -sum_i x_i(k) ln x_i(k)``, ``ME = sum_k n(k) e(k) / (N_total e_mix)`` with
    ``e_mix = -sum_i p_i ln p_i`` of the overall composition.
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
    if e_mix == 0:
        raise ValueError("only one type present: mixing entropy undefined")
    return float(np.sum(n * e) / (n.sum() * e_mix))


def degree_of_mixedness(a: np.ndarray, n: np.ndarray) -> float:
    """DM = 1 - sqrt( (sum (x_i - x_c)^2 / N) / (x_c (1 - x_c)) ).

    Seed Eq. (16) with the square restored (docs/seed.md); x_c the overall fraction.
    Reference: Rhodes et al., Powder Technol. 115 (2001) (degree of mixedness of
    fluidised beds), following Danckwerts' intensity. 0 segregated, 1 - 1/sqrt(n) random.
    """
    a, n, p = _fractions(a, n)
    return float(1.0 - np.sqrt(np.mean((a / n - p) ** 2) / (p * (1 - p))))
