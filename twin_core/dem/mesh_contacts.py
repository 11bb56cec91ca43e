"""Contacts of the spheres with mesh triangles, batched (LIGGGHTS' ``fix wall/gran`` on a
``fix mesh/surface``; the geometry and motion of the triangles are in
:mod:`twin_core.dem.meshes`, the candidate triangles of each sphere in its list from
:mod:`twin_core.dem.partition`).

One pass per step (:func:`mesh_pass`), before the forces are summed, over the particles split
into chunks (one per ``mwork`` row, each on its own thread; every result is a function of its
own contact only, so the chunking changes no bit):

1. Geometry, over all candidate (sphere, triangle) pairs of the chunk in blocks of
   :data:`MBLOCK`: their coordinates copied into the rows of a block buffer, then one loop
   without branches that the compiler turns into SIMD code (:func:`closest_block`): the image of
   the sphere's centre nearest to the triangle along periodic axes and the closest point on the
   triangle (:func:`twin_core.dem.meshes.closest_point_triangle`). A candidate for which a
   second periodic image is within reach (a wall spanning the whole period, next to the seam)
   is redone by the full image search (:func:`twin_core.dem.meshes.nearest_image_contact`).
   The pairs in contact (distance below the radius, mesh active) are kept, in particle then
   slot order; the springs of the others are cleared.
2. Acceptance, per particle with contacts: faces first, then edges, then vertices; an edge or
   vertex contact is dropped when its contact point coincides with one already accepted or lies
   on a triangle with an accepted face contact (one contact per sphere on a flat or convex
   tessellated surface), and after the law its spring becomes a copy of the shadowing
   contact's (the history follows a sphere sliding from one triangle to the next).
3. Contact law of the accepted contacts in blocks (:func:`twin_core.dem.contact.wall_law`
   over the columns of a block, SIMD code) with the mesh velocity at the contact point; the
   springs written back, the force and torque kept per contact for the force pass, which adds
   each particle's contacts in acceptance order (:func:`add_mesh_sums`).

Work arrays (sized by the candidate slots, ``cap * ktri``; the candidates packed by
:func:`flatten_triangles` after each rebuild and before each run of steps, the rest each step):
``mcnt`` int64 (3, cap + 1): row 0 the first candidate of each particle, rows 1 and 2 its first
accepted position and the number accepted; ``mint`` int32 (8, cap * ktri): rows 0-1 the
candidates (particle, triangle), row 2 whether a candidate's spring may be non-zero, row 3 the
contacts and row 4 the accepted contacts (candidate indices), rows 5-6 the spring copies
(shadowed candidate, shadowing candidate), row 7 the contact code; ``mflt`` float64
(cap * ktri, 8), a row per candidate (one cache line for the force pass to read): the contact
point (3), the unit normal from the centre to it (3), the distance and the feature, then
(columns 0-5) the force and torque of an accepted contact;
``mwork`` (chunks, :data:`MBLOCK_WORDS`), one block buffer per chunk.

References: Ericson, Real-Time Collision Detection (2005), Sec. 5.1.5; Su, Gu & Xu (2011),
Chem. Eng. Sci. 66, 6069 (edge and vertex contacts shadowed by face contacts); Kloss et al.
(2012), Prog. Comput. Fluid Dyn. 12, 140 (LIGGGHTS mesh walls).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .contact import (
    clear_history,
    pair_coefficients,
    rotating_wall_velocity,
    spring_set,
    wall_law,
)
from .meshes import (
    axis_images,
    closest_point_triangle,
    dist_point_tri,
    mesh_state,
    nearest_image_contact,
)
from .space import FMA

__all__ = [
    "MBLOCK",
    "MBLOCK_WORDS",
    "MINT_ROWS",
    "MFLT_COLS",
    "add_mesh_sums",
    "closest_block",
    "flatten_triangles",
    "mesh_pass",
    "wall_block",
]

#: candidates or contacts per block (their rows stay in L1)
MBLOCK = 128
_ROW = MBLOCK + 8  # row stride of a block buffer (rows 1 KiB apart would share L1 sets)
_GIN = 14  # geometry inputs: centre (3), radius, triangle (9), mesh active
_GOUT = 9  # geometry results (the columns of ``mflt``, then the contact code)
_LIN = 28  # law inputs (see _load_law)
_LOUT = 9  # law results: force (3), torque (3), spring (3)
#: words of one chunk's block buffer (``mwork[c]``)
MBLOCK_WORDS = max(_GIN + _GOUT, _LIN + _LOUT) * _ROW
#: rows of ``mint`` and ``mflt``
MINT_ROWS = 8
MFLT_COLS = 8
_FAR = 2  # contact code of a candidate with a second periodic image within reach
#: reach of a sphere of radius r, ``r^2 (1 + 1e-9)``: a margin over the exact test on the
#: distance, the same in the SIMD geometry and in the full image search
_REACH_MARGIN = 1.0 + 1e-9


@njit(cache=True)
def flatten_triangles(n, ntri, tri_nb, thist, mcnt, mint):
    """The candidate lists packed: ``mcnt[0, i]`` the first candidate of particle i, and for
    candidate p (slot ``p - mcnt[0, i]``) its particle ``mint[0, p]``, triangle ``mint[1, p]``
    and ``mint[2, p] = 1`` where its spring is not zero (the springs to clear when the
    candidate is found apart). Redone after each list rebuild and before each run of steps."""
    p = 0
    for i in range(n):
        mcnt[0, i] = p
        for k in range(ntri[i]):
            mint[0, p] = i
            mint[1, p] = tri_nb[i, k]
            mint[2, p] = spring_set(thist, i, k)
            p += 1
    mcnt[0, n] = p


@njit(cache=True, inline="always")
def _load_candidates(p0, nq, P, tri_x, tri_mesh, motion, mint, w):
    """Copy the sphere centres and radii, the triangles and whether their mesh is active, of
    candidates ``p0 .. p0+nq-1``, into the rows of the block buffer ``w``."""
    for q in range(nq):
        i = np.uint64(mint[0, p0 + q])
        tq = np.uint64(mint[1, p0 + q])
        w[q] = P[i, 0]
        w[_ROW + q] = P[i, 1]
        w[2 * _ROW + q] = P[i, 2]
        w[3 * _ROW + q] = P[i, 9]
        w[4 * _ROW + q] = tri_x[tq, 0]
        w[5 * _ROW + q] = tri_x[tq, 1]
        w[6 * _ROW + q] = tri_x[tq, 2]
        w[7 * _ROW + q] = tri_x[tq, 3]
        w[8 * _ROW + q] = tri_x[tq, 4]
        w[9 * _ROW + q] = tri_x[tq, 5]
        w[10 * _ROW + q] = tri_x[tq, 6]
        w[11 * _ROW + q] = tri_x[tq, 7]
        w[12 * _ROW + q] = tri_x[tq, 8]
        w[13 * _ROW + q] = motion[np.uint64(tri_mesh[tq]), 0]


@njit(cache=True, fastmath=FMA, error_model="numpy")
def closest_block(nq, w, dom, per):
    """Geometry of the ``nq`` candidates of a block buffer (rows of :func:`_load_candidates`),
    written to its result rows: the image q of the centre nearest to the triangle along
    periodic axes (:func:`twin_core.dem.meshes.axis_images`), the closest point c on the
    triangle (:func:`twin_core.dem.meshes.closest_point_triangle`; 3), the unit vector from q
    to c (3), ``|c - q|``, the feature, and the contact code (:func:`_store_geometry` puts it in
    ``mint[7]``): 1 in contact (distance below the radius and not zero, mesh active), 0 not,
    :data:`_FAR` where a second image lies within reach of the triangle's box (then the full
    image search decides). One loop without branches: compiled to SIMD code, the same bits in
    any column."""
    o = _GIN * _ROW
    for q in range(nq):
        px, py, pz, r = w[q], w[_ROW + q], w[2 * _ROW + q], w[3 * _ROW + q]
        ax, ay, az = w[4 * _ROW + q], w[5 * _ROW + q], w[6 * _ROW + q]
        bx, by, bz = w[7 * _ROW + q], w[8 * _ROW + q], w[9 * _ROW + q]
        cx, cy, cz = w[10 * _ROW + q], w[11 * _ROW + q], w[12 * _ROW + q]
        sx, _, _, gx1 = axis_images(px, ax, bx, cx, dom[6], per[0] != 0)
        sy, _, _, gy1 = axis_images(py, ay, by, cy, dom[7], per[1] != 0)
        sz, _, _, gz1 = axis_images(pz, az, bz, cz, dom[8], per[2] != 0)
        reach2 = r * r * _REACH_MARGIN
        far = (gx1 * gx1 < reach2) | (gy1 * gy1 < reach2) | (gz1 * gz1 < reach2)
        qx, qy, qz = px + sx, py + sy, pz + sz
        kx, ky, kz, feat = closest_point_triangle(qx, qy, qz, ax, ay, az, bx, by, bz, cx, cy, cz)
        dx, dy, dz = kx - qx, ky - qy, kz - qz
        dist = math.sqrt(dx * dx + dy * dy + dz * dz)
        inv = 1.0 / dist if dist > 0.0 else 0.0
        touch = (w[13 * _ROW + q] != 0.0) & (dist < r) & (dist > 0.0)
        w[o + q] = kx
        w[o + _ROW + q] = ky
        w[o + 2 * _ROW + q] = kz
        w[o + 3 * _ROW + q] = dx * inv
        w[o + 4 * _ROW + q] = dy * inv
        w[o + 5 * _ROW + q] = dz * inv
        w[o + 6 * _ROW + q] = dist
        w[o + 7 * _ROW + q] = feat
        w[o + 8 * _ROW + q] = 2.0 if far else (1.0 if touch else 0.0)


@njit(cache=True, inline="always")
def _store_geometry(p0, nq, w, mint, mflt):
    """The block's geometry results to the candidates' rows ``mflt[p0:p0+nq]`` and their
    contact codes to ``mint[7, p0:p0+nq]``."""
    o = _GIN * _ROW
    for q in range(nq):
        p = p0 + q
        for c in range(8):
            mflt[p, c] = w[o + c * _ROW + q]
        mint[7, p] = np.int32(w[o + 8 * _ROW + q])


@njit(cache=True, inline="always")
def _far_contact(p, P, tri_x, tri_mesh, motion, dom, per, mint, mflt):
    """Redo the geometry of candidate p (a second periodic image within reach) by the full image
    search (:func:`twin_core.dem.meshes.nearest_image_contact`); returns whether it is a
    contact."""
    i = np.uint64(mint[0, p])
    tq = np.uint64(mint[1, p])
    r = P[i, 9]
    qx, qy, qz, kx, ky, kz, f, d2 = nearest_image_contact(
        P[i, 0], P[i, 1], P[i, 2], tri_x, tq, dom, per, r * r * _REACH_MARGIN
    )
    dist = math.sqrt((kx - qx) ** 2 + (ky - qy) ** 2 + (kz - qz) ** 2)
    touch = d2 < math.inf and dist < r and dist > 0.0 and motion[tri_mesh[tq], 0] != 0.0
    if touch:
        mflt[p, 0] = kx
        mflt[p, 1] = ky
        mflt[p, 2] = kz
        mflt[p, 3] = (kx - qx) / dist
        mflt[p, 4] = (ky - qy) / dist
        mflt[p, 5] = (kz - qz) / dist
        mflt[p, 6] = dist
        mflt[p, 7] = f
    return touch


@njit(cache=True, inline="always")
def _keep_contacts(p0, nq, m, P, thist, tri_x, tri_mesh, motion, dom, per, mint, mflt, mcnt):
    """The candidates ``p0 .. p0+nq-1`` in contact appended to the contact list ``mint[3]``
    from entry m (their candidate indices); the springs of the others cleared (where live,
    ``mint[2]``). Returns the next free entry. Branch-free on the contact test (taken about
    one time in three, unpredictably): each candidate is written to the next free entry, which
    is kept when it is a contact."""
    for q in range(nq):
        p = p0 + q
        code = mint[7, p]
        touch = code == 1
        if code == _FAR:
            touch = _far_contact(p, P, tri_x, tri_mesh, motion, dom, per, mint, mflt)
        mint[3, m] = p
        m += np.int64(touch)
        stale = mint[2, p] > np.int32(touch)
        mint[2, p] = touch
        if stale:
            i = np.uint64(mint[0, p])
            clear_history(thist, i, np.uint64(p - mcnt[0, i]))
    return m


@njit(cache=True, inline="always")
def _shadowing_contact(p, g0, g1, tol, tri_x, mint, mflt):
    """The accepted contact (``mflt[7]`` = 10 + feature) among the particle's contacts
    ``mint[3, g0:g1]`` that shadows edge/vertex contact (candidate) p: the same contact point
    within ``tol``, or p's contact point on a triangle with an accepted face contact. Returns
    its candidate index, or -1."""
    kx, ky, kz = mflt[p, 0], mflt[p, 1], mflt[p, 2]
    for g in range(g0, g1):
        p2 = mint[3, g]
        f2 = mflt[p2, 7]
        if f2 < 10.0:  # not (yet) accepted
            continue
        dx = kx - mflt[p2, 0]
        dy = ky - mflt[p2, 1]
        dz = kz - mflt[p2, 2]
        if dx * dx + dy * dy + dz * dz < tol * tol:
            return p2
        if f2 == 10.0 and dist_point_tri(kx, ky, kz, tri_x, np.uint64(mint[1, p2])) < tol:
            return p2
    return -1


@njit(cache=True, inline="always")
def _accept_contacts(off, m, P, tri_x, mint, mflt, mcnt):
    """Acceptance of the contacts ``mint[3, off:off+m]`` (module docstring, step 2): the
    accepted contacts' candidate indices from ``mint[4, off]`` on, each particle's first
    position and count in ``mcnt[1, i]``, ``mcnt[2, i]``, and the spring copies (shadowed
    candidate, shadowing candidate) from ``mint[5:7, off]`` on. Returns (accepted, copies)."""
    a = off
    s = off
    e = off
    end = off + m
    while e < end:
        owner = mint[0, mint[3, e]]
        i = np.uint64(owner)
        g0 = e
        while e < end and mint[0, mint[3, e]] == owner:
            e += 1
        mcnt[1, i] = a
        if e - g0 == 1:
            mint[4, a] = mint[3, g0]
            a += 1
        else:
            tol = 1e-7 * P[i, 9]
            for feat_pass in range(3):  # faces, then edges, then vertices
                for g in range(g0, e):
                    p = mint[3, g]
                    if mflt[p, 7] != feat_pass:
                        continue
                    shadow = -1
                    if feat_pass > 0:
                        shadow = _shadowing_contact(p, g0, e, tol, tri_x, mint, mflt)
                    if shadow >= 0:
                        mflt[p, 7] = -1.0
                        mint[5, s] = p
                        mint[6, s] = shadow
                        s += 1
                        continue
                    mflt[p, 7] = 10.0 + feat_pass
                    mint[4, a] = p
                    a += 1
        mcnt[2, i] = a - mcnt[1, i]
    return a - off, s - off


@njit(cache=True)
def _mesh_motion(mesh_par, t):
    """Per mesh at time t: (active, angular speed, translation velocity (3)) of
    :func:`twin_core.dem.meshes.mesh_state`, once per step instead of per contact."""
    nm = mesh_par.shape[0]
    motion = np.empty((nm, 5))
    for m in range(nm):
        active, _, _, om, _, _, _, vx, vy, vz = mesh_state(mesh_par, m, t)
        motion[m, 0] = 1.0 if active else 0.0
        motion[m, 1] = om if int(mesh_par[m, 0]) == 1 else 0.0
        motion[m, 2] = vx
        motion[m, 3] = vy
        motion[m, 4] = vz
    return motion


@njit(cache=True, inline="always")
def _load_law(a0, nq, P, IA, thist, tri_mesh, mesh_par, motion, pt, mint, mflt, mcnt, w):
    """Copy the inputs of the accepted contacts at positions ``a0 .. a0+nq-1`` into the rows of
    the block buffer ``w``: velocity (3), angular velocity (3), radius, mass, inverse inertia,
    unit normal (3), overlap, mesh velocity at the contact point (3) and angular velocity (3;
    ``omega u x (c - a)`` and ``omega u`` for a rotating mesh, the translation velocity
    otherwise), the coefficients of the particle-mesh material pair (6), the spring (3)."""
    for q in range(nq):
        e = np.uint64(mint[4, a0 + q])
        i = np.uint64(mint[0, e])
        k = np.uint64(e - mcnt[0, i])
        mesh = np.uint64(tri_mesh[np.uint64(mint[1, e])])
        for c in range(6):
            w[c * _ROW + q] = P[i, 3 + c]  # velocity, angular velocity
        w[6 * _ROW + q] = P[i, 9]
        w[7 * _ROW + q] = P[i, 10]
        w[8 * _ROW + q] = P[i, 12]
        w[9 * _ROW + q] = mflt[e, 3]
        w[10 * _ROW + q] = mflt[e, 4]
        w[11 * _ROW + q] = mflt[e, 5]
        w[12 * _ROW + q] = P[i, 9] - mflt[e, 6]
        om = motion[mesh, 1]
        vwx, vwy, vwz = motion[mesh, 2], motion[mesh, 3], motion[mesh, 4]
        wwx = wwy = wwz = 0.0
        if om != 0.0:
            ux, uy, uz = mesh_par[mesh, 4], mesh_par[mesh, 5], mesh_par[mesh, 6]
            vwx, vwy, vwz = rotating_wall_velocity(
                om, ux, uy, uz, mflt[e, 0] - mesh_par[mesh, 1], mflt[e, 1] - mesh_par[mesh, 2],
                mflt[e, 2] - mesh_par[mesh, 3],
            )  # fmt: skip
            wwx, wwy, wwz = om * ux, om * uy, om * uz
        w[13 * _ROW + q] = vwx
        w[14 * _ROW + q] = vwy
        w[15 * _ROW + q] = vwz
        w[16 * _ROW + q] = wwx
        w[17 * _ROW + q] = wwy
        w[18 * _ROW + q] = wwz
        e_star, g_star, mu, mur, dmp, tn_ratio = pair_coefficients(
            pt, IA[i, 1], int(mesh_par[mesh, 15])
        )
        w[19 * _ROW + q] = e_star
        w[20 * _ROW + q] = g_star
        w[21 * _ROW + q] = mu
        w[22 * _ROW + q] = mur
        w[23 * _ROW + q] = dmp
        w[24 * _ROW + q] = tn_ratio
        w[25 * _ROW + q] = thist[i, k, 0]
        w[26 * _ROW + q] = thist[i, k, 1]
        w[27 * _ROW + q] = thist[i, k, 2]


@njit(cache=True, fastmath=FMA, error_model="numpy")
def wall_block(nq, w, dt):
    """The wall contact law (:func:`twin_core.dem.contact.wall_law`) of the ``nq`` contacts of a
    block buffer (rows of :func:`_load_law`): force (3), torque (3) and new spring (3) per
    contact. One loop without branches: compiled to SIMD code, the same bits in any column."""
    o = _LIN * _ROW
    for q in range(nq):
        fx, fy, fz, tx, ty, tz, hx, hy, hz = wall_law(
            w[q], w[_ROW + q], w[2 * _ROW + q], w[3 * _ROW + q], w[4 * _ROW + q],
            w[5 * _ROW + q], w[6 * _ROW + q], w[7 * _ROW + q], w[8 * _ROW + q],
            w[9 * _ROW + q], w[10 * _ROW + q], w[11 * _ROW + q], w[12 * _ROW + q],
            w[13 * _ROW + q], w[14 * _ROW + q], w[15 * _ROW + q], w[16 * _ROW + q],
            w[17 * _ROW + q], w[18 * _ROW + q], w[19 * _ROW + q], w[20 * _ROW + q],
            w[21 * _ROW + q], w[22 * _ROW + q], w[23 * _ROW + q], w[24 * _ROW + q],
            w[25 * _ROW + q], w[26 * _ROW + q], w[27 * _ROW + q], dt,
        )  # fmt: skip
        w[o + q] = fx
        w[o + _ROW + q] = fy
        w[o + 2 * _ROW + q] = fz
        w[o + 3 * _ROW + q] = tx
        w[o + 4 * _ROW + q] = ty
        w[o + 5 * _ROW + q] = tz
        w[o + 6 * _ROW + q] = hx
        w[o + 7 * _ROW + q] = hy
        w[o + 8 * _ROW + q] = hz


@njit(cache=True, inline="always")
def _store_law(a0, nq, thist, mint, mflt, mcnt, w):
    """The block's new springs back to ``thist``, its forces and torques to columns 0-5 of
    each contact's row of ``mflt`` (its geometry is no longer needed)."""
    o = _LIN * _ROW
    for q in range(nq):
        e = np.uint64(mint[4, a0 + q])
        i = np.uint64(mint[0, e])
        k = np.uint64(e - mcnt[0, i])
        for c in range(6):
            mflt[e, c] = w[o + c * _ROW + q]
        thist[i, k, 0] = w[o + 6 * _ROW + q]
        thist[i, k, 1] = w[o + 7 * _ROW + q]
        thist[i, k, 2] = w[o + 8 * _ROW + q]


@njit(cache=True, parallel=True, fastmath=FMA)
def mesh_pass(n, P, IA, thist, tri_x, tri_mesh, mesh_par, pt, dom, per, dt, t, mint, mflt,
              mcnt, mwork):  # fmt: skip
    """The mesh contacts of all particles at time t (module docstring): the forces and torques
    of the accepted contacts left in ``mflt`` for :func:`add_mesh_sums`, the springs
    ``thist`` updated. The particles are split into ``mwork.shape[0]`` chunks of equal count,
    each on its own thread, each writing the entries of its own candidates only."""
    motion = _mesh_motion(mesh_par, t)
    nchunk = mwork.shape[0]
    for c in prange(nchunk):
        w = mwork[c]
        lo = n * c // nchunk
        hi = n * (c + 1) // nchunk
        for i in range(lo, hi):
            mcnt[2, i] = 0
        off = mcnt[0, lo]
        end = mcnt[0, hi]
        m = off
        for p0 in range(off, end, MBLOCK):
            nq = min(MBLOCK, end - p0)
            _load_candidates(p0, nq, P, tri_x, tri_mesh, motion, mint, w)
            closest_block(nq, w, dom, per)
            _store_geometry(p0, nq, w, mint, mflt)
            m = _keep_contacts(
                p0, nq, m, P, thist, tri_x, tri_mesh, motion, dom, per, mint, mflt, mcnt
            )
        na, ns = _accept_contacts(off, m - off, P, tri_x, mint, mflt, mcnt)
        for a0 in range(off, off + na, MBLOCK):
            nq = min(MBLOCK, off + na - a0)
            _load_law(a0, nq, P, IA, thist, tri_mesh, mesh_par, motion, pt, mint, mflt, mcnt, w)
            wall_block(nq, w, dt)
            _store_law(a0, nq, thist, mint, mflt, mcnt, w)
        for s in range(off, off + ns):
            e = np.uint64(mint[5, s])
            i = np.uint64(mint[0, e])
            k = np.uint64(e - mcnt[0, i])
            src = np.uint64(mint[6, s] - mcnt[0, i])
            thist[i, k, 0] = thist[i, src, 0]
            thist[i, k, 1] = thist[i, src, 1]
            thist[i, k, 2] = thist[i, src, 2]


@njit(cache=True, inline="always")
def add_mesh_sums(i, mint, mflt, mcnt, fx, fy, fz, tx, ty, tz):
    """Add to particle i's force and torque (fx .. tz) its accepted mesh contacts of
    :func:`mesh_pass`, in acceptance order (faces, edges, vertices). Returns the new sums."""
    a0 = mcnt[1, i]
    for a in range(a0, a0 + mcnt[2, i]):
        e = np.uint64(mint[4, a])
        fx += mflt[e, 0]
        fy += mflt[e, 1]
        fz += mflt[e, 2]
        tx += mflt[e, 3]
        ty += mflt[e, 4]
        tz += mflt[e, 5]
    return fx, fy, fz, tx, ty, tz
