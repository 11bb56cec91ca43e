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
- The scatter scheme (:func:`pair_scatter`, the default) replaces pass 1 and the pair part of
  pass 2: each pair added straight to both particles, no pair buffer; the owners are split into
  a fixed number of chunks, each summing into its own buffer on its own thread, and the gather
  adds the chunks in order (the same sums for any thread count; with one chunk, bit-identical
  to the two-pass scheme).

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
from .space import FMA, min_image

__all__ = [
    "add_pair_energy",
    "chunk_bounds",
    "chunk_sums",
    "gather_pair_slots",
    "pair_pass",
    "pair_scatter",
]


@njit(cache=True, inline="always")
def _pair_contact(P, IA, hist, pt, i, k, j, dx, dy, dz, d2, rs, dt):
    """Contact law of the owned pair (i, j) in contact (``d2 < rs^2``, separation ``d`` from i to
    j); updates ``hist[i, k]``. Returns the force on i (3), n x F_t (3), the rolling torque on i
    (3) and delta/2."""
    ri = P[i, 9]
    rj = P[j, 9]
    mi = P[i, 10]
    e_star, g_star, mu, mur, dmp, tn_ratio = pair_coefficients(pt, IA[i, 1], IA[j, 1])
    d = math.sqrt(d2)
    inv_d = 1.0 / d
    nx, ny, nz = dx * inv_d, dy * inv_d, dz * inv_d
    delta = rs - d
    mj = P[j, 10]
    inv = 1.0 / (rs * (mi + mj))  # one division for R* = ri rj / rs and m* = mi mj / (mi + mj)
    r_star = ri * rj * (mi + mj) * inv
    m_star = mi * mj * rs * inv
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
        e_star, g_star, mu, dmp, tn_ratio, r_star, m_star, delta, nx, ny, nz, rvx, rvy, rvz,
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


@njit(cache=True, parallel=True, fastmath=FMA)
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


@njit(cache=True)
def chunk_bounds(n, nown, bounds):
    """Split the owners 0..n-1 into ``K = bounds.size - 1`` consecutive chunks of about equal
    listed-pair count: ``bounds[c]`` is chunk c's first owner, ``bounds[K] = n``. A function of
    the lists only (not of the thread count), so the sums of :func:`pair_scatter` are too."""
    k = bounds.shape[0] - 1
    total = 0
    for i in range(n):
        total += nown[i]
    bounds[0] = 0
    c = 1
    run = 0
    for i in range(n):
        while c < k and run * k >= c * total:
            bounds[c] = i
            c += 1
        run += nown[i]
    while c <= k:
        bounds[c] = n
        c += 1


@njit(cache=True, parallel=True, fastmath=FMA)
def pair_scatter(n, P, IA, nb, nown, hist, acc, bounds, pt, dom, per, dt):
    """Scatter scheme: evaluate each owned pair once and add its force and torques straight to
    both particles' sums (Newton's third law), without the pair buffer of :func:`pair_pass`.

    The owners are split into ``K = acc.shape[0]`` chunks (:func:`chunk_bounds`); chunk c sums
    into its own buffer ``acc[c]`` (rows ``bounds[c]`` to n: an owner's partners have larger
    indices), so the chunks run on as many threads as there are, race-free, and the gather adds
    ``acc[0, i] + acc[1, i] + ...`` in chunk order (:func:`chunk_sums`): the same sums for any
    thread count. Within a chunk, owners are visited in index order and an owner i is always
    < j, so particle j receives the contributions of its owners (ascending) before its own slots
    (ascending). With one chunk that is the order in which :func:`gather_pair_slots` sums the
    reverse then the owned slots: bit-identical to the two-pass scheme.

    The chunks are a ``prange``: numba compiles a parallel region with its array arguments
    marked as not aliasing each other, so the compiler can keep loads of ``P`` and ``hist``
    across the stores to ``acc`` (about 15 % faster than the same loop in a plain ``njit``
    function, measured with one chunk).
    """
    chunk_bounds(n, nown, bounds)
    for c in prange(acc.shape[0]):
        a = acc[c]
        lo, hi = bounds[c], bounds[c + 1]
        l0, l1, l2 = dom[6], dom[7], dom[8]
        p0, p1, p2 = per[0] != 0, per[1] != 0, per[2] != 0
        for i in range(lo, n):
            for q in range(6):
                a[i, q] = 0.0
        for i in range(lo, hi):
            xi, yi, zi = P[i, 0], P[i, 1], P[i, 2]
            ri = P[i, 9]
            fx, fy, fz = a[i, 0], a[i, 1], a[i, 2]
            tx, ty, tz = a[i, 3], a[i, 4], a[i, 5]
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
                cc = ri - hd
                fx += f0
                fy += f1
                fz += f2
                tx += cc * t0 + r0
                ty += cc * t1 + r1
                tz += cc * t2 + r2
                cc = rj - hd
                a[j, 0] -= f0
                a[j, 1] -= f1
                a[j, 2] -= f2
                a[j, 3] += cc * t0 - r0
                a[j, 4] += cc * t1 - r1
                a[j, 5] += cc * t2 - r2
            a[i, 0] = fx
            a[i, 1] = fy
            a[i, 2] = fz
            a[i, 3] = tx
            a[i, 4] = ty
            a[i, 5] = tz


@njit(cache=True, inline="always")
def chunk_sums(i, acc, bounds):
    """Pair force and torque (6) on particle i from the chunk buffers of :func:`pair_scatter`,
    added in chunk order (chunks whose owners all come after i hold nothing for it)."""
    fx, fy, fz = acc[0, i, 0], acc[0, i, 1], acc[0, i, 2]
    tx, ty, tz = acc[0, i, 3], acc[0, i, 4], acc[0, i, 5]
    for c in range(1, acc.shape[0]):
        if bounds[c] > i:
            break
        fx += acc[c, i, 0]
        fy += acc[c, i, 1]
        fz += acc[c, i, 2]
        tx += acc[c, i, 3]
        ty += acc[c, i, 4]
        tz += acc[c, i, 5]
    return fx, fy, fz, tx, ty, tz


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
