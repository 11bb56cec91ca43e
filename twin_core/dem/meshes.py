"""Triangle-mesh walls of the DEM engine (LIGGGHTS' ``fix mesh/surface``): triangle geometry
and prescribed mesh motion. The candidate triangles of each sphere are listed in
:mod:`twin_core.dem.partition`; the contacts and their forces are computed in
:mod:`twin_core.dem.mesh_contacts`.

- Geometry: closest point of a triangle to a point with its feature (face, edge, vertex); the
  image of a particle nearest to a triangle on periodic axes (of the images that can come
  close to it, the one whose closest point is nearest).
- Motion: ``mesh_par`` rows (kind 0 static, 1 rotation, 2 translation; axis point, axis, omega,
  velocity, motion window, activation window, material); rotation by Rodrigues' formula
  ``x' = a + p cos th + (u x p) sin th + u (u.p)(1 - cos th)``, ``p = x0 - a``.

References: Ericson, Real-Time Collision Detection (2005), Sec. 5.1.5 (closest point on a
triangle); Su, Gu & Xu (2011), Chem. Eng. Sci. 66, 6069 (one contact per sphere on tessellated
walls: edge and vertex contacts shadowed by face contacts); Kloss et al. (2012), Prog. Comput.
Fluid Dyn. 12, 140 (LIGGGHTS mesh walls).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = [
    "axis_images",
    "closest_point_triangle",
    "dist_point_tri",
    "max_tri_disp2",
    "mesh_state",
    "nearest_image_contact",
    "update_mesh",
]


@njit(cache=True, inline="always")
def closest_point_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Closest point of triangle (a, b, c) to point p (Ericson's Voronoi regions, tested in his
    order: vertex a, vertex b, edge ab, vertex c, edge ac, edge bc, face).

    Returns (x, y, z, feature) with feature 0 = face interior, 1 = edge, 2 = vertex.
    Straight-line code: every region's test is computed and the first that holds is selected,
    with one division (the selected region's parameter), so that a loop over many points is
    compiled to SIMD code and a single call has no mispredicted branches. A vertex is returned
    exactly; an edge point is ``a + t (b - a)`` (``b + t (c - b)`` on bc), a face point
    ``a + v (b - a) + w (c - a)`` with barycentric ``v = vb / (va + vb + vc)``,
    ``w = vc / (va + vb + vc)``.
    Reference: Ericson, Real-Time Collision Detection (2005), Sec. 5.1.5.
    """
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    # region codes: 0 face, 1 edge ab, 2 edge ac, 3 edge bc, 4 vertex a, 5 vertex b, 6 vertex c;
    # selected from the last test to the first, so the first test that holds wins
    region = 0
    num = 1.0
    den = va + vb + vc
    e43 = d4 - d3
    e56 = d5 - d6
    if (va <= 0.0) & (e43 >= 0.0) & (e56 >= 0.0):
        region, num, den = 3, e43, e43 + e56
    if (vb <= 0.0) & (d2 >= 0.0) & (d6 <= 0.0):
        region, num, den = 2, d2, d2 - d6
    if (d6 >= 0.0) & (d5 <= d6):
        region = 6
    if (vc <= 0.0) & (d1 >= 0.0) & (d3 <= 0.0):
        region, num, den = 1, d1, d1 - d3
    if (d3 >= 0.0) & (d4 <= d3):
        region = 5
    if (d1 <= 0.0) & (d2 <= 0.0):
        region = 4
    if region >= 4 or den == 0.0:
        den = 1.0  # a vertex needs no parameter (and a degenerate region divides by nothing)
    rcp = 1.0 / den
    t = num * rcp
    # face: a + v ab + w ac
    x = ax + abx * (vb * rcp) + acx * (vc * rcp)
    y = ay + aby * (vb * rcp) + acy * (vc * rcp)
    z = az + abz * (vb * rcp) + acz * (vc * rcp)
    feat = 0
    if region == 1:
        x, y, z, feat = ax + t * abx, ay + t * aby, az + t * abz, 1
    if region == 2:
        x, y, z, feat = ax + t * acx, ay + t * acy, az + t * acz, 1
    if region == 3:
        x, y, z, feat = bx + t * (cx - bx), by + t * (cy - by), bz + t * (cz - bz), 1
    if region == 4:
        x, y, z, feat = ax, ay, az, 2
    if region == 5:
        x, y, z, feat = bx, by, bz, 2
    if region == 6:
        x, y, z, feat = cx, cy, cz, 2
    return x, y, z, feat


@njit(cache=True, inline="always")
def _insert_image(s0, g0, s1, g1, s, g):
    """The two nearest images (s0, g0), (s1, g1) (shift, gap; the first of equal gaps kept
    first) after image (s, g) is considered."""
    first = g < g0
    second = (not first) and g < g1
    s1n = s0 if first else (s if second else s1)
    g1n = g0 if first else (g if second else g1)
    return (s if first else s0), (g if first else g0), s1n, g1n


@njit(cache=True, inline="always")
def axis_images(p, t0, t1, t2, length, periodic):
    """The two images ``p + k L`` (k in -1, 0, 1) of a coordinate nearest to the interval
    spanned by a triangle's coordinates t0, t1, t2 along one axis: (shift, gap) of the nearest
    and of the second nearest (gap ``inf`` along a closed axis, where only ``p`` exists).
    Straight-line code (the three images written out)."""
    lo = min(t0, t1, t2)
    hi = max(t0, t1, t2)
    if not periodic:
        return 0.0, 0.0, 0.0, math.inf
    q = p - length
    s0, g0, s1, g1 = -length, max(lo - q, q - hi, 0.0), 0.0, math.inf
    s0, g0, s1, g1 = _insert_image(s0, g0, s1, g1, 0.0, max(lo - p, p - hi, 0.0))
    q = p + length
    return _insert_image(s0, g0, s1, g1, length, max(lo - q, q - hi, 0.0))


@njit(cache=True, inline="always")
def _pick(k, a, b):
    """``a`` for k == 0, ``b`` otherwise."""
    return a if k == 0 else b


@njit(cache=True, inline="always")
def _image_contact(qx, qy, qz, tri_x, tq, ax, ay, az, nx, ny, nz, nn, best):
    """Closest point c of triangle ``tri_x[tq]`` (first vertex a, normal n, ``nn = |n|^2``) to
    the image q, if q's distance to the triangle's plane is below ``sqrt(best)``:
    (cx, cy, cz, feature, |q - c|^2), the squared distance ``inf`` when the plane is out of
    reach (then so is the triangle; no plane test for a degenerate triangle, ``nn = 0``)."""
    dn = nx * (qx - ax) + ny * (qy - ay) + nz * (qz - az)
    if dn * dn >= best * nn and nn > 0.0:
        return qx, qy, qz, 0, math.inf
    cx, cy, cz, feat = closest_point_triangle(
        qx, qy, qz, ax, ay, az, tri_x[tq, 3], tri_x[tq, 4], tri_x[tq, 5], tri_x[tq, 6],
        tri_x[tq, 7], tri_x[tq, 8],
    )  # fmt: skip
    return cx, cy, cz, feat, (qx - cx) ** 2 + (qy - cy) ** 2 + (qz - cz) ** 2


@njit(cache=True, inline="always")
def nearest_image_contact(px, py, pz, tri_x, tq, dom, per, reach2):
    """Image q of point p nearest to triangle ``tri_x[tq]`` and its closest point c on the
    triangle: (qx, qy, qz, cx, cy, cz, feature, d2), feature as in
    :func:`closest_point_triangle`, d2 = |q - c|^2.

    Along a periodic axis a triangle can come close to two images of p (a wall that spans the
    whole period, e.g. a trough extruded along the periodic axis): both are tried, the second
    only when its gap along the axis (a lower bound of its distance) is below the distance
    found so far. Minimum image about the triangle's centroid instead picks, for p within a
    third of the period of the seam, an image outside a full-length triangle and misses the
    contact.

    Only contacts closer than ``sqrt(reach2)`` are sought: an image is skipped without the
    closest-point search when its gap to the triangle's bounding box or its distance to the
    triangle's plane is not below that reach (most candidates of a list built with a skin).
    Returns the squared distance last, ``inf`` with p itself for both points when no image is
    within reach.
    """
    ax, ay, az = tri_x[tq, 0], tri_x[tq, 1], tri_x[tq, 2]
    ux, uy, uz = tri_x[tq, 3] - ax, tri_x[tq, 4] - ay, tri_x[tq, 5] - az
    wx, wy, wz = tri_x[tq, 6] - ax, tri_x[tq, 7] - ay, tri_x[tq, 8] - az
    nx, ny, nz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
    nn = nx * nx + ny * ny + nz * nz  # |normal|^2 (0 for a degenerate triangle: no plane test)
    sx0, gx0, sx1, gx1 = axis_images(px, ax, tri_x[tq, 3], tri_x[tq, 6], dom[6], per[0] != 0)
    sy0, gy0, sy1, gy1 = axis_images(py, ay, tri_x[tq, 4], tri_x[tq, 7], dom[7], per[1] != 0)
    sz0, gz0, sz1, gz1 = axis_images(pz, az, tri_x[tq, 5], tri_x[tq, 8], dom[8], per[2] != 0)
    best = reach2
    out = (px, py, pz, px, py, pz, 0, math.inf)
    if gx1 * gx1 >= best and gy1 * gy1 >= best and gz1 * gz1 >= best:
        # the usual case: no second image within reach, one image to try (the loop below
        # with its seven other images skipped, written out)
        if gx0 * gx0 + gy0 * gy0 + gz0 * gz0 >= best:
            return out
        qx, qy, qz = px + sx0, py + sy0, pz + sz0
        cx, cy, cz, feat, d2 = _image_contact(
            qx, qy, qz, tri_x, tq, ax, ay, az, nx, ny, nz, nn, best
        )
        if d2 < best:
            out = (qx, qy, qz, cx, cy, cz, feat, d2)
        return out
    for a in range(2):
        gx = _pick(a, gx0, gx1)
        for b in range(2):
            gy = _pick(b, gy0, gy1)
            for c in range(2):
                gz = _pick(c, gz0, gz1)
                if gx * gx + gy * gy + gz * gz >= best:
                    continue
                qx = px + _pick(a, sx0, sx1)
                qy = py + _pick(b, sy0, sy1)
                qz = pz + _pick(c, sz0, sz1)
                cx, cy, cz, feat, d2 = _image_contact(
                    qx, qy, qz, tri_x, tq, ax, ay, az, nx, ny, nz, nn, best
                )
                if d2 < best:
                    best = d2
                    out = (qx, qy, qz, cx, cy, cz, feat, d2)
    return out


@njit(cache=True)
def dist_point_tri(px, py, pz, tri_x, q):
    """Distance of point p to triangle ``tri_x[q]`` (9 floats)."""
    cx, cy, cz, _ = closest_point_triangle(
        px, py, pz, tri_x[q, 0], tri_x[q, 1], tri_x[q, 2], tri_x[q, 3], tri_x[q, 4], tri_x[q, 5],
        tri_x[q, 6], tri_x[q, 7], tri_x[q, 8],
    )  # fmt: skip
    return math.sqrt((px - cx) ** 2 + (py - cy) ** 2 + (pz - cz) ** 2)


@njit(cache=True)
def mesh_state(mesh_par, m, t):
    """Motion of mesh m at time t.

    Returns (active, kind, theta, omega, dx, dy, dz, vx, vy, vz): ``kind`` 0 static, 1 rotation,
    2 translation; ``theta`` the rotation angle, ``omega`` the current angular speed (rad/s) and
    ``d``/``v`` the translation and its current velocity.
    """
    kind = int(mesh_par[m, 0])
    t_start, t_end = mesh_par[m, 11], mesh_par[m, 12]
    active = mesh_par[m, 13] <= t < mesh_par[m, 14]
    tc = min(max(t, t_start), t_end)
    moving = t_start <= t < t_end
    theta = 0.0
    omega = 0.0
    dx = dy = dz = 0.0
    vx = vy = vz = 0.0
    if kind == 1:
        theta = mesh_par[m, 7] * (tc - t_start)
        if moving:
            omega = mesh_par[m, 7]
    elif kind == 2:
        dx = mesh_par[m, 8] * (tc - t_start)
        dy = mesh_par[m, 9] * (tc - t_start)
        dz = mesh_par[m, 10] * (tc - t_start)
        if moving:
            vx, vy, vz = mesh_par[m, 8], mesh_par[m, 9], mesh_par[m, 10]
    return active, kind, theta, omega, dx, dy, dz, vx, vy, vz


@njit(cache=True)
def update_mesh(tri_x0, tri_x, tri_mesh, mesh_par, t):
    """Place every triangle of a moving mesh at time t (Rodrigues rotation about the mesh axis or
    translation), from its reference coordinates ``tri_x0``. Each mesh's motion (and the cosine
    and sine of its angle) is evaluated once, not per triangle: it runs every step while meshes
    move (skin criterion), serially (a few hundred triangles: a parallel region costs more)."""
    nm = mesh_par.shape[0]
    motion = np.empty((nm, 5))  # cos, sin of the angle; translation (3)
    for m in range(nm):
        _, _, theta, _, dx, dy, dz, _, _, _ = mesh_state(mesh_par, m, t)
        motion[m, 0] = math.cos(theta)
        motion[m, 1] = math.sin(theta)
        motion[m, 2] = dx
        motion[m, 3] = dy
        motion[m, 4] = dz
    for q in range(tri_x0.shape[0]):
        m = tri_mesh[q]
        kind = int(mesh_par[m, 0])
        if kind == 0:
            continue
        if kind == 1:
            ax, ay, az = mesh_par[m, 1], mesh_par[m, 2], mesh_par[m, 3]
            ux, uy, uz = mesh_par[m, 4], mesh_par[m, 5], mesh_par[m, 6]
            ct = motion[m, 0]
            s = motion[m, 1]
            for v in range(3):
                px = tri_x0[q, 3 * v] - ax
                py = tri_x0[q, 3 * v + 1] - ay
                pz = tri_x0[q, 3 * v + 2] - az
                kd = ux * px + uy * py + uz * pz
                cx = uy * pz - uz * py
                cy = uz * px - ux * pz
                cz = ux * py - uy * px
                tri_x[q, 3 * v] = ax + px * ct + cx * s + ux * kd * (1.0 - ct)
                tri_x[q, 3 * v + 1] = ay + py * ct + cy * s + uy * kd * (1.0 - ct)
                tri_x[q, 3 * v + 2] = az + pz * ct + cz * s + uz * kd * (1.0 - ct)
        else:
            for v in range(3):
                tri_x[q, 3 * v] = tri_x0[q, 3 * v] + motion[m, 2]
                tri_x[q, 3 * v + 1] = tri_x0[q, 3 * v + 1] + motion[m, 3]
                tri_x[q, 3 * v + 2] = tri_x0[q, 3 * v + 2] + motion[m, 4]


@njit(cache=True)
def max_tri_disp2(tri_x, tri_xb):
    """Largest squared displacement of a triangle vertex since the last build (``tri_xb``)."""
    m = 0.0
    for q in range(tri_x.shape[0]):
        for v in range(3):
            d = (
                (tri_x[q, 3 * v] - tri_xb[q, 3 * v]) ** 2
                + (tri_x[q, 3 * v + 1] - tri_xb[q, 3 * v + 1]) ** 2
                + (tri_x[q, 3 * v + 2] - tri_xb[q, 3 * v + 2]) ** 2
            )
            if d > m:
                m = d
    return m
