"""Particle-particle contacts of the DEM engine (LIGGGHTS' ``pair gran``): the contact of one
listed pair, and the two race-free schemes that sum the pair forces of all particles.

Parallel scheme (no data races, deterministic for any thread count)

- The neighbour list is a half list (:mod:`twin_core.dem.partition`): each pair (i, j) with
  i < j is *owned* by i and stored in ``nb[i, k]``; its tangential history is ``hist[i, k]``
  (from i's point of view).
- Pass 1 (:func:`pair_pass`, ``prange`` over particles): each particle evaluates its owned pairs
  once and writes the pair force/torques into ``pf[i, k]`` (only its own rows: no race).
- Pass 2 (the integrator's ``gather_pass``): each particle sums, in a fixed order, the slots of
  the pairs owned by others that involve it (reverse list ``rev_o, rev_k``, owners ascending;
  Newton's third law), then its owned slots (:func:`gather_pair_slots`).
- One thread: :func:`pair_scatter` replaces pass 1 and the pair part of pass 2 (each pair added
  straight to both particles, in the gather's order: bit-identical sums, no pair buffer).

Pair slot ``pf[i, k]``: force on i (3), n x F_t (3), rolling torque on i (3), delta/2 (1; 0 for
a slot not in contact). The torque of the tangential force on i is ``(R_i - delta/2) n x F_t``
and on j ``(R_j - delta/2) n x F_t`` (same sign: n and F_t both flip for j).

References: Plimpton (1995), J. Comput. Phys. 117, 1 (half lists, Newton's third law); Kloss et
al. (2012), Prog. Comput. Fluid Dyn. 12, 140 (LIGGGHTS granular pair styles); contact law in
:mod:`twin_core.dem.contact`.
"""

from __future__ import annotations

import math

from numba import njit, prange

from .contact import (
    clear_history,
    hertz_energy,
    hertz_mindlin,
    pair_coefficients,
    rolling_torque,
)
from .space import min_image

__all__ = ["add_pair_energy", "gather_pair_slots", "pair_pass", "pair_scatter"]


@njit(cache=True, inline="always")
def _pair_contact(P, IA, hist, pt, i, k, j, dx, dy, dz, d2, rs, dt):
    """Contact law of the owned pair (i, j) in contact (``d2 < rs^2``, separation ``d`` from i to
    j); updates ``hist[i, k]``. Returns the force on i (3), n x F_t (3), the rolling torque on i
    (3) and delta/2."""
    ri = P[i, 9]
    rj = P[j, 9]
    mi = P[i, 10]
    e_star, g_star, mu, mur, dmp = pair_coefficients(pt, IA[i, 1], IA[j, 1])
    d = math.sqrt(d2)
    inv_d = 1.0 / d
    nx, ny, nz = dx * inv_d, dy * inv_d, dz * inv_d
    delta = rs - d
    mj = P[j, 10]
    r_star = ri * rj / rs
    m_star = mi * mj / (mi + mj)
    ci = ri - 0.5 * delta
    cj = rj - 0.5 * delta
    wxi, wyi, wzi = P[i, 6], P[i, 7], P[i, 8]
    wxj, wyj, wzj = P[j, 6], P[j, 7], P[j, 8]
    ax = ci * wxi + cj * wxj
    ay = ci * wyi + cj * wyj
    az = ci * wzi + cj * wzj
    rvx = P[i, 3] - P[j, 3] + (ay * nz - az * ny)
    rvy = P[i, 4] - P[j, 4] + (az * nx - ax * nz)
    rvz = P[i, 5] - P[j, 5] + (ax * ny - ay * nx)
    fn, ftx, fty, ftz, hx, hy, hz = hertz_mindlin(
        e_star, g_star, mu, dmp, r_star, m_star, delta, nx, ny, nz, rvx, rvy, rvz,
        hist[i, k, 0], hist[i, k, 1], hist[i, k, 2], dt,
    )  # fmt: skip
    hist[i, k, 0] = hx
    hist[i, k, 1] = hy
    hist[i, k, 2] = hz
    trx, try_, trz = rolling_torque(
        mur, fn, r_star, wxi - wxj, wyi - wyj, wzi - wzj, dt * (P[i, 12] + P[j, 12])
    )
    return (
        -fn * nx + ftx,
        -fn * ny + fty,
        -fn * nz + ftz,
        ny * ftz - nz * fty,
        nz * ftx - nx * ftz,
        nx * fty - ny * ftx,
        trx,
        try_,
        trz,
        0.5 * delta,
    )


@njit(cache=True, parallel=True)
def pair_pass(n, P, F, IA, nb, nown, hist, pf, pt, dom, per, dt):
    """Pass 1 (parallel scheme): evaluate each owned pair once; write ``pf[i, k]`` and update
    ``hist[i, k]``.

    Velocities in ``P`` are at the half step (t + dt/2): they integrate the tangential spring
    (``xi += v_t dt``, midpoint rule) and drive the dashpots (as in LIGGGHTS). ``F`` (previous
    forces) is not used by the contact law.
    """
    l0, l1, l2 = dom[6], dom[7], dom[8]
    p0, p1, p2 = per[0] != 0, per[1] != 0, per[2] != 0
    for i in prange(n):
        xi, yi, zi = P[i, 0], P[i, 1], P[i, 2]
        ri = P[i, 9]
        for k in range(nown[i]):
            j = nb[i, k]
            dx = min_image(P[j, 0] - xi, l0, p0)
            dy = min_image(P[j, 1] - yi, l1, p1)
            dz = min_image(P[j, 2] - zi, l2, p2)
            rs = ri + P[j, 9]
            d2 = dx * dx + dy * dy + dz * dz
            if d2 >= rs * rs:
                # not in contact: flag the slot (delta/2 = 0) and clear a stale history
                pf[i, k, 9] = 0.0
                clear_history(hist, i, k)
                continue
            f0, f1, f2, t0, t1, t2, r0, r1, r2, hd = _pair_contact(
                P, IA, hist, pt, i, k, j, dx, dy, dz, d2, rs, dt
            )
            pf[i, k, 0] = f0
            pf[i, k, 1] = f1
            pf[i, k, 2] = f2
            pf[i, k, 3] = t0
            pf[i, k, 4] = t1
            pf[i, k, 5] = t2
            pf[i, k, 6] = r0
            pf[i, k, 7] = r1
            pf[i, k, 8] = r2
            pf[i, k, 9] = hd


@njit(cache=True, parallel=True)
def pair_scatter(n, P, IA, nb, nown, hist, acc, pt, dom, per, dt):
    """Serial scheme (one thread): evaluate each owned pair once and add its force and torques
    straight to both particles' sums ``acc[i]`` and ``acc[j]`` (Newton's third law), without the
    pair buffer of :func:`pair_pass`.

    Particles are visited in index order and an owner i is always < j, so particle j receives the
    contributions of its owners (ascending) before its own slots (ascending): the order in which
    :func:`gather_pair_slots` sums the reverse then the owned slots. The sums are therefore
    bit-identical to the parallel scheme.

    The serial loop is wrapped in a one-iteration ``prange``: it runs on one thread whatever the
    thread count (no race), and numba compiles a parallel region with its array arguments marked
    as not aliasing each other, so the compiler can keep loads of ``P`` and ``hist`` across the
    stores to ``acc`` (about 15 % faster than the same loop in a plain ``njit`` function).
    """
    for _ in prange(1):
        l0, l1, l2 = dom[6], dom[7], dom[8]
        p0, p1, p2 = per[0] != 0, per[1] != 0, per[2] != 0
        for i in range(n):
            for a in range(6):
                acc[i, a] = 0.0
        for i in range(n):
            xi, yi, zi = P[i, 0], P[i, 1], P[i, 2]
            ri = P[i, 9]
            fx, fy, fz = acc[i, 0], acc[i, 1], acc[i, 2]
            tx, ty, tz = acc[i, 3], acc[i, 4], acc[i, 5]
            for k in range(nown[i]):
                j = nb[i, k]
                dx = min_image(P[j, 0] - xi, l0, p0)
                dy = min_image(P[j, 1] - yi, l1, p1)
                dz = min_image(P[j, 2] - zi, l2, p2)
                rj = P[j, 9]
                rs = ri + rj
                d2 = dx * dx + dy * dy + dz * dz
                if d2 >= rs * rs:
                    clear_history(hist, i, k)
                    continue
                f0, f1, f2, t0, t1, t2, r0, r1, r2, hd = _pair_contact(
                    P, IA, hist, pt, i, k, j, dx, dy, dz, d2, rs, dt
                )
                c = ri - hd
                fx += f0
                fy += f1
                fz += f2
                tx += c * t0 + r0
                ty += c * t1 + r1
                tz += c * t2 + r2
                c = rj - hd
                acc[j, 0] -= f0
                acc[j, 1] -= f1
                acc[j, 2] -= f2
                acc[j, 3] += c * t0 - r0
                acc[j, 4] += c * t1 - r1
                acc[j, 5] += c * t2 - r2
            acc[i, 0] = fx
            acc[i, 1] = fy
            acc[i, 2] = fz
            acc[i, 3] = tx
            acc[i, 4] = ty
            acc[i, 5] = tz


@njit(cache=True, inline="always")
def gather_pair_slots(i, ri, pf, nrev, rev_o, rev_k, nown):
    """Pair force and torque (6) on particle i (radius ``ri``) from the slots written by
    :func:`pair_pass`: first the slots of the pairs owned by others (reverse list, owners
    ascending, Newton's third law), then its owned slots (ascending), skipping slots not in
    contact (their other entries are stale)."""
    fx = 0.0
    fy = 0.0
    fz = 0.0
    tx = 0.0
    ty = 0.0
    tz = 0.0
    for q in range(nrev[i]):
        o = rev_o[i, q]
        s = rev_k[i, q]
        hd = pf[o, s, 9]
        if hd == 0.0:
            continue
        c = ri - hd
        fx -= pf[o, s, 0]
        fy -= pf[o, s, 1]
        fz -= pf[o, s, 2]
        tx += c * pf[o, s, 3] - pf[o, s, 6]
        ty += c * pf[o, s, 4] - pf[o, s, 7]
        tz += c * pf[o, s, 5] - pf[o, s, 8]
    for k in range(nown[i]):
        hd = pf[i, k, 9]
        if hd == 0.0:
            continue
        c = ri - hd
        fx += pf[i, k, 0]
        fy += pf[i, k, 1]
        fz += pf[i, k, 2]
        tx += c * pf[i, k, 3] + pf[i, k, 6]
        ty += c * pf[i, k, 4] + pf[i, k, 7]
        tz += c * pf[i, k, 5] + pf[i, k, 8]
    return fx, fy, fz, tx, ty, tz


@njit(cache=True, inline="always")
def add_pair_energy(en, i, P, IA, nb, nown, pt, dom, per):
    """``en`` plus the Hertz energy of particle i's overlaps with the particles it owns in the
    half list (each pair counted once)."""
    ri = P[i, 9]
    for k in range(nown[i]):
        j = nb[i, k]
        dx = min_image(P[j, 0] - P[i, 0], dom[6], per[0] != 0)
        dy = min_image(P[j, 1] - P[i, 1], dom[7], per[1] != 0)
        dz = min_image(P[j, 2] - P[i, 2], dom[8], per[2] != 0)
        rs = ri + P[j, 9]
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        if d < rs:
            en += hertz_energy(pt[0, IA[i, 1], IA[j, 1]], ri * P[j, 9] / rs, rs - d)
    return en
