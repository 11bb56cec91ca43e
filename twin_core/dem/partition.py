"""Partition of space for the DEM engine (jax-md's ``partition``; LIGGGHTS' ``neighbor``): the
cell grid, the half neighbour list of particle pairs, its reverse list, the candidate triangles
of each particle, and the Verlet skin criterion that decides when they are rebuilt.

- Cell grid: cubic-ish cells of size >= ``2 r_max + skin`` (so every pair within the cut-off
  ``r_i + r_j + skin`` lies in neighbouring cells), minimum image on periodic axes.
- Rebuild: particles flagged for removal are dropped, the others counting-sorted by cell (their
  rows permuted, for memory locality); the half list (pair (i, j), i < j, owned by i in
  ``nb[i, k]``) and the triangle lists are built against the old ones through the permutation,
  so each tangential history is carried over (its sign flipped when the owner of a pair changes).
  Lists are double-buffered (``cur`` selects the live one); a list that overflows its width makes
  the rebuild return a status with the width needed, with nothing modified.
- Skin criterion (after the drift): rebuild when a particle has moved more than skin/2 since the
  last build, or a moving mesh plus a particle more than the skin, or a particle is to be
  removed.

References: Allen & Tildesley, Computer Simulation of Liquids (2nd ed. 2017), Sec. 5.3 (Verlet
lists, skin) and 5.3.2 (cell lists); Plimpton (1995), J. Comput. Phys. 117, 1 (half lists,
Newton's third law); LIGGGHTS ``neighbor``/``fix contacthistory`` (history carried across
rebuilds).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .meshes import max_tri_disp2, nearest_image_contact
from .space import min_image

__all__ = ["axis_span", "cell_of", "rebuild", "rebuild_due", "reverse_lists", "wrap_cell"]


@njit(cache=True, inline="always")
def axis_span(c, ncell, periodic):
    """Neighbouring cells of cell c along one axis (deduplicated), as (first, count): the cells
    are ``first``, ``first + 1``, ... (count of them; c-1, c, c+1 in that order), each wrapped
    once by :func:`wrap_cell` on a periodic axis, clipped to the grid on a closed axis, and all
    cells once on a periodic axis of fewer than 3 cells. Scalars only: it is called per particle
    in parallel loops, where a small array would be an allocation."""
    if periodic:
        if ncell < 3:
            return 0, ncell
        return (c - 1 if c > 0 else ncell - 1), 3
    first = c - 1 if c > 0 else 0
    last = c + 1 if c + 1 < ncell else ncell - 1
    return first, last - first + 1


@njit(cache=True, inline="always")
def wrap_cell(c, ncell):
    """Cell index ``c < 2 ncell`` wrapped into the grid (a compare, not an integer division)."""
    return c - ncell if c >= ncell else c


@njit(cache=True)
def cell_of(x, lo, cs, ncell, periodic):
    """Cell index ``floor((x - lo) / cs)`` along one axis (wrapped on a periodic axis, clamped
    to the grid otherwise)."""
    c = int(math.floor((x - lo) / cs))
    if periodic:
        c %= ncell
    else:
        if c < 0:
            c = 0
        elif c >= ncell:
            c = ncell - 1
    return c


@njit(cache=True, inline="always")
def _cell_grid(dom, rmax, skin):
    """Cells per axis (at least one, of size >= ``2 r_max + skin``) and their sizes (3,)."""
    cs_min = 2.0 * rmax + skin
    ncx = max(1, int(dom[6] / cs_min))
    ncy = max(1, int(dom[7] / cs_min))
    ncz = max(1, int(dom[8] / cs_min))
    cs = np.array([dom[6] / ncx, dom[7] / ncy, dom[8] / ncz])
    return ncx, ncy, ncz, cs


@njit(cache=True, inline="always")
def _sort_by_cell(n, P, rm, dom, per, cs, ncx, ncy, ncz):
    """Counting sort of the particles by cell, flagged ones (``rm != 0``) last and dropped.

    Returns (perm, cell_new, cstart, n_new): new row i is old row ``perm[i]``, in cell
    ``cell_new[i]``; the rows of cell c are ``cstart[c]:cstart[c + 1]``."""
    ncell = ncx * ncy * ncz
    cell_old = np.empty(n, np.int64)
    counts = np.zeros(ncell + 2, np.int64)
    for i in range(n):
        if rm[i] != 0:
            cell_old[i] = ncell
        else:
            cx = cell_of(P[i, 0], dom[0], cs[0], ncx, per[0] != 0)
            cy = cell_of(P[i, 1], dom[1], cs[1], ncy, per[1] != 0)
            cz = cell_of(P[i, 2], dom[2], cs[2], ncz, per[2] != 0)
            cell_old[i] = (cx * ncy + cy) * ncz + cz
        counts[cell_old[i] + 1] += 1
    for c in range(ncell + 1):
        counts[c + 1] += counts[c]
    cstart = counts[: ncell + 1].copy()
    fill = counts.copy()
    perm = np.empty(n, np.int64)
    for i in range(n):
        c = cell_old[i]
        perm[fill[c]] = i
        fill[c] += 1
    n_new = cstart[ncell]
    cell_new = np.empty(n_new, np.int64)
    for i in range(n_new):
        cell_new[i] = cell_old[perm[i]]
    return perm, cell_new, cstart, n_new


@njit(cache=True, inline="always")
def _carry_history(hist_new, i, cnt, nb_old, n_old, hist_old, row, key, sign):
    """Tangential spring of the new list's slot (i, cnt): the old list's slot (row, key) times
    ``sign`` (zero when that pair was not listed)."""
    h0 = 0.0
    h1 = 0.0
    h2 = 0.0
    row = np.uint64(row)
    for kk in range(n_old[row]):
        if nb_old[row, kk] == key:
            h0 = sign * hist_old[row, kk, 0]
            h1 = sign * hist_old[row, kk, 1]
            h2 = sign * hist_old[row, kk, 2]
            break
    hist_new[i, cnt, 0] = h0
    hist_new[i, cnt, 1] = h1
    hist_new[i, cnt, 2] = h2


@njit(cache=True, parallel=True)
def _build_own(
    n_new, perm, P, cell_of_new, cstart, ncx, ncy, ncz, dom, per, skin,
    nb_old, nown_old, hist_old, nb_new, nown_new, hist_new, kmax,
):  # fmt: skip
    """Half neighbour list in the new (sorted) order with history carried over; returns the
    width needed when ``kmax`` is too small (0 otherwise)."""
    l0, l1, l2 = dom[6], dom[7], dom[8]
    p0, p1, p2 = per[0] != 0, per[1] != 0, per[2] != 0
    over = 0
    for i in prange(n_new):
        oi = perm[i]
        oiu = np.uint64(oi)  # unsigned indices: no wraparound code (space, "Indexing")
        xi, yi, zi, ri = P[oiu, 0], P[oiu, 1], P[oiu, 2], P[oiu, 9]
        c = cell_of_new[i]
        fx, mx = axis_span(c // (ncz * ncy), ncx, p0)
        fy, my = axis_span((c // ncz) % ncy, ncy, p1)
        fz, mz = axis_span(c % ncz, ncz, p2)
        cnt = 0
        for a in range(mx):
            ca = wrap_cell(fx + a, ncx)
            for b in range(my):
                base = (ca * ncy + wrap_cell(fy + b, ncy)) * ncz
                # the cells along z that do not wrap are consecutive rows: one range
                nz_run = mz if fz + mz <= ncz else 1
                for e in range(mz - nz_run + 1):
                    c0 = base + wrap_cell(fz + e, ncz)
                    # rows are sorted by cell: partners j > i only; each candidate is
                    # written to the next free slot, kept when within the cut-off (no branch
                    # on the distance: it is taken about one time in six, unpredictably)
                    for j in range(max(cstart[c0], i + 1), cstart[c0 + nz_run]):
                        oj = np.uint64(perm[j])
                        dx = min_image(P[oj, 0] - xi, l0, p0)
                        dy = min_image(P[oj, 1] - yi, l1, p1)
                        dz = min_image(P[oj, 2] - zi, l2, p2)
                        cut = ri + P[oj, 9] + skin
                        nb_new[i, np.uint64(min(cnt, kmax - 1))] = j
                        cnt += dx * dx + dy * dy + dz * dz < cut * cut
        for k in range(min(cnt, kmax)):
            j = nb_new[i, k]
            oj = perm[j]
            # where the owner changed, the spring changes sign
            row, key, sign = (oi, oj, 1.0) if oi < oj else (oj, oi, -1.0)
            _carry_history(hist_new, i, k, nb_old, nown_old, hist_old, row, key, sign)
        nown_new[i] = min(cnt, kmax)
        if cnt > kmax:
            over = max(over, cnt)
    return over


@njit(cache=True, inline="always")
def _build_reverse(n_new, nb, nown, rev_o, rev_k, nrev):
    """Reverse list: for each particle j, the owners i (ascending) and slots k of the pairs
    ``nb[i, k] == j`` (serial, deterministic order). Returns the width needed."""
    krev = rev_o.shape[1]
    for i in range(n_new):
        nrev[i] = 0
    rover = 0
    for i in range(n_new):
        for k in range(nown[i]):
            j = nb[i, k]
            c = nrev[j]
            if c < krev:
                rev_o[j, c] = i
                rev_k[j, c] = k
            nrev[j] = c + 1
            if c + 1 > rover:
                rover = c + 1
    return rover


@njit(cache=True)
def reverse_lists(n, nb, nown, rev_o, rev_k, nrev):
    """The reverse lists of the half lists ``nb``, ``nown`` (:func:`rebuild` without them);
    returns the width needed (more than ``rev_o.shape[1]``: enlarge and call again)."""
    return _build_reverse(n, nb, nown, rev_o, rev_k, nrev)


@njit(cache=True, parallel=True)
def _build_tri(
    n_new, perm, P, cell_of_new, tstart, tcell, tri_x, dom, per, skin,
    tri_nb_old, ntri_old, thist_old, tri_nb_new, ntri_new, thist_new, kmax,
):  # fmt: skip
    """Candidate triangles of each particle (distance < r + skin), history carried over; returns
    the width needed when ``kmax`` is too small (0 otherwise)."""
    over = 0
    for i in prange(n_new):
        oi = perm[i]
        oiu = np.uint64(oi)
        x, y, z, r = P[oiu, 0], P[oiu, 1], P[oiu, 2], P[oiu, 9]
        c = cell_of_new[i]
        cnt = 0
        for s in range(tstart[c], tstart[c + 1]):
            q = tcell[s]
            reach2 = (r + skin) ** 2
            _, _, _, _, _, _, _, d2 = nearest_image_contact(
                x, y, z, tri_x, np.uint64(q), dom, per, reach2
            )
            if d2 < reach2:
                if cnt < kmax:
                    tri_nb_new[i, cnt] = q
                    _carry_history(thist_new, i, cnt, tri_nb_old, ntri_old, thist_old, oi, q, 1.0)
                cnt += 1
        ntri_new[i] = min(cnt, kmax)
        if cnt > kmax:
            over = max(over, cnt)
    return over


@njit(cache=True)
def _tri_cell_range(tri_x, q, dom, per, cs, nc, reach, out):
    """Cell index range (inclusive, unwrapped) of triangle q's box grown by ``reach``."""
    for a in range(3):
        vmin = min(tri_x[q, a], tri_x[q, 3 + a], tri_x[q, 6 + a]) - reach
        vmax = max(tri_x[q, a], tri_x[q, 3 + a], tri_x[q, 6 + a]) + reach
        c0 = int(math.floor((vmin - dom[a]) / cs[a]))
        c1 = int(math.floor((vmax - dom[a]) / cs[a]))
        if per[a] != 0:
            if c1 - c0 + 1 >= nc[a]:
                c0 = 0
                c1 = nc[a] - 1
        else:
            c0 = max(c0, 0)
            c1 = min(c1, nc[a] - 1)
        out[a, 0] = c0
        out[a, 1] = c1


@njit(cache=True, inline="always")
def _wrap(c, ncell):
    """Cell index c of a box's range wrapped into the grid: without an integer division in the
    usual case (``-ncell <= c < 2 ncell``; the binning runs over ~40,000 cells of the seed
    blender's triangles per rebuild)."""
    if 0 <= c < ncell:
        return c
    if -ncell <= c < 0:
        return c + ncell
    if ncell <= c < 2 * ncell:
        return c - ncell
    return c % ncell


@njit(cache=True)
def _bin_triangles(tri_x, dom, per, cs, ncx, ncy, ncz, reach):
    """CSR map cell -> triangles whose bounding box grown by ``reach`` touches the cell:
    the triangles of cell c are ``tcell[start[c]:start[c + 1]]``. Returns (start, tcell)."""
    nt = tri_x.shape[0]
    ncell = ncx * ncy * ncz
    nc = np.array([ncx, ncy, ncz])
    rng = np.zeros((3, 2), np.int64)
    counts = np.zeros(ncell + 1, np.int64)
    for q in range(nt):
        _tri_cell_range(tri_x, q, dom, per, cs, nc, reach, rng)
        for a in range(rng[0, 0], rng[0, 1] + 1):
            for b in range(rng[1, 0], rng[1, 1] + 1):
                for e in range(rng[2, 0], rng[2, 1] + 1):
                    cell = (_wrap(a, ncx) * ncy + _wrap(b, ncy)) * ncz + _wrap(e, ncz)
                    counts[cell + 1] += 1
    for c in range(ncell):
        counts[c + 1] += counts[c]
    fill = counts.copy()
    tcell = np.empty(counts[ncell], np.int64)
    for q in range(nt):
        _tri_cell_range(tri_x, q, dom, per, cs, nc, reach, rng)
        for a in range(rng[0, 0], rng[0, 1] + 1):
            for b in range(rng[1, 0], rng[1, 1] + 1):
                for e in range(rng[2, 0], rng[2, 1] + 1):
                    cell = (_wrap(a, ncx) * ncy + _wrap(b, ncy)) * ncz + _wrap(e, ncz)
                    tcell[fill[cell]] = q
                    fill[cell] += 1
    return counts, tcell


@njit(cache=True, inline="always")
def _commit(n, n_new, perm, P, F, IA, XB, rm, whist, removed, tri_x, tri_xb):
    """Count the removed particles (number and mass per removal code), permute the particle
    rows into the new order, clear the removal flags and record the positions (particles and
    triangles) of this build for the skin criterion."""
    for i in range(n):
        if rm[i] != 0:
            code = rm[i] - 1
            removed[code, 0] += 1.0
            removed[code, 1] += P[i, 10]
    tmp = P[:n].copy()
    for i in range(n_new):
        P[i] = tmp[perm[i]]
    tmpf = F[:n].copy()
    for i in range(n_new):
        F[i] = tmpf[perm[i]]
    tmpi = IA[:n].copy()
    for i in range(n_new):
        IA[i] = tmpi[perm[i]]
    if whist.shape[1] > 0:
        tmpw = whist[:n].copy()
        for i in range(n_new):
            whist[i] = tmpw[perm[i]]
    for i in range(n):
        rm[i] = 0
    for i in range(n_new):
        XB[i, 0] = P[i, 0]
        XB[i, 1] = P[i, 1]
        XB[i, 2] = P[i, 2]
    tri_xb[:] = tri_x


@njit(cache=True)
def rebuild(
    n, P, F, IA, XB, rm, whist,
    nb_b, hist_b, nown_b, rev_o, rev_k, nrev, cur,
    tri_nb_b, thist_b, ntri_b, tri_x, tri_xb,
    dom, per, skin, rmax, removed, with_reverse,
):  # fmt: skip
    """Remove flagged particles, sort the rest by cell, rebuild the neighbour and triangle lists
    (carrying the contact histories) and commit. Returns (status, n_new, needed):
    status 0 ok, 1 pair list too short (``needed`` slots), 2 reverse list too short,
    3 triangle list too short. On status != 0 nothing is modified. The reverse lists are
    built only ``with_reverse`` (the two-pass scheme needs them, the scatter does not:
    :func:`reverse_lists` builds them later from the same lists)."""
    ncx, ncy, ncz, cs = _cell_grid(dom, rmax, skin)
    perm, cell_new, cstart, n_new = _sort_by_cell(n, P, rm, dom, per, cs, ncx, ncy, ncz)
    old = cur[0]
    new = 1 - old
    over = _build_own(
        n_new, perm, P, cell_new, cstart, ncx, ncy, ncz, dom, per, skin,
        nb_b[old], nown_b[old], hist_b[old], nb_b[new], nown_b[new], hist_b[new], nb_b.shape[2],
    )  # fmt: skip
    if over > 0:
        return 1, n, over
    if with_reverse:
        rover = _build_reverse(n_new, nb_b[new], nown_b[new], rev_o, rev_k, nrev)
        if rover > rev_o.shape[1]:
            return 2, n, rover
    if tri_x.shape[0] > 0:
        start, tcell = _bin_triangles(tri_x, dom, per, cs, ncx, ncy, ncz, rmax + skin)
        tover = _build_tri(
            n_new, perm, P, cell_new, start, tcell, tri_x, dom, per, skin,
            tri_nb_b[old], ntri_b[old], thist_b[old], tri_nb_b[new], ntri_b[new], thist_b[new],
            tri_nb_b.shape[2],
        )  # fmt: skip
        if tover > 0:
            return 3, n, tover
    else:
        ntri_b[new, :n_new] = 0
    _commit(n, n_new, perm, P, F, IA, XB, rm, whist, removed, tri_x, tri_xb)
    cur[0] = new
    return 0, n_new, 0


@njit(cache=True, inline="always")
def rebuild_due(dmax2, flagged, counters, skin, meshes_move, tri_x, tri_xb):
    """Verlet skin criterion after the drift: a rebuild is pending (``counters[0]``), particles
    are flagged for removal (``flagged``), the largest squared displacement since the last build
    ``dmax2`` exceeds (skin/2)^2, or (moving meshes, already placed at the new time) the
    largest triangle displacement plus the largest particle displacement exceeds the skin."""
    need = counters[0] != 0 or flagged != 0 or dmax2 > (0.5 * skin) ** 2
    if meshes_move and not need:
        if math.sqrt(max_tri_disp2(tri_x, tri_xb)) + math.sqrt(dmax2) > skin:
            need = True
    return need
