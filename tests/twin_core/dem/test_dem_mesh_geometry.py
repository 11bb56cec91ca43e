"""The sphere-triangle search of the mesh walls against a brute force written independently.

``meshes.nearest_image_contact`` tries one image of the sphere's centre per triangle when no
second image is within reach (the usual case) and the images of both sides of the periodic seam
otherwise; here every one of the 27 images is tried with a closest-point construction of its
own (projection onto the plane when it falls inside the triangle, else the nearest of the three
edges as clamped segments), not Ericson's Voronoi regions that the engine uses.
"""

from __future__ import annotations

import numpy as np
from numba import njit

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


def _brute_force(p: np.ndarray, tri: np.ndarray, per: np.ndarray) -> tuple[float, bool]:
    """Smallest squared distance from the 27 images of p (shifts of one period along the
    periodic axes) to the triangle, and whether a shifted image is the nearest."""
    best, shifted = np.inf, False
    for sx in (-1, 0, 1) if per[0] else (0,):
        for sy in (-1, 0, 1) if per[1] else (0,):
            for sz in (-1, 0, 1) if per[2] else (0,):
                q = p + np.array([sx, sy, sz]) * _L
                d2 = float(np.sum((q - _closest_on_triangle(q, tri)) ** 2))
                if d2 < best:
                    best, shifted = d2, (sx, sy, sz) != (0, 0, 0)
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
