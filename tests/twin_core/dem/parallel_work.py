"""A campaign run function with a numba parallel region (importable by pool workers)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange, threading_layer


@njit(parallel=True)
def _twice_sum(a):
    s = 0.0
    for i in prange(a.size):
        s += 2.0 * a[i]
    return s


def parallel_sum(params: dict, seed: int) -> dict:
    """``{"total": 2 n, "openmp": 1 under numba's OpenMP layer, else 0}`` from a parallel
    region over ``n`` ones."""
    total = float(_twice_sum(np.ones(int(params["n"]))))
    return {"total": total, "openmp": float(threading_layer() == "omp")}
