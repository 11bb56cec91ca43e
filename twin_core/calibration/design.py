"""Definitive screening designs (DSD) and their diagnostics.

Construction (Jones & Nachtsheim 2011, J. Qual. Technol. 43:1-15): with C a conference
matrix of even order n (zero diagonal, +-1 elsewhere, C^T C = (n-1) I), the design
``D = [C; -C; 0]`` has 2n + 1 runs on three levels (-1, 0, +1). Its main-effect columns are
mutually orthogonal and, because every run has its fold-over ``-x`` in the design, orthogonal
to every two-factor interaction and every quadratic column.

Extra runs (Jones & Nachtsheim 2017, J. Qual. Technol. 49:1-15, "fake factors"): build the DSD
for two more factors than needed and drop their columns; for m even this gives
2m + 1 + 4 runs, the 21-run, 8-factor design of the seed's Table 3.2 (10 fold-over pairs and a
centre run). For m odd the design is built for m + 3 factors (2m + 7 runs).

Conference matrices come from the Paley constructions on GF(q), q an odd prime power
(order q + 1; symmetric for q = 1 mod 4, antisymmetric for q = 3 mod 4). Orders without a
Paley construction here (16, 22, 34, ...; 22 does not exist at all) are replaced by the next
constructible order, i.e. the design carries more fake factors and a few more runs.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

__all__ = [
    "SEED_LEVELS",
    "DefinitiveScreeningDesign",
    "conference_matrix",
    "definitive_screening_design",
    "coded_to_physical",
    "physical_to_coded",
    "model_columns",
    "correlation_map",
    "dsd_properties",
]

#: Lower / middle / upper levels of the seed's DEM material study: Table 3.1 bounds with the
#: middle levels actually used in Table 3.2 (static frictions at 0.35, not Table 3.1's 0.3).
SEED_LEVELS: dict[str, tuple[float, float, float]] = {
    "PP_SF": (0.1, 0.35, 0.6),
    "PP_RF": (0.01, 0.04, 0.1),
    "PP_COR": (0.1, 0.4, 0.7),
    "PW_SF": (0.1, 0.35, 0.6),
    "PW_RF": (0.01, 0.04, 0.1),
    "PW_COR": (0.01, 0.1, 0.2),
    "SM": (1e6, 5e6, 1e7),
    "PR": (0.2, 0.35, 0.5),
}


# --------------------------------------------------------------------------- GF(q)
def _factor_prime_power(q: int) -> tuple[int, int] | None:
    """(p, k) with q = p**k, p prime, or None."""
    if q < 2:
        return None
    p = next(d for d in range(2, q + 1) if q % d == 0)
    k, r = 0, q
    while r % p == 0:
        r //= p
        k += 1
    return (p, k) if r == 1 else None


def _poly_mulmod(a: list[int], b: list[int], mod: list[int], p: int) -> list[int]:
    """Product of polynomials a*b modulo the monic ``mod`` over GF(p) (low degree first)."""
    k = len(mod) - 1
    prod = [0] * (len(a) + len(b) - 1)
    for i, ai in enumerate(a):
        for j, bj in enumerate(b):
            prod[i + j] = (prod[i + j] + ai * bj) % p
    for d in range(len(prod) - 1, k - 1, -1):
        c = prod[d]
        if c:
            for i in range(k + 1):
                prod[d - k + i] = (prod[d - k + i] - c * mod[i]) % p
    return (prod + [0] * k)[:k]


def _irreducible(p: int, k: int) -> list[int]:
    """A monic irreducible polynomial of degree k over GF(p) (low degree first)."""
    for tail in itertools.product(range(p), repeat=k):
        poly = list(tail) + [1]
        if poly[0] == 0:
            continue
        # irreducible iff no root-free factorisation: brute force over monic divisors of degree <= k/2
        reducible = False
        for d in range(1, k // 2 + 1):
            for dt in itertools.product(range(p), repeat=d):
                div = list(dt) + [1]
                if _poly_mulmod(poly, [1], div, p) == [0] * d:
                    reducible = True
                    break
            if reducible:
                break
        if not reducible:
            return poly
    raise RuntimeError(f"no irreducible polynomial of degree {k} over GF({p})")  # unreachable


def _quadratic_character_table(q: int) -> tuple[np.ndarray, np.ndarray]:
    """Elements of GF(q) coded 0..q-1 (base-p digits = polynomial coefficients).

    Returns (sub, chi): ``sub[a, b]`` = code of a - b, ``chi[c]`` = quadratic character of c.
    """
    pk = _factor_prime_power(q)
    if pk is None or pk[0] == 2:
        raise ValueError(f"q must be an odd prime power, got {q}")
    p, k = pk
    digits = np.array([[(x // p**i) % p for i in range(k)] for x in range(q)], dtype=int)
    weights = p ** np.arange(k)
    sub = ((digits[:, None, :] - digits[None, :, :]) % p) @ weights
    mod = _irreducible(p, k) if k > 1 else [0, 1]
    squares = set()
    for x in range(1, q):
        if k == 1:
            squares.add((x * x) % p)
        else:
            d = digits[x].tolist()
            squares.add(int(np.dot(_poly_mulmod(d, d, mod, p), weights)))
    chi = np.array([0] + [1 if c in squares else -1 for c in range(1, q)], dtype=int)
    return sub, chi


def _constructible(n: int) -> bool:
    if n == 2:
        return True
    pk = _factor_prime_power(n - 1)
    return n % 2 == 0 and pk is not None and pk[0] != 2


def conference_matrix(n: int) -> np.ndarray:
    """Conference matrix of order n (Paley I/II on GF(n-1); n = 2 trivial).

    Returns an integer matrix C with zero diagonal, +-1 elsewhere and C^T C = (n-1) I.
    Symmetric when n-1 = 1 (mod 4), antisymmetric when n-1 = 3 (mod 4)
    (Paley 1933; Jacobsthal matrix Q_ij = chi(a_i - a_j)).
    """
    if n == 2:
        return np.array([[0, 1], [1, 0]])
    if not _constructible(n):
        raise ValueError(
            f"n must be 2 or q + 1 with q an odd prime power for the Paley construction, got {n}"
        )
    q = n - 1
    sub, chi = _quadratic_character_table(q)
    jac = chi[sub]
    c = np.zeros((n, n), dtype=int)
    c[0, 1:] = 1
    c[1:, 0] = 1 if q % 4 == 1 else -1
    c[1:, 1:] = jac
    # put the zeros on the diagonal already (row i has its zero in column i)
    return c


def _next_order(n: int) -> int:
    while not _constructible(n):
        n += 2
    return n


@dataclass(frozen=True)
class DefinitiveScreeningDesign:
    """A DSD: coded (-1/0/+1) and physical design tables (one row per run)."""

    coded: pd.DataFrame
    physical: pd.DataFrame
    levels: dict[str, tuple[float, float, float]]
    conference_order: int
    n_fake: int

    @property
    def n_runs(self) -> int:
        return len(self.coded)


def _normalise_levels(
    factors: int | Sequence[str] | Mapping[str, Sequence[float]],
) -> tuple[list[str], dict[str, tuple[float, float, float]]]:
    if isinstance(factors, int):
        if factors < 2:
            raise ValueError(f"factors must be >= 2, got {factors}")
        names = [f"X{i + 1}" for i in range(factors)]
        return names, {k: (-1.0, 0.0, 1.0) for k in names}
    if isinstance(factors, Mapping):
        levels: dict[str, tuple[float, float, float]] = {}
        for name, lv in factors.items():
            lv = [float(v) for v in lv]
            if len(lv) == 2:
                lv = [lv[0], 0.5 * (lv[0] + lv[1]), lv[1]]
            if len(lv) != 3 or not (lv[0] < lv[1] < lv[2]):
                raise ValueError(
                    f"levels of {name!r} must be (lower, upper) or increasing (lower, middle, "
                    f"upper), got {lv}"
                )
            levels[str(name)] = (lv[0], lv[1], lv[2])
        if len(levels) < 2:
            raise ValueError(f"need at least 2 factors, got {len(levels)}")
        return list(levels), levels
    names = [str(x) for x in factors]
    if len(set(names)) != len(names) or len(names) < 2:
        raise ValueError(f"factors must be >= 2 distinct names, got {names}")
    return names, {k: (-1.0, 0.0, 1.0) for k in names}


def coded_to_physical(
    coded: pd.DataFrame, levels: Mapping[str, tuple[float, float, float]]
) -> pd.DataFrame:
    """Map coded values to physical units piecewise-linearly: -1 -> lower, 0 -> middle,
    +1 -> upper (so unequal half-ranges such as the seed's 0.01 / 0.04 / 0.1 are kept)."""
    out = {}
    for name in coded.columns:
        lo, mid, hi = levels[name]
        x = coded[name].to_numpy(dtype=float)
        v = np.where(x < 0, mid + x * (mid - lo), mid + x * (hi - mid))
        v = np.where(x == -1, lo, np.where(x == 1, hi, np.where(x == 0, mid, v)))
        out[name] = v
    return pd.DataFrame(out, index=coded.index)


def physical_to_coded(
    physical: pd.DataFrame, levels: Mapping[str, tuple[float, float, float]]
) -> pd.DataFrame:
    """Inverse of :func:`coded_to_physical` (piecewise linear around the middle level)."""
    out = {}
    for name in physical.columns:
        if name not in levels:
            continue
        lo, mid, hi = levels[name]
        v = physical[name].to_numpy(dtype=float)
        out[name] = np.where(v < mid, (v - mid) / (mid - lo), (v - mid) / (hi - mid))
    return pd.DataFrame(out, index=physical.index)


def definitive_screening_design(
    factors: int | Sequence[str] | Mapping[str, Sequence[float]],
    extra_runs: bool = True,
    randomize: bool = False,
    seed: int | np.random.Generator | None = None,
) -> DefinitiveScreeningDesign:
    """Definitive screening design for m factors.

    ``factors``: a count, a list of names (coded levels only) or a mapping name ->
    (lower, middle, upper) or (lower, upper). ``extra_runs`` adds the 4 runs of Jones &
    Nachtsheim (2017) via two fake factors (2m + 5 runs for m even, 2m + 7 for m odd);
    without it the 2011 design (2m + 1 runs for m even, 2m + 3 for m odd). Rows are in
    standard order (fold-over pairs i and i + n, centre run last) unless ``randomize``.
    """
    names, levels = _normalise_levels(factors)
    m = len(names)
    order = m + (m % 2) + (2 if extra_runs else 0)
    order = _next_order(order)
    c = conference_matrix(order)
    d = np.vstack([c, -c, np.zeros((1, order), dtype=int)])[:, :m]
    coded = pd.DataFrame(d, columns=names)
    if randomize:
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        coded = coded.iloc[rng.permutation(len(coded))]
    coded = coded.reset_index(drop=True)
    coded.index = pd.RangeIndex(1, len(coded) + 1, name="run")
    physical = coded_to_physical(coded, levels)
    return DefinitiveScreeningDesign(coded, physical, levels, order, order - m)


def model_columns(coded: pd.DataFrame) -> pd.DataFrame:
    """Main effects, two-factor interactions (A*B) and quadratics (A*A) of a coded design."""
    names = list(coded.columns)
    cols: dict[str, np.ndarray] = {n: coded[n].to_numpy(dtype=float) for n in names}
    for a, b in itertools.combinations(names, 2):
        cols[f"{a}*{b}"] = cols[a] * cols[b]
    for a in names:
        cols[f"{a}*{a}"] = cols[a] ** 2
    return pd.DataFrame(cols, index=coded.index)


def correlation_map(coded: pd.DataFrame) -> pd.DataFrame:
    """Absolute Pearson correlations |r| between main effects, two-factor interactions and
    quadratics (the seed's Fig. 3.4 colour map; JMP's 'Color Map on Correlations')."""
    cols = model_columns(coded)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.corrcoef(cols.to_numpy().T)
    return pd.DataFrame(np.abs(r), index=cols.columns, columns=cols.columns)


def dsd_properties(coded: pd.DataFrame) -> dict[str, float]:
    """Largest |r| within and between term groups of a coded design.

    A DSD has ``main_main = main_2fi = main_quad = 0``; ``2fi_2fi`` and ``quad_quad`` are
    below 1 (no complete confounding), which the seed's section 3.2.4 lists as its reasons
    for choosing the design.
    """
    names = list(coded.columns)
    r = correlation_map(coded).to_numpy()
    m = len(names)
    n2 = m * (m - 1) // 2
    main = np.arange(m)
    tfi = np.arange(m, m + n2)
    quad = np.arange(m + n2, m + n2 + m)

    def block(a: np.ndarray, b: np.ndarray, same: bool) -> float:
        sub = r[np.ix_(a, b)].copy()
        if same:
            np.fill_diagonal(sub, 0.0)
        return float(np.nanmax(sub)) if sub.size else 0.0

    return {
        "main_main": block(main, main, True),
        "main_2fi": block(main, tfi, False),
        "main_quad": block(main, quad, False),
        "2fi_2fi": block(tfi, tfi, True),
        "2fi_quad": block(tfi, quad, False),
        "quad_quad": block(quad, quad, True),
    }
