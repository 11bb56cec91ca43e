"""The sphere-triangle search of the mesh walls against a brute force written independently.

``meshes.nearest_image_contact`` tries one image of the sphere's centre per triangle when no
second image is within reach (the usual case) and the images of both sides of the periodic seam
otherwise; here every one of the 27 images is tried with a closest-point construction of its
own (projection onto the plane when it falls inside the triangle, else the nearest of the three
edges as clamped segments), not Ericson's Voronoi regions that the engine uses. The batched
mesh contacts (``mesh_contacts.mesh_pass``: SIMD geometry, the full image search near the seam,
the wall law) are checked against the same brute force through the Hertz force (Hertz 1882).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from twin_core.dem.mesh_contacts import (
    MBLOCK_WORDS,
    MFLT_COLS,
    MINT_ROWS,
    add_mesh_sums,
    flatten_triangles,
    mesh_pass,
)
from twin_core.dem.meshes import nearest_image_contact

_L = np.array([0.04, 0.08, 0.08])  # the seed blender's section: x periodic


def _closest_on_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0.0, 1.0)
    return a + t * ab


def _closest_on_triangle(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Projection onto the plane if inside (barycentric coordinates by least squares), else the
    nearest point of the three edges."""
    a, b, c = tri[0:3], tri[3:6], tri[6:9]
    n = np.cross(b - a, c - a)
    q = p - np.dot(p - a, n) / np.dot(n, n) * n
    m = np.column_stack([b - a, c - a])
    (u, v), *_ = np.linalg.lstsq(m, q - a, rcond=None)
    if u >= 0.0 and v >= 0.0 and u + v <= 1.0:
        return q
    edges = [
        _closest_on_segment(p, a, b),
        _closest_on_segment(p, b, c),
        _closest_on_segment(p, c, a),
    ]
    return min(edges, key=lambda e: float(np.sum((p - e) ** 2)))


def _brute_force_vector(p: np.ndarray, tri: np.ndarray, per: np.ndarray):
    """Over the 27 images q of p (shifts of one period along the periodic axes): the smallest
    squared distance to the triangle, whether a shifted image is the nearest, and the vector
    from that image to its closest point."""
    best, shifted, vec = np.inf, False, np.zeros(3)
    for sx in (-1, 0, 1) if per[0] else (0,):
        for sy in (-1, 0, 1) if per[1] else (0,):
            for sz in (-1, 0, 1) if per[2] else (0,):
                q = p + np.array([sx, sy, sz]) * _L
                v = _closest_on_triangle(q, tri) - q
                d2 = float(np.sum(v**2))
                if d2 < best:
                    best, shifted, vec = d2, (sx, sy, sz) != (0, 0, 0), v
    return best, shifted, vec


def _brute_force(p: np.ndarray, tri: np.ndarray, per: np.ndarray) -> tuple[float, bool]:
    """:func:`_brute_force_vector` without the vector."""
    best, shifted, _ = _brute_force_vector(p, tri, per)
    return best, shifted


@njit(cache=True)
def _search(p, tri_x, q, dom, per, reach2):
    return nearest_image_contact(p[0], p[1], p[2], tri_x, q, dom, per, reach2)


def _triangles(rng: np.random.Generator, k: int) -> np.ndarray:
    """Half small triangles anywhere in the box, half full-period strips along x (the trough of
    the blender: walls extruded along the periodic axis)."""
    tris = []
    for t in range(k):
        if t % 2 == 0:
            c = rng.uniform([0.005, 0.01, 0.01], _L - [0.005, 0.01, 0.01])
            tris.append(np.concatenate([c + rng.normal(0, 0.004, 3) for _ in range(3)]))
        else:
            y0, z0 = rng.uniform(0.01, 0.07, 2)
            dy, dz = rng.normal(0, 0.006, 2)
            x0, x1 = 0.0, _L[0]
            tris.append(np.array([x0, y0, z0, x1, y0, z0, x1 if t % 4 == 1 else x0,
                                  y0 + dy, z0 + dz]))  # fmt: skip
    return np.array(tris)


def test_nearest_image_contact_matches_a_brute_force_over_all_images():
    """On 400 triangles (small ones and full-period strips) and 40 points per triangle within
    reach or not, near the periodic seam or not: the contact is found exactly when some image
    lies within reach, at the brute force's distance (to 1e-9 of the reach), also where the
    nearest image is across the seam; no contact is invented beyond the reach."""
    rng = np.random.default_rng(11)
    dom = np.array([0.0, 0.0, 0.0, *_L, *_L])
    per = np.array([1, 0, 0], np.int64)
    tri_x = _triangles(rng, 400)
    reach = 1.5e-3
    found = wrapped = 0
    for q in range(tri_x.shape[0]):
        tri = tri_x[q]
        centre = (tri[0:3] + tri[3:6] + tri[6:9]) / 3
        for _ in range(40):
            p = centre + rng.normal(0.0, 1.5e-3, 3)
            if rng.random() < 0.3:  # a point next to the seam, on either side
                p[0] = rng.choice([rng.uniform(0.0, 2e-3), _L[0] - rng.uniform(0.0, 2e-3)])
            p[0] %= _L[0]
            want, shifted = _brute_force(p, tri, per)
            got = _search(p, tri_x, q, dom, per, reach * reach)[7]
            if want < reach * reach * (1 - 1e-9):
                assert abs(got - want) <= 1e-9 * reach * reach, (q, p, got, want)
                found += 1
                wrapped += shifted
            elif want > reach * reach * (1 + 1e-9):
                assert got == np.inf, (q, p, got, want)
    assert found > 2000 and wrapped > 50  # contacts through the seam were among them


@njit(cache=True)
def _mesh_forces(n, mint, mflt, mcnt):
    out = np.zeros((n, 6))
    for i in range(n):
        out[i] = add_mesh_sums(i, mint, mflt, mcnt, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    return out


def _batched_mesh_forces(P, tri_x, tri_of, dom, per, pt, chunks):
    """Mesh force and torque on each particle from ``mesh_pass``, each particle with one
    candidate triangle (``tri_of``), a static mesh, no spring."""
    n = P.shape[0]
    IA = np.zeros((n, 3), np.int64)
    ntri = np.ones(n, np.int32)
    tri_nb = tri_of.astype(np.int32).reshape(n, 1)
    thist = np.zeros((n, 1, 3))
    mesh_par = np.zeros((1, 16))
    mesh_par[0, 13], mesh_par[0, 14], mesh_par[0, 15] = -np.inf, np.inf, 1.0
    mint = np.zeros((MINT_ROWS, n), np.int32)
    mflt = np.zeros((n, MFLT_COLS))
    mcnt = np.zeros((3, n + 1), np.int64)
    flatten_triangles(n, ntri, tri_nb, thist, mcnt, mint)
    mesh_pass(
        n, P, IA, thist, tri_x, np.zeros(len(tri_x), np.int64), mesh_par, pt, dom, per, 1e-6,
        0.0, mint, mflt, mcnt, np.zeros((chunks, MBLOCK_WORDS)),
    )  # fmt: skip
    return _mesh_forces(n, mint, mflt, mcnt)


def test_batched_mesh_contacts_give_the_hertz_force_of_the_brute_force_distance():
    """Spheres at rest (r = 1.5 mm), each with one candidate triangle (400 triangles, small ones
    and full-period strips; 30 % of the centres next to the periodic seam), through the batched
    pass: a sphere within reach of some image gets the Hertz force ``(4/3) E* sqrt(R delta)
    delta`` (Hertz 1882; no velocity, no spring, no torque) with delta from the brute force's
    distance, along the brute force's normal, pushing the sphere away; the others get nothing.
    The sums are the same bits when the particles are split into 1 or 3 chunks (SIMD lanes,
    blocks and the scalar remainder)."""
    rng = np.random.default_rng(5)
    dom = np.array([0.0, 0.0, 0.0, *_L, *_L])
    per = np.array([1, 0, 0], np.int64)
    tri_x = _triangles(rng, 400)
    r, e_star = 1.5e-3, 1e8
    pts, tri_of = [], []
    for q in range(tri_x.shape[0]):
        centre = (tri_x[q, 0:3] + tri_x[q, 3:6] + tri_x[q, 6:9]) / 3
        for _ in range(10):
            p = centre + rng.normal(0.0, 1.5e-3, 3)
            if rng.random() < 0.3:
                p[0] = rng.choice([rng.uniform(0.0, 2e-3), _L[0] - rng.uniform(0.0, 2e-3)])
            p[0] %= _L[0]
            pts.append(p)
            tri_of.append(q)
    n = len(pts)
    P = np.zeros((n, 13))
    P[:, 0:3] = pts
    P[:, 9], P[:, 10] = r, 1e-5
    P[:, 11], P[:, 12] = 1e5, 1.0 / (0.4 * 1e-5 * r * r)
    pt = np.zeros((6, 2, 2))
    pt[0], pt[1], pt[2], pt[4] = e_star, e_star / 2.5, 0.5, 0.3
    pt[5] = np.sqrt(4 / 2.5)
    got = _batched_mesh_forces(P, tri_x, np.array(tri_of), dom, per, pt, 1)
    assert np.array_equal(got, _batched_mesh_forces(P, tri_x, np.array(tri_of), dom, per, pt, 3))
    touching = wrapped = 0
    for i in range(n):
        d2, shifted, vec = _brute_force_vector(P[i, 0:3], tri_x[tri_of[i]], per)
        if d2 < r * r * (1 - 1e-9):
            delta = r - np.sqrt(d2)
            f = 4 / 3 * e_star * np.sqrt(r * delta) * delta
            want = -f * vec / np.sqrt(d2)
            assert np.allclose(got[i, 0:3], want, rtol=0, atol=1e-6 * f), (i, got[i], want)
            assert np.all(np.abs(got[i, 3:6]) <= 1e-9 * f * r)
            touching += 1
            wrapped += shifted
        elif d2 > r * r * (1 + 1e-9):
            assert np.all(got[i] == 0.0), (i, got[i])
    assert touching > 1500 and wrapped > 30
