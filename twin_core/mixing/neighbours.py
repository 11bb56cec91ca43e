"""Contacts and nearest neighbours from particle positions (periodic boxes allowed).

One cell-list pass (numba, one thread) finds both: the contact pairs and the ``k`` nearest
neighbours of every particle. Particles are binned into cells about the contact cut-off
``2 r_max (1 + tolerance)`` wide; the particles of the 27 cells around each cell are gathered
once and compared with every particle of the cell, which finds every contact, and the same
distances give the neighbour candidates (one pass for NNM, PS, CN and SI); a particle
whose ``k``-th nearest candidate lies beyond the reach of those cells (free surface, flying
particle) is searched again over growing blocks of cells, so contacts and neighbours are exact
(the same pairs and sets as a KD-tree, ``tests/twin_core/mixing/test_mixing_indices.py``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: contact pairs reserved per particle before a search is retried with more room
_PAIRS_PER_PARTICLE = 16


def _periods(box: np.ndarray | None) -> np.ndarray:
    """Period per axis, 0 where the axis is not periodic (``inf``/``nan``/``None``)."""
    if box is None:
        return np.zeros(3)
    b = np.asarray(box, float)
    return np.where(np.isfinite(b) & (b > 0), b, 0.0)


@njit(cache=True)
def _bounds(pos):
    """Smallest and largest coordinate per axis of the positions ``(N, 3)``, in one pass."""
    low = np.full(3, np.inf)
    high = np.full(3, -np.inf)
    for i in range(pos.shape[0]):
        for ax in range(3):
            low[ax] = min(low[ax], pos[i, ax])
            high[ax] = max(high[ax], pos[i, ax])
    return low, high


def _cell_layout(
    low: np.ndarray, span: np.ndarray, n: int, period: np.ndarray, h: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lower corner, cell count and cell width per axis of a cell list of side >= ``h`` over
    ``n`` particles whose positions start at ``low`` and extend over ``span``."""
    lo = np.where(period > 0, 0.0, low)
    extent = np.where(period > 0, period, span)
    ncell = np.maximum(1, np.floor(extent / h)).astype(np.int64)
    while np.prod(ncell.astype(float)) > 8.0 * n + 27:  # sparse or far-flung particles
        ncell = np.maximum(1, ncell // 2)
    ncell = np.where(period > 0, np.maximum(ncell, 3), ncell)
    width = np.where(period > 0, extent / ncell, np.maximum(extent / ncell, h))
    return lo, ncell, width


@njit(cache=True)
def _bin_particles(pos, lo, width, ncell, period):
    """Counting sort of the particles by cell: (cell of each particle, start of each cell, order)."""
    n = pos.shape[0]
    cell = np.empty((n, 3), np.int64)
    flat = np.empty(n, np.int64)
    for i in range(n):
        for a in range(3):
            x = pos[i, a]
            if period[a] > 0.0:
                x -= period[a] * math.floor(x / period[a])
            c = int(math.floor((x - lo[a]) / width[a]))
            cell[i, a] = min(max(c, 0), ncell[a] - 1)
        flat[i] = (cell[i, 0] * ncell[1] + cell[i, 1]) * ncell[2] + cell[i, 2]
    total = ncell[0] * ncell[1] * ncell[2]
    start = np.zeros(total + 1, np.int64)
    for i in range(n):
        start[flat[i] + 1] += 1
    for c in range(total):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[flat[i]]] = i
        fill[flat[i]] += 1
    return cell, start, order


@njit(cache=True, inline="always")
def _insert(best_d, best_j, d2, j):
    """Insert (d2, j) into the ascending arrays of the k best candidates."""
    q = best_d.shape[0] - 1
    while q > 0 and best_d[q - 1] > d2:
        best_d[q] = best_d[q - 1]
        best_j[q] = best_j[q - 1]
        q -= 1
    best_d[q] = d2
    best_j[q] = j


@njit(cache=True, inline="always")
def _neighbour_cell(c, off, ncell, period):
    """Index of the cell ``off`` cells from ``c`` along one axis and the shift (m) that brings its
    particles next to cell ``c`` (a period across a periodic boundary); -1 if there is none."""
    m = c + off
    if period > 0.0 and (off < -(ncell // 2) or off > (ncell - 1) // 2):
        return -1, 0.0  # each periodic image of a cell once
    if m >= 0 and m < ncell:
        return m, 0.0
    if period == 0.0:
        return -1, 0.0
    if m < 0:
        return m + ncell, -period
    return m - ncell, period


@njit(cache=True, inline="always")
def _gap(frac, off, width):
    """Distance along one axis from a point at fractional position ``frac`` in its cell to the
    cell ``off`` cells away."""
    if off < 0:
        return (frac - off - 1.0) * width
    if off > 0:
        return (off - frac) * width
    return 0.0


@njit(cache=True, inline="always")
def _image_d2(dx, dy, dz, im0, im1, im2):
    """Squared length of the separation (dx, dy, dz) at its nearest periodic image along the
    axes whose period ``im0, im1, im2`` is > 0: ``d - L rint(d / L)`` (Allen & Tildesley 2017,
    Sec. 1.6.2)."""
    if im0 > 0.0:
        dx -= im0 * np.rint(dx / im0)
    if im1 > 0.0:
        dy -= im1 * np.rint(dy / im1)
    if im2 > 0.0:
        dz -= im2 * np.rint(dz / im2)
    return dx * dx + dy * dy + dz * dz


@njit(cache=True, inline="always")
def _scan_range(ps, a, b0, b1, sh0, sh1, sh2, im0, im1, im2, thr, order, cand_d, cand_j, m):
    """Candidates ``b0 <= b < b1`` (cell order, shifted by a period where they lie across a
    periodic boundary; the nearest periodic image along the axes where ``im0, im1, im2`` hold
    the period) of particle ``a`` closer than ``sqrt(thr)``, appended to ``cand_d, cand_j``
    (``m`` held so far). Returns the new count."""
    xa, ya, za = ps[a, 0], ps[a, 1], ps[a, 2]
    for b in range(b0, b1):
        if b == a:
            continue
        d2 = _image_d2(ps[b, 0] + sh0 - xa, ps[b, 1] + sh1 - ya, ps[b, 2] + sh2 - za, im0, im1, im2)
        if d2 < thr:
            cand_d[m] = d2
            cand_j[m] = order[b]
            m += 1
    return m


@njit(cache=True)
def _scan_block(ps, order, start, cell, frac, ncell, width, period, a, s, thr, cand_d, cand_j):
    """Candidates of particle ``a`` closer than ``sqrt(thr)`` in the ``(2 s + 1)^3`` cells
    around its cell, into ``cand_d, cand_j``; returns how many. Cells are taken in rows along
    axis 2, whose particles are contiguous in cell order (two ranges where a row wraps around
    a periodic boundary); a row, or a cell at either end of it, farther than ``sqrt(thr)`` is
    skipped."""
    lo2, hi2 = -s, s
    if period[2] > 0.0:
        lo2, hi2 = max(lo2, -(ncell[2] // 2)), min(hi2, (ncell[2] - 1) // 2)
    im0 = period[0] if 2 * s + 2 >= ncell[0] else 0.0
    im1 = period[1] if 2 * s + 2 >= ncell[1] else 0.0
    im2 = period[2] if 2 * s + 2 >= ncell[2] else 0.0
    m = 0
    for o0 in range(-s, s + 1):
        c0, sh0 = _neighbour_cell(cell[0], o0, ncell[0], period[0])
        if c0 < 0:
            continue
        for o1 in range(-s, s + 1):
            c1, sh1 = _neighbour_cell(cell[1], o1, ncell[1], period[1])
            if c1 < 0:
                continue
            g = _gap(frac[0], o0, width[0]) ** 2 + _gap(frac[1], o1, width[1]) ** 2
            if g >= thr:
                continue
            first, last = lo2, hi2
            while first < 0 and g + _gap(frac[2], first, width[2]) ** 2 >= thr:
                first += 1
            while last > 0 and g + _gap(frac[2], last, width[2]) ** 2 >= thr:
                last -= 1
            first, last = cell[2] + first, cell[2] + last
            if period[2] == 0.0:
                first, last = max(first, 0), min(last, ncell[2] - 1)
            row = (c0 * ncell[1] + c1) * ncell[2]
            if first < 0:  # wrapped part below the periodic boundary
                m = _scan_range(ps, a, start[row + first + ncell[2]], start[row + ncell[2]],
                                sh0, sh1, -period[2], im0, im1, im2, thr, order, cand_d, cand_j,
                                m)  # fmt: skip
                first = 0
            if last >= ncell[2]:  # wrapped part above it
                m = _scan_range(ps, a, start[row], start[row + last - ncell[2] + 1], sh0, sh1,
                                period[2], im0, im1, im2, thr, order, cand_d, cand_j, m)  # fmt: skip
                last = ncell[2] - 1
            if first <= last:
                m = _scan_range(ps, a, start[row + first], start[row + last + 1], sh0, sh1, 0.0,
                                im0, im1, im2, thr, order, cand_d, cand_j, m)  # fmt: skip
    return m


@njit(cache=True)
def _select(cand_d, cand_j, m, best_d, best_j):
    """The ``k`` smallest of the ``m`` candidates into ``best_d, best_j`` (ascending)."""
    k = best_d.shape[0]
    best_d[:] = np.inf
    for q in range(m):
        if cand_d[q] < best_d[k - 1]:
            _insert(best_d, best_j, cand_d[q], cand_j[q])


@njit(cache=True, inline="always")
def _block_reach(frac, s, ncell, width, period):
    """Distance within which every particle lies in the ``(2 s + 1)^3`` cells around a particle
    at fractional position ``frac`` in its cell (``inf`` if the block spans every axis)."""
    reach = np.inf
    for ax in range(3):
        if not (period[ax] > 0.0 and 2 * s + 1 >= ncell[ax]):
            reach = min(reach, (s + min(frac[ax], 1.0 - frac[ax])) * width[ax])
    return reach


@njit(cache=True)
def _gather_block(ps, rs, start, c0, c1, c2, ncell, period, buf_p, buf_r, buf_b):
    """Copy the particles of the 27 cells around cell ``(c0, c1, c2)`` into contiguous buffers
    (``buf_p`` one row per coordinate; positions shifted by a period where a cell lies across a periodic boundary; each cell
    once). Returns how many, and where the cell's own particles start in the buffers."""
    m = 0
    own = 0
    for o0 in range(-1, 2):
        n0, sh0 = _neighbour_cell(c0, o0, ncell[0], period[0])
        if n0 < 0:
            continue
        for o1 in range(-1, 2):
            n1, sh1 = _neighbour_cell(c1, o1, ncell[1], period[1])
            if n1 < 0:
                continue
            for o2 in range(-1, 2):
                n2, sh2 = _neighbour_cell(c2, o2, ncell[2], period[2])
                if n2 < 0:
                    continue
                c = (n0 * ncell[1] + n1) * ncell[2] + n2
                if o0 == 0 and o1 == 0 and o2 == 0:
                    own = m
                for b in range(start[c], start[c + 1]):
                    buf_p[0, m] = ps[b, 0] + sh0
                    buf_p[1, m] = ps[b, 1] + sh1
                    buf_p[2, m] = ps[b, 2] + sh2
                    buf_r[m] = rs[b]
                    buf_b[m] = b
                    m += 1
    return m, own


@njit(cache=True, inline="always")
def _block_distances(buf_p, m_buf, xa, ya, za, im0, im1, im2, dist):
    """Squared distances from ``(xa, ya, za)`` to the ``m_buf`` gathered particles into ``dist``
    (nearest periodic image along the axes whose ``im`` is > 0; a plain loop, which the
    compiler vectorises, when there is none)."""
    if im0 > 0.0 or im1 > 0.0 or im2 > 0.0:
        for q in range(m_buf):
            dist[q] = _image_d2(buf_p[0, q] - xa, buf_p[1, q] - ya, buf_p[2, q] - za, im0, im1, im2)
    else:
        for q in range(m_buf):
            dx = buf_p[0, q] - xa
            dy = buf_p[1, q] - ya
            dz = buf_p[2, q] - za
            dist[q] = dx * dx + dy * dy + dz * dz


@njit(cache=True, inline="always")
def _block_contacts(dist, buf_r, buf_b, m_buf, a, ra, cutoff_factor, order, pairs, n_pairs):
    """Append the contacts of particle ``a`` (cell order) with the gathered particles after it
    in cell order (each pair once) to ``pairs``, counting beyond its length; returns the count."""
    max_pairs = pairs.shape[0]
    i = order[a]
    for q in range(m_buf):
        b = buf_b[q]
        if b > a:
            rc = (ra + buf_r[q]) * cutoff_factor
            if dist[q] < rc * rc:
                if n_pairs < max_pairs:
                    j = order[b]
                    pairs[n_pairs, 0] = min(i, j)
                    pairs[n_pairs, 1] = max(i, j)
                n_pairs += 1
    return n_pairs


@njit(cache=True)
def _search(pos, radii, period, lo, width, ncell, cutoff_factor, k, max_pairs):
    """Contacts (pairs ``i < j`` closer than ``(r_i + r_j) * cutoff_factor``; none if the factor
    is 0) and the ``k`` nearest neighbours of every particle (none if ``k`` is 0).

    Cell by cell (positions, wrapped on periodic axes, copied in cell order), the particles of
    the 27 cells around a cell are gathered once into contiguous buffers (one array per
    coordinate) and the squared distances of every particle of the cell to them are computed
    in one loop; the contacts and the neighbour candidates are read from these distances. The
    buffers hold every contact partner (cells are at least the cut-off wide). For the
    neighbours, only candidates closer than a running estimate of the ``k``-th distance (the
    previous particle's plus 10 %) are ranked; when fewer than ``k`` are that close, all are
    ranked, and when the ``k``-th candidate lies beyond the reach of the 27
    cells (a free-surface or flying particle), growing blocks of cells are ranked until it is
    within reach. Periodic axes need at least three cells; with four or fewer, distances take
    the nearest periodic image."""
    n = pos.shape[0]
    cell, start, order = _bin_particles(pos, lo, width, ncell, period)
    ps = np.empty((n, 3))
    rs = np.empty(n)
    for q in range(n):
        i = order[q]
        for ax in range(3):
            x = pos[i, ax]
            if period[ax] > 0.0:
                x -= period[ax] * math.floor(x / period[ax])
            ps[q, ax] = x
        rs[q] = radii[i]
    s_max = max(ncell[0], max(ncell[1], ncell[2]))
    im0 = period[0] if ncell[0] <= 4 else 0.0
    im1 = period[1] if ncell[1] <= 4 else 0.0
    im2 = period[2] if ncell[2] <= 4 else 0.0
    pairs = np.empty((max_pairs, 2), np.int64)
    n_pairs = 0
    nb = np.empty((n, k), np.int64)
    best_d = np.empty(k)
    best_j = np.empty(k, np.int64)
    cand_d = np.empty(n)
    cand_j = np.empty(n, np.int64)
    buf_p = np.empty((3, n))
    buf_r = np.empty(n)
    dist = np.empty(n)
    buf_b = np.empty(n, np.int64)
    frac = np.empty(3)
    min_reach2 = min(width[0], min(width[1], width[2])) ** 2  # the 27 cells hold this ball
    estimate = 0.0 if k == 0 else np.inf
    n_cells = ncell[0] * ncell[1] * ncell[2]
    for c in range(n_cells):
        if start[c + 1] == start[c]:
            continue
        i0 = order[start[c]]
        m_buf, own = _gather_block(ps, rs, start, cell[i0, 0], cell[i0, 1], cell[i0, 2], ncell,
                              period, buf_p, buf_r, buf_b)  # fmt: skip
        for a in range(start[c], start[c + 1]):
            i = order[a]
            _block_distances(buf_p, m_buf, ps[a, 0], ps[a, 1], ps[a, 2], im0, im1, im2, dist)
            if cutoff_factor > 0.0:
                n_pairs = _block_contacts(dist, buf_r, buf_b, m_buf, a, rs[a], cutoff_factor,
                                          order, pairs, n_pairs)  # fmt: skip
            if k == 0:
                continue
            dist[own + a - start[c]] = np.inf  # the particle itself
            m = 0
            for q in range(m_buf):  # branch-free compaction of those within the estimate
                cand_d[m] = dist[q]
                cand_j[m] = q
                m += dist[q] < estimate
            if m < k:  # fewer than k within the estimate: rank the whole block
                for q in range(m_buf):
                    cand_d[q] = dist[q]
                    cand_j[q] = q
                m = m_buf
            _select(cand_d, cand_j, m, best_d, best_j)
            for q in range(k):  # buffer slots -> particle indices (inf: no candidate)
                if best_d[q] < np.inf:
                    best_j[q] = order[buf_b[best_j[q]]]
            if best_d[k - 1] > min_reach2:  # the k-th may lie beyond the 27 cells
                for ax in range(3):
                    frac[ax] = min(max((ps[a, ax] - lo[ax]) / width[ax] - cell[i, ax], 0.0), 1.0)
            s = 1
            while (
                best_d[k - 1] > min_reach2
                and best_d[k - 1] > _block_reach(frac, s, ncell, width, period) ** 2
                and s <= s_max
            ):
                s += 1  # a wider block; only cells nearer than the k-th candidate so far
                m = _scan_block(ps, order, start, cell[i], frac, ncell, width, period, a, s,
                                best_d[k - 1] * (1 + 1e-9), cand_d, cand_j)  # fmt: skip
                _select(cand_d, cand_j, m, best_d, best_j)
            for q in range(k):
                nb[i, q] = best_j[q]
            estimate = best_d[k - 1] * 1.21
    return pairs, n_pairs, nb


def _typical_spacing(span: np.ndarray, n: int) -> float:
    """Cell side for a search without contacts: about two of ``n`` particles per cell on
    average over the extent ``span``."""
    volume = float(np.prod(np.maximum(span, span.max() * 1e-3 + 1e-300)))
    return (2.0 * volume / max(n, 1)) ** (1.0 / 3.0)


def neighbour_search(
    positions: np.ndarray,
    radii: np.ndarray,
    box: np.ndarray | None = None,
    tolerance: float | None = 0.02,
    k: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Contact pairs and ``k`` nearest neighbours in one cell-list pass.

    Returns ``(pairs, neighbours)``: pairs ``(i, j)``, ``i < j``, whose centre distance is below
    ``(r_i + r_j)(1 + tolerance)`` (in no particular order; an empty ``(0, 2)`` array when
    ``tolerance`` is ``None``), and the indices ``(N, k)`` of each particle's ``k`` nearest other
    particles, nearest first. ``box``: per-axis period for periodic axes, ``inf`` for the others.
    """
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    rad = np.ascontiguousarray(radii, dtype=np.float64)
    n = len(pos)
    if pos.shape != (n, 3) or rad.shape != (n,):
        raise ValueError(f"positions must be (N, 3) and radii (N,), got {pos.shape}, {rad.shape}")
    if tolerance is not None and tolerance < 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    if k < 0 or (k > 0 and k >= n):
        raise ValueError(f"k must be in [1, N-1], got {k} for N={n}")
    period = _periods(box)
    factor = 0.0 if tolerance is None else 1.0 + float(tolerance)
    low, high = _bounds(pos) if n else (np.zeros(3), np.zeros(3))
    span = high - low
    h = max(2.0 * float(rad.max(initial=0.0)) * factor, _typical_spacing(span, n))
    lo, ncell, width = _cell_layout(low, span, n, period, h)
    max_pairs = _PAIRS_PER_PARTICLE * max(n, 1)
    while True:
        pairs, n_pairs, nb = _search(pos, rad, period, lo, width, ncell, factor, k, max_pairs)
        if n_pairs <= max_pairs:
            break
        max_pairs = n_pairs
    return pairs[:n_pairs], nb


def contacts_from_positions(
    positions: np.ndarray,
    radii: np.ndarray,
    box: np.ndarray | None = None,
    tolerance: float = 0.02,
) -> np.ndarray:
    """Pairs ``(i, j)``, ``i < j``, whose centre distance is below ``(r_i + r_j)(1 + tolerance)``.

    ``box``: per-axis period length for periodic axes, ``inf`` for the others.
    The tolerance accepts near-touching pairs in frames saved with finite precision.
    """
    return neighbour_search(positions, radii, box, tolerance, 0)[0]


def nearest_neighbours(positions: np.ndarray, k: int, box: np.ndarray | None = None) -> np.ndarray:
    """Indices ``(N, k)`` of the ``k`` nearest other particles of each particle."""
    pos = np.asarray(positions, float)
    if k < 1 or k >= len(pos):
        raise ValueError(f"k must be in [1, N-1], got {k} for N={len(pos)}")
    return neighbour_search(pos, np.zeros(len(pos)), box, None, k)[1]


def minimum_image_distance(p: np.ndarray, q: np.ndarray, box: np.ndarray | None) -> np.ndarray:
    """Euclidean distance with the minimum-image convention on periodic axes."""
    d = np.asarray(q, float) - np.asarray(p, float)
    if box is not None:
        box = np.asarray(box, float)
        per = np.isfinite(box)
        if per.any():
            L = np.where(per, box, 1.0)
            d = np.where(per, d - L * np.round(d / L), d)
    return np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2])
