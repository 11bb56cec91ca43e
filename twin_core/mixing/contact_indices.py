"""Contact and neighbour based mixing indices of seed section 4.3.1 (CN, SI, PS, NNM).

``types`` is an integer array; the tracer ("A") type is ``tracer``; every other type is "B".
Contacts are ``(n_pairs, 2)`` index pairs counted once (see
:func:`twin_core.mixing.neighbours.contacts_from_positions`).
"""

from __future__ import annotations

import numpy as np


def contact_type_counts(pairs: np.ndarray, types: np.ndarray, tracer: int) -> tuple[int, int, int]:
    """Numbers of AA, AB and BB contact pairs (each pair counted once)."""
    if len(pairs) == 0:
        return 0, 0, 0
    is_a = (np.asarray(types) == tracer).astype(np.int8)
    n_a = is_a[pairs[:, 0]] + is_a[pairs[:, 1]]  # tracer particles in each pair: 0, 1 or 2
    n_bb, n_ab, n_aa = np.bincount(n_a, minlength=3)[:3].tolist()
    return n_aa, n_ab, n_bb


def coordination_number_index(
    pairs: np.ndarray,
    types: np.ndarray,
    tracer: int,
    counts: tuple[int, int, int] | None = None,
) -> float:
    """CN = C_AB / (C_AA + C_BB), contact pairs counted once (seed Eq. 17).

    0 segregated (only interface contacts), ~1 for a random 50:50 mixture (a random mixture of
    tracer fraction p gives 2 p (1 - p) / (p^2 + (1 - p)^2)).
    Reference: seed Eq. (17); Deen et al., Chem. Eng. Sci. 65 (2010) 1 (contact counting).
    ``counts``: the :func:`contact_type_counts` of these pairs when already known.
    """
    aa, ab, bb = contact_type_counts(pairs, types, tracer) if counts is None else counts
    if aa + bb == 0:
        raise ValueError("no like-type contacts: CN undefined")
    return ab / (aa + bb)


def segregation_index(
    pairs: np.ndarray,
    types: np.ndarray,
    tracer: int,
    counts: tuple[int, int, int] | None = None,
) -> float:
    """SI = C_AA/(C_AA + C_AB) + C_BB/(C_BB + C_AB) (seed Eq. 15).

    Counting convention: C_AA (C_BB) counts like-type contacts from both particles (2 per pair),
    C_AB once per pair, so that "the total number of contacts made by particles of A type equals
    C_AA + C_AB" as the seed states. Then SI = 2 segregated, 1 random mixture (any fraction),
    0 perfectly ordered (alternating). ``counts``: the :func:`contact_type_counts` of these
    pairs when already known.
    """
    aa, ab, bb = contact_type_counts(pairs, types, tracer) if counts is None else counts
    if aa + ab == 0 or bb + ab == 0:
        raise ValueError("a type has no contacts: SI undefined")
    return 2 * aa / (2 * aa + ab) + 2 * bb / (2 * bb + ab)


def particle_scale_index(pairs: np.ndarray, types: np.ndarray, tracer: int) -> float:
    """Particle-scale mixing index (PSMI).

    ``p_i`` = tracer fraction among particle i and its ``C_n,i`` contacting neighbours,
    ``p_i = (#tracer in {i} U contacts(i)) / (C_n,i + 1)``;
    ``PS = (S0^2 - St^2) / (S0^2 - Sr^2)``, ``St^2 = var(p_i)``, ``S0^2 = p (1 - p)``,
    ``Sr^2 = p (1 - p) / (C_n + 1)`` with ``C_n`` the mean coordination number.
    0 segregated, ~1 random.
    Reference: Chandratilleke, Yu, Bridgwater & Shinohara, "A particle-scale index in the
    quantification of mixing of particles", AIChE J. 58 (2012) 1099-1118. The seed's Eq. (21) counts only differently coloured neighbours, which is not a fraction of a
    sample; the original local-composition definition is used.
    """
    types = np.asarray(types)
    n = len(types)
    is_a = (types == tracer).astype(float)
    cn = np.bincount(pairs.ravel(), minlength=n).astype(float)
    n_a = is_a.copy()
    if len(pairs):
        n_a += np.bincount(pairs[:, 0], is_a[pairs[:, 1]], n)
        n_a += np.bincount(pairs[:, 1], is_a[pairs[:, 0]], n)
    p_i = n_a / (cn + 1.0)
    p = is_a.mean()
    if not 0 < p < 1:
        raise ValueError(f"tracer fraction must be in (0, 1), got {p}")
    s0 = p * (1 - p)
    sr = s0 / (cn.mean() + 1.0)
    return float((s0 - np.var(p_i)) / (s0 - sr))


def nearest_neighbour_index(neighbours: np.ndarray, types: np.ndarray) -> float:
    """NNM = (1/N) sum_i 2 n_diff,i / n_nb (seed Eq. 19), ``n_nb`` = neighbours per particle.

    0 segregated; a random mixture gives ``4 p (1 - p)`` (1 for a 50:50 binary mixture).
    Reference: Godlieb et al., Proc. 12th Int. Conf. Fluidization (2007), neighbour counting with
    12 nearest neighbours, as in the seed.
    """
    types = np.asarray(types)
    diff = types[neighbours] != types[:, None]
    return float(2.0 * np.count_nonzero(diff) / diff.size)
