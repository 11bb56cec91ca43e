"""Triangle-mesh walls of the DEM engine (LIGGGHTS' ``fix mesh/surface`` and ``fix
wall/gran``): triangle geometry, prescribed mesh motion and the contacts of a sphere with the
candidate triangles of its list (built in :mod:`twin_core.dem.partition`).

- Geometry: closest point of a triangle to a point with its feature (face, edge, vertex); the
  image of a particle nearest to a triangle on periodic axes (of the images that can come
  close to it, the one whose closest point is nearest).
- Motion: ``mesh_par`` rows (kind 0 static, 1 rotation, 2 translation; axis point, axis, omega,
  velocity, motion window, activation window, material); rotation by Rodrigues' formula
  ``x' = a + p cos th + (u x p) sin th + u (u.p)(1 - cos th)``, ``p = x0 - a``.
- Contact: face contacts always count; an edge/vertex contact is dropped when its contact point
  coincides with one already counted or lies on a triangle that has a face contact (a sphere on a
  flat or convex tessellated surface feels one contact, not one per triangle); the dropped
  contact copies the tangential history of the contact that shadows it, so the history follows a
  sphere sliding from one triangle to the next. The force is the wall contact law of
  :mod:`twin_core.dem.contact` with the mesh velocity at the contact point.

References: Ericson, Real-Time Collision Detection (2005), Sec. 5.1.5 (closest point on a
triangle); Su, Gu & Xu (2011), Chem. Eng. Sci. 66, 6069 (one contact per sphere on tessellated
walls: edge and vertex contacts shadowed by face contacts); Kloss et al. (2012), Prog. Comput.
Fluid Dyn. 12, 140 (LIGGGHTS mesh walls).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .contact import add_wall_contact, clear_history

__all__ = [
    "add_mesh_contacts",
    "closest_point_triangle",
    "dist_point_tri",
    "max_tri_disp2",
    "mesh_state",
    "nearest_image_contact",
    "update_mesh",
]


@njit(cache=True, inline="always")
def closest_point_triangle(px, py, pz, tri_x, q):
    """Closest point of triangle ``tri_x[q]`` (9 floats: a, b, c) to point p.

    Returns (cx, cy, cz, feature) with feature 0 = face interior, 1 = edge, 2 = vertex.
    Reference: Ericson, Real-Time Collision Detection (2005), Sec. 5.1.5.
    """
    ax, ay, az = tri_x[q, 0], tri_x[q, 1], tri_x[q, 2]
    bx, by, bz = tri_x[q, 3], tri_x[q, 4], tri_x[q, 5]
    cx, cy, cz = tri_x[q, 6], tri_x[q, 7], tri_x[q, 8]
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az, 2
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz, 2
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return ax + v * abx, ay + v * aby, az + v * abz, 1
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz, 2
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return ax + w * acx, ay + w * acy, az + w * acz, 1
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz), 1
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return (
        ax + abx * v + acx * w,
        ay + aby * v + acy * w,
        az + abz * v + acz * w,
        0,
    )


@njit(cache=True, inline="always")
def _axis_images(p, t0, t1, t2, length, periodic):
    """The two images ``p + k L`` (k in -1, 0, 1) of a coordinate nearest to the interval
    spanned by a triangle's coordinates t0, t1, t2 along one axis: (shift, gap) of the nearest
    and of the second nearest (gap ``inf`` along a closed axis, where only ``p`` exists)."""
    lo = min(t0, t1, t2)
    hi = max(t0, t1, t2)
    if not periodic:
        return 0.0, 0.0, 0.0, math.inf
    s0 = s1 = 0.0
    g0 = g1 = math.inf
    for k in range(-1, 2):
        q = p + k * length
        g = max(lo - q, q - hi, 0.0)
        if g < g0:
            s1, g1 = s0, g0
            s0, g0 = k * length, g
        elif g < g1:
            s1, g1 = k * length, g
    return s0, g0, s1, g1


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
    cx, cy, cz, feat = closest_point_triangle(qx, qy, qz, tri_x, tq)
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
    sx0, gx0, sx1, gx1 = _axis_images(px, ax, tri_x[tq, 3], tri_x[tq, 6], dom[6], per[0] != 0)
    sy0, gy0, sy1, gy1 = _axis_images(py, ay, tri_x[tq, 4], tri_x[tq, 7], dom[7], per[1] != 0)
    sz0, gz0, sz1, gz1 = _axis_images(pz, az, tri_x[tq, 5], tri_x[tq, 8], dom[8], per[2] != 0)
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
    cx, cy, cz, _ = closest_point_triangle(px, py, pz, tri_x, q)
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


@njit(cache=True, inline="always")
def _closest_contacts(i, P, nt, tri_nb, tri_x, tri_mesh, mesh_par, thist, tri_tmp, tid, dom, per,
                      t):  # fmt: skip
    """First sweep over the candidate triangles of particle i: closest point (cx, cy, cz),
    distance and feature of each triangle of an active mesh that the sphere overlaps, stored in
    ``tri_tmp[tid, k]`` (the calling thread's scratch rows, (ktri, 8); feature -1: no contact,
    its history cleared). Returns the contact count."""
    x, y, z = P[i, 0], P[i, 1], P[i, 2]
    ri = P[i, 9]
    reach2 = ri * ri * (1.0 + 1e-9)  # a margin: the exact test is on the distance below
    ncont = 0
    for k in range(nt):
        q = np.uint64(tri_nb[i, k])  # unsigned: no wraparound code (space, "Indexing")
        mesh = np.uint64(tri_mesh[q])
        tri_tmp[tid, k, 4] = -1.0
        if not (mesh_par[mesh, 13] <= t < mesh_par[mesh, 14]):
            clear_history(thist, i, k)
            continue
        qx, qy, qz, cpx, cpy, cpz, feat, d2 = nearest_image_contact(
            x, y, z, tri_x, q, dom, per, reach2
        )
        if d2 == math.inf:
            clear_history(thist, i, k)
            continue
        ddx, ddy, ddz = cpx - qx, cpy - qy, cpz - qz
        dist = math.sqrt(ddx * ddx + ddy * ddy + ddz * ddz)
        if dist >= ri or dist == 0.0:
            clear_history(thist, i, k)
            continue
        tri_tmp[tid, k, 0] = cpx
        tri_tmp[tid, k, 1] = cpy
        tri_tmp[tid, k, 2] = cpz
        tri_tmp[tid, k, 3] = dist
        tri_tmp[tid, k, 4] = feat
        tri_tmp[tid, k, 5] = ddx / dist
        tri_tmp[tid, k, 6] = ddy / dist
        tri_tmp[tid, k, 7] = ddz / dist
        ncont += 1
    return ncont


@njit(cache=True, inline="always")
def _shadowing_contact(i, k, nt, tol, tri_tmp, tid, tri_nb, tri_x):
    """The accepted contact (``tri_tmp`` feature 10 + f) that shadows the edge/vertex contact k
    of particle i: same contact point within ``tol``, or k's contact point lies on a triangle
    with an accepted face contact. Returns its slot, or -1."""
    cpx, cpy, cpz = tri_tmp[tid, k, 0], tri_tmp[tid, k, 1], tri_tmp[tid, k, 2]
    for k2 in range(nt):
        f2 = tri_tmp[tid, k2, 4]
        if f2 < 10.0:  # not (yet) accepted
            continue
        ddx = cpx - tri_tmp[tid, k2, 0]
        ddy = cpy - tri_tmp[tid, k2, 1]
        ddz = cpz - tri_tmp[tid, k2, 2]
        if ddx * ddx + ddy * ddy + ddz * ddz < tol * tol:
            return k2
        if f2 == 10.0:
            if dist_point_tri(cpx, cpy, cpz, tri_x, np.uint64(tri_nb[i, k2])) < tol:
                return k2
    return -1


@njit(cache=True, inline="always")
def _wall_motion(mesh_par, mesh, t, cpx, cpy, cpz):
    """Velocity of mesh ``mesh`` at the contact point c at time t and its angular velocity:
    ``omega u x (c - a)`` and ``omega u`` for a rotation, the translation velocity otherwise."""
    _, kind, _, om, _, _, _, tvx, tvy, tvz = mesh_state(mesh_par, mesh, t)
    vwx, vwy, vwz = tvx, tvy, tvz
    wwx = wwy = wwz = 0.0
    if kind == 1 and om != 0.0:
        ux, uy, uz = mesh_par[mesh, 4], mesh_par[mesh, 5], mesh_par[mesh, 6]
        rx = cpx - mesh_par[mesh, 1]
        ry = cpy - mesh_par[mesh, 2]
        rz = cpz - mesh_par[mesh, 3]
        vwx = om * (uy * rz - uz * ry)
        vwy = om * (uz * rx - ux * rz)
        vwz = om * (ux * ry - uy * rx)
        wwx, wwy, wwz = om * ux, om * uy, om * uz
    return vwx, vwy, vwz, wwx, wwy, wwz


@njit(cache=True, inline="always")
def _add_triangle_contact(i, k, P, IA, tri_tmp, tid, tri_nb, tri_x, tri_mesh, mesh_par, thist, pt,
                          dom, per, dt, t, fx, fy, fz, tx, ty, tz):  # fmt: skip
    """Add to particle i's force and torque (fx .. tz) its accepted contact with candidate
    triangle k (contact point and distance from ``tri_tmp``); updates the history
    ``thist[i, k]``. Returns the new (fx, fy, fz, tx, ty, tz)."""
    cpx, cpy, cpz = tri_tmp[tid, k, 0], tri_tmp[tid, k, 1], tri_tmp[tid, k, 2]
    q = np.uint64(tri_nb[i, k])
    mesh = np.uint64(tri_mesh[q])
    dist = tri_tmp[tid, k, 3]
    nx, ny, nz = tri_tmp[tid, k, 5], tri_tmp[tid, k, 6], tri_tmp[tid, k, 7]
    vwx, vwy, vwz, wwx, wwy, wwz = _wall_motion(mesh_par, mesh, t, cpx, cpy, cpz)
    return add_wall_contact(
        P, IA, i, nx, ny, nz, P[i, 9] - dist, vwx, vwy, vwz, wwx, wwy, wwz,
        int(mesh_par[mesh, 15]), pt, thist, k, dt, fx, fy, fz, tx, ty, tz,
    )  # fmt: skip


@njit(cache=True, inline="always")
def add_mesh_contacts(
    i, P, IA, ntri, tri_nb, thist, tri_tmp, tid, tri_x, tri_mesh, mesh_par, pt, dom, per, dt, t,
    fx, fy, fz, tx, ty, tz,
):  # fmt: skip
    """Add to particle i's force and torque (fx .. tz) its mesh contacts (module docstring):
    faces first, then edges, then vertices, each dropped when shadowed (it then copies the
    shadowing contact's history). ``tri_tmp[tid]`` (ktri, 8): the calling thread's scratch rows
    (a few cache lines that stay in L1, where one row block per particle did not), indexed in
    place: a view of them made for every particle cost ~5 ns (a reference count) each. Returns
    the new (fx, fy, fz, tx, ty, tz)."""
    nt = ntri[i]
    if nt == 0:
        return fx, fy, fz, tx, ty, tz
    if _closest_contacts(i, P, nt, tri_nb, tri_x, tri_mesh, mesh_par, thist, tri_tmp, tid, dom,
                         per, t) == 0:  # fmt: skip
        return fx, fy, fz, tx, ty, tz
    tol = 1e-7 * P[i, 9]
    # faces first (feature 0), then edges (1), then vertices (2)
    for feat_pass in range(3):
        for k in range(nt):
            if tri_tmp[tid, k, 4] != feat_pass:
                continue
            shadow = -1
            if feat_pass > 0:
                shadow = _shadowing_contact(i, k, nt, tol, tri_tmp, tid, tri_nb, tri_x)
            if shadow >= 0:
                thist[i, k, 0] = thist[i, shadow, 0]
                thist[i, k, 1] = thist[i, shadow, 1]
                thist[i, k, 2] = thist[i, shadow, 2]
                tri_tmp[tid, k, 4] = -1.0
                continue
            tri_tmp[tid, k, 4] = 10.0 + feat_pass
            fx, fy, fz, tx, ty, tz = _add_triangle_contact(
                i, k, P, IA, tri_tmp, tid, tri_nb, tri_x, tri_mesh, mesh_par, thist, pt, dom, per,
                dt, t, fx, fy, fz, tx, ty, tz,
            )  # fmt: skip
    return fx, fy, fz, tx, ty, tz
