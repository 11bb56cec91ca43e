"""Primitive walls of the DEM engine (LIGGGHTS' ``fix wall/gran`` with ``primitive`` planes and
cylinders): the contacts of one sphere with every plane and cylinder, and their elastic energy.

Wall tables (one row per wall):

- ``planes`` (npl, 9): a point (0:3), the unit normal pointing into the domain (3:6), material (6),
  activation window ``t_on <= t < t_off`` (7, 8); overlap ``delta = r - (x - p).n``; contact
  only for ``delta > 0`` and ``(x - p).n >= -r``.
- ``cyls`` (ncy, 14): a point on the axis (0:3), unit axis u (3:6), radius R (6), side (7: +1
  particles inside, a drum; -1 outside, a shaft), angular speed about u (8, rad/s), material (9),
  axial range from the point (10, 11), activation window (12, 13). With s the distance of the
  centre from the axis,
  ``delta = r + s - R`` inside and ``r - (s - R)`` outside; contact for ``0 < delta <= 2 r``.
  The wall velocity at the contact point c is ``omega u x (c - a)``.

Wall histories: ``whist[i, w]``, planes first, then cylinders. The force is the wall contact law
of :mod:`twin_core.dem.contact` (R* = R, m* = m: the flat-wall limit).

References: Kloss et al. (2012), Prog. Comput. Fluid Dyn. 12, 140 (LIGGGHTS primitive walls);
Johnson, Contact Mechanics (1985), Sec. 4.2 (sphere on a flat: R* = R).
"""

from __future__ import annotations

import math

from numba import njit

from .contact import add_wall_contact, clear_history, hertz_energy, rotating_wall_velocity

__all__ = [
    "add_cylinder_contacts",
    "add_cylinder_energy",
    "add_plane_contacts",
    "add_plane_energy",
]


@njit(cache=True, inline="always")
def add_plane_contacts(i, P, IA, planes, whist, pt, dt, t, fx, fy, fz, tx, ty, tz):
    """Add to particle i's force and torque (fx .. tz) its contacts with the planes active at
    time t, in table order; update their histories. Returns the new (fx, fy, fz, tx, ty, tz)."""
    x, y, z = P[i, 0], P[i, 1], P[i, 2]
    ri = P[i, 9]
    for w in range(planes.shape[0]):
        if not (planes[w, 7] <= t < planes[w, 8]):
            clear_history(whist, i, w)
            continue
        dist = (
            (x - planes[w, 0]) * planes[w, 3]
            + (y - planes[w, 1]) * planes[w, 4]
            + (z - planes[w, 2]) * planes[w, 5]
        )
        delta = ri - dist
        if delta <= 0.0 or dist < -ri:
            clear_history(whist, i, w)
            continue
        fx, fy, fz, tx, ty, tz = add_wall_contact(
            P, IA, i, -planes[w, 3], -planes[w, 4], -planes[w, 5], delta,
            0.0, 0.0, 0.0, 0.0, 0.0, 0.0, int(planes[w, 6]), pt, whist, w, dt,
            fx, fy, fz, tx, ty, tz,
        )  # fmt: skip
    return fx, fy, fz, tx, ty, tz


@njit(cache=True, inline="always")
def add_cylinder_contacts(i, P, IA, cyls, npl, whist, pt, dt, t, fx, fy, fz, tx, ty, tz):
    """Add to particle i's force and torque (fx .. tz) its contacts with the cylinders active at
    time t, in table order (histories in ``whist[i, npl + w]``). Returns the new
    (fx, fy, fz, tx, ty, tz)."""
    x, y, z = P[i, 0], P[i, 1], P[i, 2]
    ri = P[i, 9]
    for w in range(cyls.shape[0]):
        qx, qy, qz = x - cyls[w, 0], y - cyls[w, 1], z - cyls[w, 2]
        ux, uy, uz = cyls[w, 3], cyls[w, 4], cyls[w, 5]
        ax_ = qx * ux + qy * uy + qz * uz
        hw = npl + w
        if ax_ < cyls[w, 10] or ax_ > cyls[w, 11] or not (cyls[w, 12] <= t < cyls[w, 13]):
            clear_history(whist, i, hw)
            continue
        rx, ry, rz = qx - ax_ * ux, qy - ax_ * uy, qz - ax_ * uz
        s = math.sqrt(rx * rx + ry * ry + rz * rz)
        rc = cyls[w, 6]
        if cyls[w, 7] > 0:
            delta = ri + s - rc
            sgn = 1.0
        else:
            delta = ri - (s - rc)
            sgn = -1.0
        if delta <= 0.0 or s == 0.0 or delta > 2.0 * ri:
            clear_history(whist, i, hw)
            continue
        nx, ny, nz = sgn * rx / s, sgn * ry / s, sgn * rz / s
        om = cyls[w, 8]
        # contact point and wall velocity omega u x (c - a)
        cpx = rx + (ri - delta) * nx
        cpy = ry + (ri - delta) * ny
        cpz = rz + (ri - delta) * nz
        vwx, vwy, vwz = rotating_wall_velocity(om, ux, uy, uz, cpx, cpy, cpz)
        fx, fy, fz, tx, ty, tz = add_wall_contact(
            P, IA, i, nx, ny, nz, delta, vwx, vwy, vwz, om * ux, om * uy, om * uz,
            int(cyls[w, 9]), pt, whist, hw, dt, fx, fy, fz, tx, ty, tz,
        )  # fmt: skip
    return fx, fy, fz, tx, ty, tz


@njit(cache=True, inline="always")
def add_plane_energy(en, i, P, IA, planes, pt):
    """``en`` plus the Hertz energy of particle i's overlaps with the planes (R* = R)."""
    ri = P[i, 9]
    for w in range(planes.shape[0]):
        dist = (
            (P[i, 0] - planes[w, 0]) * planes[w, 3]
            + (P[i, 1] - planes[w, 1]) * planes[w, 4]
            + (P[i, 2] - planes[w, 2]) * planes[w, 5]
        )
        if dist < ri:
            en += hertz_energy(pt[0, IA[i, 1], int(planes[w, 6])], ri, ri - dist)
    return en


@njit(cache=True, inline="always")
def add_cylinder_energy(en, i, P, IA, cyls, pt):
    """``en`` plus the Hertz energy of particle i's overlaps with the cylinders within their
    axial range (R* = R)."""
    ri = P[i, 9]
    for w in range(cyls.shape[0]):
        qx, qy, qz = P[i, 0] - cyls[w, 0], P[i, 1] - cyls[w, 1], P[i, 2] - cyls[w, 2]
        a = qx * cyls[w, 3] + qy * cyls[w, 4] + qz * cyls[w, 5]
        if a < cyls[w, 10] or a > cyls[w, 11]:
            continue
        s = math.sqrt(
            (qx - a * cyls[w, 3]) ** 2 + (qy - a * cyls[w, 4]) ** 2 + (qz - a * cyls[w, 5]) ** 2
        )
        delta = ri + s - cyls[w, 6] if cyls[w, 7] > 0 else ri - (s - cyls[w, 6])
        if delta > 0.0:
            en += hertz_energy(pt[0, IA[i, 1], int(cyls[w, 9])], ri, delta)
    return en
