"""Particle-particle contacts of the DEM engine (LIGGGHTS' ``pair gran``): the contact of one
listed pair, and the two race-free schemes that sum the pair forces of all particles.

Parallel scheme (no data races, deterministic for any thread count)

- The neighbour list is a half list (:mod:`twin_core.dem.partition`): each pair (i, j) with
  i < j is *owned* by i and stored in ``nb[i, k]``; its tangential history is ``hist[i, k]``
  (from i's point of view).
- Pass 1 (:func:`pair_pass`): each owned pair is evaluated once and its force/torques written
  into ``pf[i, k]`` (only the owner's rows: no race).
- Pass 2 (the integrator's ``gather_pass``): each particle sums, in a fixed order, the slots of
  the pairs owned by others that involve it (reverse list ``rev_o, rev_k``, owners ascending;
  Newton's third law), then its owned slots (:func:`gather_pair_slots`).
- The scatter scheme (:func:`pair_scatter`, the default) replaces pass 1 and the pair part of
  pass 2: each pair added straight to both particles, no pair buffer; the owners are split into
  a fixed number of chunks, each summing into its own buffer on its own thread, and the gather
  adds the chunks in order (the same sums for any thread count; with one chunk, bit-identical
  to the two-pass scheme).

Batched contact law (both schemes, per chunk of owners, as LIGGGHTS splits the pair loop from
the contact model but with the model vectorised): the pairs in contact are found first
(:func:`find_contacts`, branch-free on the contact test), then evaluated in blocks of
:data:`BLOCK` contacts: their inputs copied into the rows of a small buffer
(:func:`_load_block`), the law computed over the block by one loop that the compiler turns into
SIMD code (:func:`contact_block`: the scalar law of :mod:`twin_core.dem.contact`, inlined), and
the results added in contact order. Work arrays, derived from the lists after each rebuild and
before each run of steps (:func:`flatten_pairs`): ``pstart`` (cap + 1) and ``nbf`` (2, cap *
kown) int32, the half list packed (owner i's pairs are ``pstart[i]`` to ``pstart[i + 1]``, row 0
their owner, row 1 their partner: the search over all listed pairs is one loop that reads 8
bytes per pair, not a loop per owner over the rows of ``nb`` padded to the widest row), and
``live`` (cap * kown) uint8, the packed pairs whose spring may be non-zero; ``clist``
(3, cap * kown) int32, the contacts (owner, slot, partner) of each chunk from offset
``pstart[bounds[c]]``; ``work`` (chunks, :data:`BLOCK_WORDS`), one block buffer per chunk.

Pair slot ``pf[i, k]``: force on i (3), torque on i (3), torque on j (3), delta/2 (1; 0 for a
slot not in contact). The torque of the tangential force on i is ``(R_i - delta/2) n x F_t``
and on j ``(R_j - delta/2) n x F_t`` (same sign: n and F_t both flip for j); the rolling torque
is added on i and subtracted on j.

References: Plimpton (1995), J. Comput. Phys. 117, 1 (half lists, Newton's third law); Kloss et
al. (2012), Prog. Comput. Fluid Dyn. 12, 140 (LIGGGHTS granular pair styles); contact law in
:mod:`twin_core.dem.contact`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .contact import (
    clear_history,
    hertz_energy,
    hertz_mindlin,
    pair_coefficients,
    rolling_torque,
    spring_set,
)
from .space import FMA, min_image

__all__ = [
    "BLOCK",
    "BLOCK_WORDS",
    "add_pair_energy",
    "chunk_bounds",
    "chunk_sums",
    "contact_block",
    "find_contacts",
    "flatten_pairs",
    "gather_pair_slots",
    "pair_pass",
    "pair_scatter",
]


#: contacts per block of the batched contact law (its inputs and results stay in L1)
BLOCK = 128
_ROW = BLOCK + 8  # row stride of a block buffer: rows 1 KiB apart would share L1 sets
_NIN = 27  # input rows of a block (see _load_block)
_NOUT = 13  # result rows (see contact_block)
#: words of one chunk's block buffer (``work[c]``)
BLOCK_WORDS = (_NIN + _NOUT) * _ROW


@njit(cache=True)
def flatten_pairs(n, nb, nown, hist, pstart, nbf, live):
    """The half list ``nb`` packed: ``pstart[i]`` the first packed pair of owner i, ``nbf[0, p]``
    the owner and ``nbf[1, p]`` the partner of packed pair p (slot ``p - pstart[i]`` of owner
    i), and ``live[p] = 1`` where that pair's tangential spring is not zero (the pairs whose
    spring must be cleared when they are found apart). Derived from the lists and springs, so it
    is redone after each list rebuild and before each run of steps."""
    p = 0
    for i in range(n):
        pstart[i] = p
        for k in range(nown[i]):
            nbf[0, p] = i
            nbf[1, p] = nb[i, k]
            live[p] = spring_set(hist, i, k)
            p += 1
    pstart[n] = p


@njit(cache=True, fastmath=FMA)
def find_contacts(lo, hi, P, nbf, pstart, hist, live, dom, per, clist):
    """The owned pairs of owners ``lo .. hi-1`` in contact, in owner then slot order, written as
    (owner, slot, partner) to ``clist[:, pstart[lo]:]``; returns their count. A listed pair
    found apart has its spring cleared if it was live (packed lists of :func:`flatten_pairs`).

    One loop over the packed pairs (not a loop per owner: the exit of an inner loop of a few
    pairs is mispredicted once per owner), branch-free on the contact test (taken about one
    time in four, unpredictably): each listed pair is written to the next free entry, which is
    kept when the pair is in contact; the spring is cleared under ``live > in contact``, rarely
    true. Indices read from arrays are cast to unsigned (:mod:`twin_core.dem.space`, "Indexing")."""
    l0, l1, l2 = dom[6], dom[7], dom[8]
    p0, p1, p2 = per[0] != 0, per[1] != 0, per[2] != 0
    off = np.uint64(pstart[lo])
    m = off
    for p in range(off, np.uint64(pstart[hi])):
        i = np.uint64(nbf[0, p])
        j = np.uint64(nbf[1, p])
        dx = min_image(P[j, 0] - P[i, 0], l0, p0)
        dy = min_image(P[j, 1] - P[i, 1], l1, p1)
        dz = min_image(P[j, 2] - P[i, 2], l2, p2)
        rs = P[i, 9] + P[j, 9]
        touch = np.uint8(dx * dx + dy * dy + dz * dz < rs * rs)
        k = np.uint32(p - np.uint64(pstart[i]))
        clist[0, m] = i
        clist[1, m] = k
        clist[2, m] = j
        m += np.uint64(touch)
        stale = live[p] > touch
        live[p] = touch
        if stale:
            clear_history(hist, i, k)
    return np.int64(m - off)


@njit(cache=True)
def _load_block(clist, q0, nq, P, IA, hist, pt, dom, per, w):
    """Copy the inputs of contacts ``clist[:, q0:q0+nq]`` into the rows of the block buffer
    ``w`` (one row per quantity, one column per contact): separation (3), radii and masses (4),
    relative velocity (3), angular velocities (6), inverse-inertia sum, spring (3), material
    pair coefficients (6) and the code of that material pair (1; :func:`_forget_pairs` resets the
    codes at the start of each evaluation, so the coefficients come from the current tables)."""
    l0, l1, l2 = dom[6], dom[7], dom[8]
    p0, p1, p2 = per[0] != 0, per[1] != 0, per[2] != 0
    for q in range(nq):
        i = np.uint64(clist[0, q0 + q])
        k = np.uint64(clist[1, q0 + q])
        j = np.uint64(clist[2, q0 + q])
        w[q] = min_image(P[j, 0] - P[i, 0], l0, p0)
        w[_ROW + q] = min_image(P[j, 1] - P[i, 1], l1, p1)
        w[2 * _ROW + q] = min_image(P[j, 2] - P[i, 2], l2, p2)
        w[3 * _ROW + q] = P[i, 9]
        w[4 * _ROW + q] = P[j, 9]
        w[5 * _ROW + q] = P[i, 10]
        w[6 * _ROW + q] = P[j, 10]
        w[7 * _ROW + q] = P[i, 3] - P[j, 3]
        w[8 * _ROW + q] = P[i, 4] - P[j, 4]
        w[9 * _ROW + q] = P[i, 5] - P[j, 5]
        w[10 * _ROW + q] = P[i, 6]
        w[11 * _ROW + q] = P[i, 7]
        w[12 * _ROW + q] = P[i, 8]
        w[13 * _ROW + q] = P[j, 6]
        w[14 * _ROW + q] = P[j, 7]
        w[15 * _ROW + q] = P[j, 8]
        w[16 * _ROW + q] = P[i, 12] + P[j, 12]
        w[17 * _ROW + q] = hist[i, k, 0]
        w[18 * _ROW + q] = hist[i, k, 1]
        w[19 * _ROW + q] = hist[i, k, 2]
        # the coefficients are written only when the column held another material pair
        # (row 26: its code): a bed of one material writes them once
        a = IA[i, 1]
        b = IA[j, 1]
        code = float(a * pt.shape[2] + b)
        if w[26 * _ROW + q] != code:
            w[26 * _ROW + q] = code
            e_star, g_star, mu, mur, dmp, tn_ratio = pair_coefficients(pt, a, b)
            w[20 * _ROW + q] = e_star
            w[21 * _ROW + q] = g_star
            w[22 * _ROW + q] = mu
            w[23 * _ROW + q] = mur
            w[24 * _ROW + q] = dmp
            w[25 * _ROW + q] = tn_ratio


@njit(cache=True, inline="always")
def _forget_pairs(w):
    """Mark every column of the block buffer ``w`` as holding no material pair's coefficients."""
    for q in range(BLOCK):
        w[26 * _ROW + q] = -1.0


@njit(cache=True, fastmath=FMA, error_model="numpy")
def contact_block(nq, w, dt):
    """Contact law (:func:`twin_core.dem.contact.hertz_mindlin`, :func:`rolling_torque`) of the
    ``nq`` contacts of a block buffer (rows of :func:`_load_block`); writes per contact the
    force on the owner i (3), the torques on i and on the partner j (3 + 3), delta/2 and the new
    spring (3).

    Geometry of a pair with separation d from i to j: ``n = d/|d|``, ``delta = R_i + R_j - |d|``,
    ``R* = R_i R_j/(R_i + R_j)``, ``m* = m_i m_j/(m_i + m_j)``; relative velocity at the contact
    point ``v_i - v_j + (c_i w_i + c_j w_j) x n`` with lever arms ``c = R - delta/2``; torques
    ``c_i n x F_t + M_r`` on i and ``c_j n x F_t - M_r`` on j (``M_r`` the rolling torque).
    One loop over columns without branches that LLVM cannot turn into selects: it is compiled to
    SIMD code (four or eight contacts per instruction, square roots and divisions included)
    and gives the same bits as the scalar law, contact by contact, in any column.
    """
    for q in range(nq):
        dx = w[q]
        dy = w[_ROW + q]
        dz = w[2 * _ROW + q]
        ri = w[3 * _ROW + q]
        rj = w[4 * _ROW + q]
        mi = w[5 * _ROW + q]
        mj = w[6 * _ROW + q]
        rs = ri + rj
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        inv_d = 1.0 / d
        nx, ny, nz = dx * inv_d, dy * inv_d, dz * inv_d
        delta = rs - d
        inv = 1.0 / (rs * (mi + mj))  # one division for R* = ri rj / rs and m* = mi mj / (mi + mj)
        r_star = ri * rj * (mi + mj) * inv
        m_star = mi * mj * rs * inv
        ci = ri - 0.5 * delta
        cj = rj - 0.5 * delta
        wxi, wyi, wzi = w[10 * _ROW + q], w[11 * _ROW + q], w[12 * _ROW + q]
        wxj, wyj, wzj = w[13 * _ROW + q], w[14 * _ROW + q], w[15 * _ROW + q]
        ax = ci * wxi + cj * wxj
        ay = ci * wyi + cj * wyj
        az = ci * wzi + cj * wzj
        rvx = w[7 * _ROW + q] + (ay * nz - az * ny)
        rvy = w[8 * _ROW + q] + (az * nx - ax * nz)
        rvz = w[9 * _ROW + q] + (ax * ny - ay * nx)
        fn, ftx, fty, ftz, hx, hy, hz = hertz_mindlin(
            w[20 * _ROW + q], w[21 * _ROW + q], w[22 * _ROW + q], w[24 * _ROW + q],
            w[25 * _ROW + q], r_star, m_star, delta, nx, ny, nz, rvx, rvy, rvz,
            w[17 * _ROW + q], w[18 * _ROW + q], w[19 * _ROW + q], dt,
        )  # fmt: skip
        trx, try_, trz = rolling_torque(
            w[23 * _ROW + q], fn, r_star, wxi - wxj, wyi - wyj, wzi - wzj, dt * w[16 * _ROW + q]
        )
        tx = ny * ftz - nz * fty
        ty = nz * ftx - nx * ftz
        tz = nx * fty - ny * ftx
        hd = 0.5 * delta
        o = _NIN * _ROW
        w[o + q] = -fn * nx + ftx
        w[o + _ROW + q] = -fn * ny + fty
        w[o + 2 * _ROW + q] = -fn * nz + ftz
        cc = ri - hd
        w[o + 3 * _ROW + q] = cc * tx + trx
        w[o + 4 * _ROW + q] = cc * ty + try_
        w[o + 5 * _ROW + q] = cc * tz + trz
        cc = rj - hd
        w[o + 6 * _ROW + q] = cc * tx - trx
        w[o + 7 * _ROW + q] = cc * ty - try_
        w[o + 8 * _ROW + q] = cc * tz - trz
        w[o + 9 * _ROW + q] = hd
        w[o + 10 * _ROW + q] = hx
        w[o + 11 * _ROW + q] = hy
        w[o + 12 * _ROW + q] = hz


@njit(cache=True, inline="always")
def _store_springs(clist, q0, nq, hist, w):
    """Write the block's new springs back to ``hist``."""
    o = (_NIN + 10) * _ROW
    for q in range(nq):
        i = np.uint64(clist[0, q0 + q])
        k = np.uint64(clist[1, q0 + q])
        hist[i, k, 0] = w[o + q]
        hist[i, k, 1] = w[o + _ROW + q]
        hist[i, k, 2] = w[o + 2 * _ROW + q]


@njit(cache=True, inline="always")
def _chunk_contacts(lo, hi, P, nbf, pstart, hist, live, dom, per, clist, w):
    """The contacts of the chunk of owners ``lo .. hi-1`` (:func:`find_contacts`) from their offset
    ``pstart[lo]`` in ``clist``, the block buffer ``w`` made ready: returns (offset, count)."""
    off = pstart[lo]
    m = find_contacts(lo, hi, P, nbf, pstart, hist, live, dom, per, clist)
    _forget_pairs(w)
    return off, m


@njit(cache=True, inline="always")
def _evaluate_block(clist, q0, nq, P, IA, hist, pt, dom, per, w, dt):
    """Contacts ``clist[:, q0:q0+nq]``: inputs into ``w``, the law over the block, the new
    springs back to ``hist``; the forces and torques are left in ``w``."""
    _load_block(clist, q0, nq, P, IA, hist, pt, dom, per, w)
    contact_block(nq, w, dt)
    _store_springs(clist, q0, nq, hist, w)


@njit(cache=True, inline="always")
def _scatter_block(clist, q0, nq, w, a):
    """Add the block's forces and torques to both particles of each contact, in contact order
    (owner i: + force, + torque on i; partner j: - force, + torque on j)."""
    o = _NIN * _ROW
    for q in range(nq):
        i = np.uint64(clist[0, q0 + q])
        j = np.uint64(clist[2, q0 + q])
        f0, f1, f2 = w[o + q], w[o + _ROW + q], w[o + 2 * _ROW + q]
        a[i, 0] += f0
        a[i, 1] += f1
        a[i, 2] += f2
        a[i, 3] += w[o + 3 * _ROW + q]
        a[i, 4] += w[o + 4 * _ROW + q]
        a[i, 5] += w[o + 5 * _ROW + q]
        a[j, 0] -= f0
        a[j, 1] -= f1
        a[j, 2] -= f2
        a[j, 3] += w[o + 6 * _ROW + q]
        a[j, 4] += w[o + 7 * _ROW + q]
        a[j, 5] += w[o + 8 * _ROW + q]


@njit(cache=True, inline="always")
def _slot_block(clist, q0, nq, w, pf):
    """Write the block's results to the pair slots ``pf[i, k]`` (two-pass scheme)."""
    o = _NIN * _ROW
    for q in range(nq):
        i = np.uint64(clist[0, q0 + q])
        k = np.uint64(clist[1, q0 + q])
        for e in range(10):
            pf[i, k, e] = w[o + e * _ROW + q]


@njit(cache=True, parallel=True, fastmath=FMA)
def pair_pass(n, P, IA, nbf, pstart, nown, hist, live, clist, work, pf, bounds, pt, dom, per, dt):
    """Pass 1 (parallel scheme): evaluate each owned pair once; write ``pf[i, k]`` and update
    ``hist[i, k]``.

    The owners are split into the chunks of :func:`chunk_bounds` (one per ``work`` row), each
    on its own thread: its contacts are found (:func:`find_contacts`), then evaluated block by
    block by the same batched law as :func:`pair_scatter` (:func:`contact_block`), so the two
    schemes give the same bits. Velocities in ``P`` are at the half step (t + dt/2): they
    integrate the tangential spring (``xi += v_t dt``, midpoint rule) and drive the dashpots
    (as in LIGGGHTS).
    """
    chunk_bounds(n, nown, bounds)
    for c in prange(work.shape[0]):
        w = work[c]
        lo, hi = bounds[c], bounds[c + 1]
        for i in range(lo, hi):
            for k in range(nown[i]):
                pf[i, k, 9] = 0.0  # not in contact unless written below
        off, m = _chunk_contacts(lo, hi, P, nbf, pstart, hist, live, dom, per, clist, w)
        for q0 in range(off, off + m, BLOCK):
            nq = min(BLOCK, off + m - q0)
            _evaluate_block(clist, q0, nq, P, IA, hist, pt, dom, per, w, dt)
            _slot_block(clist, q0, nq, w, pf)


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
def pair_scatter(
    n, P, IA, nbf, pstart, nown, hist, live, clist, work, F, acc, bounds, pt, dom, per, dt
):
    """Scatter scheme: evaluate each owned pair once and add its force and torques straight to
    both particles' sums (Newton's third law), without the pair buffer of :func:`pair_pass`.

    The owners are split into ``K = work.shape[0]`` chunks (:func:`chunk_bounds`); chunk 0
    sums into ``F[:, :6]`` (free once the first half kick has used the last step's forces: one
    buffer fewer to keep in cache), chunk c > 0 into its own buffer ``acc[c - 1]`` (rows
    ``bounds[c]`` to n: an owner's partners have larger indices), so the chunks run on as many
    threads as there are, race-free, and the gather adds ``F[i] + acc[0, i] + ...`` in chunk
    order (:func:`chunk_sums`): the same sums for any thread count. Within a chunk the contacts
    are found in owner then slot order (:func:`find_contacts`), evaluated block by block
    (:func:`contact_block`, vectorised) and added in that order: particle j receives the
    contributions of its owners (ascending) before its own slots (ascending). With one chunk that is the order in which
    :func:`gather_pair_slots` sums the reverse then the owned slots: bit-identical to the
    two-pass scheme.

    The chunks are a ``prange``: numba compiles a parallel region with its array arguments
    marked as not aliasing each other, so the compiler can keep loads across the stores to
    the sums.
    """
    chunk_bounds(n, nown, bounds)
    for c in prange(work.shape[0]):
        a = F if c == 0 else acc[c - 1]
        w = work[c]
        lo, hi = bounds[c], bounds[c + 1]
        for i in range(lo, n):
            for e in range(6):
                a[i, e] = 0.0
        off, m = _chunk_contacts(lo, hi, P, nbf, pstart, hist, live, dom, per, clist, w)
        for q0 in range(off, off + m, BLOCK):
            nq = min(BLOCK, off + m - q0)
            _evaluate_block(clist, q0, nq, P, IA, hist, pt, dom, per, w, dt)
            _scatter_block(clist, q0, nq, w, a)


@njit(cache=True, inline="always")
def chunk_sums(i, F, acc, bounds):
    """Pair force and torque (6) on particle i from the chunk sums of :func:`pair_scatter`
    (chunk 0 in ``F``, chunk c > 0 in ``acc[c - 1]``), added in chunk order (chunks whose owners
    all come after i hold nothing for it)."""
    fx, fy, fz = F[i, 0], F[i, 1], F[i, 2]
    tx, ty, tz = F[i, 3], F[i, 4], F[i, 5]
    for c in range(1, bounds.shape[0] - 1):
        if bounds[c] > i:
            break
        fx += acc[c - 1, i, 0]
        fy += acc[c - 1, i, 1]
        fz += acc[c - 1, i, 2]
        tx += acc[c - 1, i, 3]
        ty += acc[c - 1, i, 4]
        tz += acc[c - 1, i, 5]
    return fx, fy, fz, tx, ty, tz


@njit(cache=True, inline="always")
def gather_pair_slots(i, pf, nrev, rev_o, rev_k, nown):
    """Pair force and torque (6) on particle i from the slots written by
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
        fx -= pf[o, s, 0]
        fy -= pf[o, s, 1]
        fz -= pf[o, s, 2]
        tx += pf[o, s, 6]
        ty += pf[o, s, 7]
        tz += pf[o, s, 8]
    for k in range(nown[i]):
        hd = pf[i, k, 9]
        if hd == 0.0:
            continue
        fx += pf[i, k, 0]
        fy += pf[i, k, 1]
        fz += pf[i, k, 2]
        tx += pf[i, k, 3]
        ty += pf[i, k, 4]
        tz += pf[i, k, 5]
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
