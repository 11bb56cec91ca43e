"""Elastic (Hertz) energy of all contacts of a DEM state, a diagnostic of the engine (jax-md's
``energy``): ``sum (8/15) E* sqrt(R*) delta^(5/2)`` over sphere-sphere, sphere-plane and
sphere-cylinder overlaps (tangential springs and mesh contacts not included).

Reference: Johnson, Contact Mechanics (1985), Sec. 4.2 (Hertz contact: ``F = (4/3) E* sqrt(R*)
delta^(3/2)``, whose potential this is).
"""

from __future__ import annotations

from numba import njit

from .pairs import add_pair_energy
from .walls import add_cylinder_energy, add_plane_energy

__all__ = ["elastic_energy"]


@njit(cache=True)
def elastic_energy(n, P, IA, nb, nown, planes, cyls, pt, dom, per):
    """Elastic normal energy ``(8/15) E* sqrt(R*) delta^(5/2)`` of all sphere-sphere, sphere-plane
    and sphere-cylinder contacts (J), summed particle by particle (its owned pairs, then its
    planes, then its cylinders)."""
    en = 0.0
    for i in range(n):
        en = add_pair_energy(en, i, P, IA, nb, nown, pt, dom, per)
        en = add_plane_energy(en, i, P, IA, planes, pt)
        en = add_cylinder_energy(en, i, P, IA, cyls, pt)
    return en
