"""Space of the DEM engine: the row layout of the particle state and the periodic box.

Holds what every kernel shares (jax-md's ``space``; LIGGGHTS' ``atom_style granular``): the
columns of the state arrays and the minimum-image displacement along periodic axes.

Data layout (struct of rows, one row per particle, ``cap >= n`` rows allocated)

- ``P`` float64 (cap, 13): x(0:3), v(3:6), omega(6:9), radius(9), mass(10), 1/mass(11),
  1/inertia(12) (solid sphere, I = 2/5 m R^2).
- ``F`` float64 (cap, 6): force(0:3), torque(3:6) at the current positions.
- ``IA`` int64 (cap, 3): persistent id, material id, type id.
- ``dom`` float64 (9,): box lower corner (0:3), upper corner (3:6), lengths (6:9);
  ``per`` int64 (3,): 1 on periodic axes.

Indexing: numba turns a negative signed index into one counted from the end, which costs a
compare and a select per index that the compiler cannot prove non-negative (one loaded from a
list). The per-contact loops therefore cast the indices they read from lists to ``np.uint64``
(no wraparound code): the contact search over the listed pairs ran 1.6x faster (mixing
``uint64`` and ``int64`` in arithmetic gives ``float64`` in numba: cast only where indexing).

Reference: Allen & Tildesley, Computer Simulation of Liquids (2nd ed. 2017), Sec. 1.6.2
(periodic boundaries, minimum image convention).
"""

from __future__ import annotations

from numba import njit

__all__ = ["FMA", "NPC", "min_image"]

NPC = 13  # columns of P

#: fast-math flags of the engine's per-step kernels: only fused multiply-add (``a * b + c`` in
#: one rounding; deterministic for a given build and CPU, so the sums stay the same for any thread
#: count), none of the flags that assume no NaN or infinity (walls use infinite windows).
FMA = {"contract"}


@njit(cache=True, inline="always")
def min_image(d: float, length: float, periodic: bool) -> float:
    """Minimum image ``d - L round(d / L)`` of a separation ``|d| < 1.5 L`` along an axis of
    period ``L`` (unchanged along a closed axis)."""
    if periodic:
        if d > 0.5 * length:
            return d - length
        if d < -0.5 * length:
            return d + length
    return d
