"""Contact law of the DEM engine (LIGGGHTS' ``pair gran`` model; jax-md's ``energy``): the force
and torque of one contact, shared by particle-particle, particle-wall and particle-mesh contacts.

Per contact, overlap delta > 0, R* = R1 R2/(R1+R2), m* = m1 m2/(m1+m2) (against a wall R* = R,
m* = m):

- normal: ``F_n = (4/3) E* sqrt(R* delta) delta + d sqrt(S_n m*) v_n``,
  ``S_n = 2 E* sqrt(R* delta)`` (Hertz; Tsuji damping), clamped at ``F_n >= 0`` (no attraction);
- tangential: spring ``xi`` (shear displacement) kept per contact, rotated into the current
  tangent plane each step (magnitude kept), ``xi += v_t dt``,
  ``F_t = -S_t xi - d sqrt(S_t m*) v_t`` with ``S_t = 8 G* sqrt(R* delta)`` (Mindlin no-slip);
  if ``|F_t| > mu_s F_n`` the force is scaled to the Coulomb limit and the spring truncated to
  ``xi = -(F_t + d sqrt(S_t m*) v_t) / S_t`` (LAMMPS ``gran/hertz/history``);
- rolling: constant directional torque ``-mu_r F_n R* w_rel/|w_rel|`` (LIGGGHTS ``cdt``; Ai et
  al. 2011 model A), capped so that it cannot reverse ``w_rel`` within one step;
- elastic energy of the normal spring: ``(8/15) E* sqrt(R*) delta^(5/2)``.

The coefficients come from the material-pair tables ``pt`` (:meth:`MaterialTable.tables`):
``pt[0]`` E*, ``pt[1]`` G*, ``pt[2]`` mu_s, ``pt[3]`` mu_r, ``pt[4]`` damping factor d,
``pt[5]`` sqrt(4 G*/E*) (the tangential dashpot's ratio to the normal one).

References: Hertz (1882); Mindlin & Deresiewicz (1953); Tsuji, Tanaka & Ishida (1992), Powder
Technol. 71, 239; Brilliantov et al. (1996), Phys. Rev. E 53, 5382 (LAMMPS ``gran/hertz/history``);
Ai, Chen, Rotter & Ooi (2011), Powder Technol. 206, 269 (rolling model A); Johnson, Contact
Mechanics (1985), Eq. 4.23 (Hertz energy).
"""

from __future__ import annotations

import math

from numba import njit

from .space import FMA

__all__ = [
    "add_wall_contact",
    "clear_history",
    "hertz_energy",
    "hertz_mindlin",
    "pair_coefficients",
    "rolling_torque",
    "rotating_wall_velocity",
    "spring_set",
    "wall_contact",
    "wall_law",
]

_TWO_THIRDS = 2.0 / 3.0


@njit(cache=True, inline="always")
def spring_set(h, i, k):
    """Whether the tangential spring ``h[i, k]`` (3,) is not zero (without branches)."""
    return (h[i, k, 0] != 0.0) | (h[i, k, 1] != 0.0) | (h[i, k, 2] != 0.0)


@njit(cache=True, inline="always")
def clear_history(h, i, k):
    """Zero the tangential spring ``h[i, k]`` (3,) of a contact that has ended, if it is not zero
    already (reads are cheaper than writes: most slots are clear; avoids dirtying cache lines)."""
    if spring_set(h, i, k):
        h[i, k, 0] = 0.0
        h[i, k, 1] = 0.0
        h[i, k, 2] = 0.0


@njit(cache=True, inline="always")
def pair_coefficients(pt, mat_a, mat_b):
    """Coefficients of the material pair (a, b) from the tables ``pt``:
    (E*, G*, mu_s, mu_r, damping factor d, sqrt(4 G*/E*))."""
    return (
        pt[0, mat_a, mat_b],
        pt[1, mat_a, mat_b],
        pt[2, mat_a, mat_b],
        pt[3, mat_a, mat_b],
        pt[4, mat_a, mat_b],
        pt[5, mat_a, mat_b],
    )


@njit(cache=True, inline="always")
def hertz_mindlin(
    e_star, g_star, mu, dmp, tn_ratio, r_eff, m_eff, delta, nx, ny, nz, rvx, rvy, rvz, hx, hy, hz,
    dt,
):  # fmt: skip
    """Normal and tangential contact force (module docstring; Hertz-Mindlin no-slip, Tsuji
    damping, Coulomb-truncated tangential spring as LAMMPS ``gran/hertz/history``).

    ``F_n = (2/3) S_n delta + d sqrt(S_n m*) v_n``, ``S_n = 2 E* sqrt(R* delta)``, clamped >= 0;
    the spring (hx, hy, hz) is rotated into the tangent plane (magnitude kept), advanced by
    ``v_t dt``, ``F_t = -S_t xi - d sqrt(S_t m*) v_t``, ``S_t = 8 G* sqrt(R* delta)``, and if
    ``|F_t| > mu F_n`` scaled to the limit with ``xi = -(F_t + d sqrt(S_t m*) v_t) / S_t``.
    ``rv``: relative velocity at the contact point (first body minus second), split into
    ``v_n = rv . n`` and ``v_t = rv - v_n n``; ``tn_ratio = sqrt(4 G*/E*)`` gives the tangential
    dashpot ``d sqrt(S_t m*)`` from the normal one. The dashpots use the same (half-step) velocities
    as the springs (a velocity predicted from the previous force, v + F/m dt/2, is unstable for
    strongly damped, many-contact beds). Returns (F_n, F_t x, y, z, new spring x, y, z).
    """
    vn = rvx * nx + rvy * ny + rvz * nz
    vtx = rvx - vn * nx
    vty = rvy - vn * ny
    vtz = rvz - vn * nz
    sq = math.sqrt(r_eff * delta)
    sn = 2.0 * e_star * sq
    st = 8.0 * g_star * sq
    cn = dmp * math.sqrt(sn * m_eff)
    fn = _TWO_THIRDS * sn * delta + cn * vn
    if fn < 0.0:
        fn = 0.0
    h2 = hx * hx + hy * hy + hz * hz
    if h2 > 0.0:
        hn = hx * nx + hy * ny + hz * nz
        hx -= hn * nx
        hy -= hn * ny
        hz -= hn * nz
        h2n = hx * hx + hy * hy + hz * hz
        if h2n > 0.0:
            s = math.sqrt(h2 / h2n)
            hx *= s
            hy *= s
            hz *= s
    hx += vtx * dt
    hy += vty * dt
    hz += vtz * dt
    ct = cn * tn_ratio  # d sqrt(S_t m*) = d sqrt(S_n m*) sqrt(4 G*/E*)
    ftx = -st * hx - ct * vtx
    fty = -st * hy - ct * vty
    ftz = -st * hz - ct * vtz
    ft2 = ftx * ftx + fty * fty + ftz * ftz
    fmax = mu * fn
    if ft2 > fmax * fmax:
        if ft2 > 0.0:
            s = fmax / math.sqrt(ft2)
            ftx *= s
            fty *= s
            ftz *= s
            inv_st = -1.0 / st
            hx = (ftx + ct * vtx) * inv_st
            hy = (fty + ct * vty) * inv_st
            hz = (ftz + ct * vtz) * inv_st
    return fn, ftx, fty, ftz, hx, hy, hz


@njit(cache=True, inline="always")
def rolling_torque(mur, fn, r_eff, rwx, rwy, rwz, dt_inv_i):
    """Constant directional rolling torque ``-mu_r F_n R* w_rel/|w_rel|`` (LIGGGHTS ``cdt``;
    Ai et al. 2011 model A), capped at ``|w_rel| / (dt (1/I_1 + 1/I_2))`` so that it cannot
    reverse the relative rotation within a step (``dt_inv_i`` = dt times that inverse-inertia
    sum). Returns the torque on the first body."""
    if mur > 0.0:
        wm = math.sqrt(rwx * rwx + rwy * rwy + rwz * rwz)
        if wm > 0.0:
            tr = mur * fn * r_eff
            if tr * dt_inv_i > wm:
                s = 1.0 / dt_inv_i  # the cap: tr = wm / dt_inv_i
            else:
                s = tr / wm
            return -s * rwx, -s * rwy, -s * rwz
    return 0.0, 0.0, 0.0


@njit(cache=True, inline="always")
def hertz_energy(e_star, r_eff, delta):
    """Elastic energy ``(8/15) E* sqrt(R*) delta^(5/2)`` of a Hertz contact of overlap delta
    (the potential of the normal spring ``F_n = (4/3) E* sqrt(R*) delta^(3/2)``; Johnson 1985)."""
    return 8.0 / 15.0 * e_star * math.sqrt(r_eff) * delta**2.5


@njit(cache=True, inline="always")
def rotating_wall_velocity(om, ux, uy, uz, rx, ry, rz):
    """Velocity ``omega u x r`` of the point at r from the axis point of a wall turning at omega
    about the unit axis u (rigid rotation)."""
    return om * (uy * rz - uz * ry), om * (uz * rx - ux * rz), om * (ux * ry - uy * rx)


@njit(cache=True, inline="always")
def wall_law(
    vx, vy, vz, wx, wy, wz, r, m, inv_i, nx, ny, nz, delta, vwx, vwy, vwz, wwx, wwy, wwz,
    e_star, g_star, mu, mur, dmp, tn_ratio, hx, hy, hz, dt,
):  # fmt: skip
    """Hertz-Mindlin force and torque on a sphere (velocity v, angular velocity w, radius r,
    mass m, inverse inertia) touching an infinitely massive wall (module docstring, with
    R* = R, m* = m; coefficients of the sphere-wall material pair; spring (hx, hy, hz)).

    ``n`` points from the sphere centre to the contact; the lever arm is ``c = r - delta``; the
    wall moves at ``vw`` at the contact point and rotates at ``ww``: relative velocity at the
    contact ``v + c (w x n) - vw``, torque ``c n x F_t + M_r`` with the rolling torque of
    ``w - ww``. Straight-line code (selects only), so that a loop over contacts is compiled to
    SIMD code (:func:`twin_core.dem.mesh_contacts.mesh_pass`). Returns (fx, fy, fz, tx, ty, tz,
    new spring x, y, z)."""
    c = r - delta
    # contact point velocity of the sphere minus wall velocity
    rvx = vx + c * (wy * nz - wz * ny) - vwx
    rvy = vy + c * (wz * nx - wx * nz) - vwy
    rvz = vz + c * (wx * ny - wy * nx) - vwz
    fn, ftx, fty, ftz, hx, hy, hz = hertz_mindlin(
        e_star, g_star, mu, dmp, tn_ratio, r, m, delta, nx, ny, nz, rvx, rvy, rvz, hx, hy, hz, dt
    )
    # torque of the tangential force: (c n) x ft
    tx = c * (ny * ftz - nz * fty)
    ty = c * (nz * ftx - nx * ftz)
    tz = c * (nx * fty - ny * ftx)
    # rolling friction (constant directional torque)
    trx, try_, trz = rolling_torque(mur, fn, r, wx - wwx, wy - wwy, wz - wwz, dt * inv_i)
    return (
        -fn * nx + ftx, -fn * ny + fty, -fn * nz + ftz, tx + trx, ty + try_, tz + trz,
        hx, hy, hz,
    )  # fmt: skip


@njit(cache=True, fastmath=FMA)
def wall_contact(
    vx, vy, vz, wx, wy, wz, r, m, inv_i, mat_p,
    nx, ny, nz, delta, vwx, vwy, vwz, wwx, wwy, wwz, mat_w, pt, hist, i, k, dt,
):  # fmt: skip
    """:func:`wall_law` of a sphere of material ``mat_p`` touching a wall of material ``mat_w``
    (coefficients from the tables ``pt``), its spring ``hist[i, k]`` (3,) updated in place
    (indexed, not passed as a view: a view costs a reference count per contact). Returns
    (fx, fy, fz, tx, ty, tz). Compiled once and called by the plane and cylinder loops (not
    inlined: it is the largest piece of their code)."""
    e_star, g_star, mu, mur, dmp, tn_ratio = pair_coefficients(pt, mat_p, mat_w)
    fx, fy, fz, tx, ty, tz, hx, hy, hz = wall_law(
        vx, vy, vz, wx, wy, wz, r, m, inv_i, nx, ny, nz, delta, vwx, vwy, vwz, wwx, wwy, wwz,
        e_star, g_star, mu, mur, dmp, tn_ratio, hist[i, k, 0], hist[i, k, 1], hist[i, k, 2], dt,
    )  # fmt: skip
    hist[i, k, 0] = hx
    hist[i, k, 1] = hy
    hist[i, k, 2] = hz
    return fx, fy, fz, tx, ty, tz


@njit(cache=True, inline="always")
def add_wall_contact(
    P, IA, i, nx, ny, nz, delta, vwx, vwy, vwz, wwx, wwy, wwz, mat_w, pt, hist, k, dt,
    fx, fy, fz, tx, ty, tz,
):  # fmt: skip
    """Add to sphere i's force and torque sums (fx .. tz) its :func:`wall_contact` (state row
    ``P[i]``, material ``IA[i, 1]``, spring ``hist[i, k]``). Returns the new
    (fx, fy, fz, tx, ty, tz)."""
    a, b, c, d, e, f = wall_contact(
        P[i, 3], P[i, 4], P[i, 5], P[i, 6], P[i, 7], P[i, 8], P[i, 9], P[i, 10], P[i, 12],
        IA[i, 1], nx, ny, nz, delta, vwx, vwy, vwz, wwx, wwy, wwz, mat_w, pt, hist, i, k, dt,
    )  # fmt: skip
    return fx + a, fy + b, fz + c, tx + d, ty + e, tz + f
