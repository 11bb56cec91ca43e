"""Time integration of the DEM engine (jax-md's ``simulate``; LIGGGHTS' ``fix nve/sphere``):
velocity Verlet for translation and rotation, with the force evaluation of each step.

One step (spheres: no gyroscopic term)::

    v += F/m dt/2;  w += T/I dt/2;  x += v dt      (kick_drift; periodic wrap)
    F, T = pairs + walls + meshes + m g at x(t + dt), half-step velocities
    v += F/m dt/2;  w += T/I dt/2                  (gather_pass)

After each drift the Verlet skin criterion (:func:`twin_core.dem.partition.rebuild_due`)
decides whether the lists are rebuilt before the forces (LIGGGHTS' order: ``fix nve``'s initial
integrate, then the neighbour check); the drift measures the largest displacement since the last
build with the positions it writes, and how far a particle went past a closed wall; particles
out of the domain or in a sink are flagged (:func:`flag_removals`) and the rebuild removes them.
The pair forces come from one of the two schemes of :mod:`twin_core.dem.pairs` (the chunked
scatter, default, or the two-pass scheme; the same sums for any thread count).

References: Verlet (1967), Phys. Rev. 159, 98; Swope, Andersen, Berens & Wilson (1982),
J. Chem. Phys. 76, 637 (velocity form); Allen & Tildesley, Computer Simulation of Liquids
(2nd ed. 2017), Sec. 3.2 and 3.3 (rigid-body rotation).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .mesh_contacts import add_mesh_sums, flatten_triangles, mesh_pass
from .meshes import update_mesh
from .pairs import chunk_sums, flatten_pairs, gather_pair_slots, pair_pass, pair_scatter
from .partition import rebuild, rebuild_due
from .space import FMA, min_image
from .walls import add_cylinder_contacts, add_plane_contacts

__all__ = ["advance", "compute_forces", "flag_removals", "gather_pass", "kick_drift"]


@njit(cache=True, inline="always")
def _kick_drift_axis(P, F, i, a, invm, inv_i, hdt, dt, dom, per):
    """Axis a of particle i: ``v += F/m dt/2; w += T/I dt/2; x += v dt``, x wrapped along a
    periodic axis; returns the new x."""
    P[i, 3 + a] += F[i, a] * invm * hdt
    P[i, 6 + a] += F[i, 3 + a] * inv_i * hdt
    x = P[i, a] + P[i, 3 + a] * dt
    if per[a] != 0:
        if x < dom[a]:
            x += dom[6 + a]
        elif x >= dom[3 + a]:
            x -= dom[6 + a]
    P[i, a] = x
    return x


@njit(cache=True, inline="always")
def _closed_bounds(dom, per):
    """Domain bounds (lo0, lo1, lo2, hi0, hi1, hi2), -inf/+inf along a periodic axis: the
    bounds a particle can leave the domain through."""
    lo0 = dom[0] if per[0] == 0 else -np.inf
    lo1 = dom[1] if per[1] == 0 else -np.inf
    lo2 = dom[2] if per[2] == 0 else -np.inf
    hi0 = dom[3] if per[0] == 0 else np.inf
    hi1 = dom[4] if per[1] == 0 else np.inf
    hi2 = dom[5] if per[2] == 0 else np.inf
    return lo0, lo1, lo2, hi0, hi1, hi2


@njit(cache=True, parallel=True, fastmath=FMA)
def kick_drift(n, P, F, XB, dom, per, dt):
    """Velocity Verlet first half: ``v += F/m dt/2; w += T/I dt/2; x += v dt``; wrap periodic.

    With the positions it writes it measures, for the Verlet skin criterion (LIGGGHTS checks
    its lists after ``fix nve``'s initial integrate), the largest squared displacement since
    the last build (minimum image) ``max_i |x_i - xb_i|^2``, and the largest excursion past a
    closed wall ``max_i max_a (lo_a - x_ia, x_ia - hi_a)`` (> 0 when a particle has left the
    domain: :func:`flag_removals` then finds it). Both are reductions of the parallel loop: no
    per-particle array, no branch for the checks. Returns (dmax2, excursion)."""
    hdt = 0.5 * dt
    lo0, lo1, lo2, hi0, hi1, hi2 = _closed_bounds(dom, per)
    dmax2 = 0.0
    excursion = -np.inf
    for i in prange(n):
        invm = P[i, 11]
        inv_i = P[i, 12]
        x0 = _kick_drift_axis(P, F, i, 0, invm, inv_i, hdt, dt, dom, per)
        x1 = _kick_drift_axis(P, F, i, 1, invm, inv_i, hdt, dt, dom, per)
        x2 = _kick_drift_axis(P, F, i, 2, invm, inv_i, hdt, dt, dom, per)
        d0 = min_image(x0 - XB[i, 0], dom[6], per[0] != 0)
        d1 = min_image(x1 - XB[i, 1], dom[7], per[1] != 0)
        d2 = min_image(x2 - XB[i, 2], dom[8], per[2] != 0)
        dmax2 = max(dmax2, d0 * d0 + d1 * d1 + d2 * d2)
        out = max(max(lo0 - x0, x0 - hi0), max(lo1 - x1, x1 - hi1), max(lo2 - x2, x2 - hi2))
        excursion = max(excursion, out)
    return dmax2, excursion


@njit(cache=True, parallel=True)
def flag_removals(n, P, rm, dom, per, sinks):
    """Removal code of each particle not yet flagged: 2 when it lies outside the domain along a
    closed axis, 3 + s when it lies in sink s (axis-aligned box ``sinks[s]``: lo (3), hi (3)).
    Returns the number of particles flagged (old and new). It runs every step in a scene with
    sinks (the feeder's 150,000 particles): a parallel loop, each particle writing its own
    flag."""
    lo0, lo1, lo2, hi0, hi1, hi2 = _closed_bounds(dom, per)
    flagged = 0
    for i in prange(n):
        x0, x1, x2 = P[i, 0], P[i, 1], P[i, 2]
        if rm[i] == 0:
            if x0 < lo0 or x0 > hi0 or x1 < lo1 or x1 > hi1 or x2 < lo2 or x2 > hi2:
                rm[i] = 2
            else:
                for s in range(sinks.shape[0]):
                    if (
                        sinks[s, 0] <= x0 <= sinks[s, 3]
                        and sinks[s, 1] <= x1 <= sinks[s, 4]
                        and sinks[s, 2] <= x2 <= sinks[s, 5]
                    ):
                        rm[i] = 3 + s
                        break
        flagged += rm[i] != 0
    return flagged


@njit(cache=True, inline="always")
def _store_and_kick(i, P, F, grav, dt, fx, fy, fz, tx, ty, tz):
    """Add gravity ``m g`` to particle i's force, store force and torque in ``F[i]`` and apply
    the second half kick ``v += F/m dt/2; w += T/I dt/2``."""
    hdt = 0.5 * dt
    m = P[i, 10]
    fx += m * grav[0]
    fy += m * grav[1]
    fz += m * grav[2]
    F[i, 0] = fx
    F[i, 1] = fy
    F[i, 2] = fz
    F[i, 3] = tx
    F[i, 4] = ty
    F[i, 5] = tz
    invm = P[i, 11]
    inv_i = P[i, 12]
    P[i, 3] += fx * invm * hdt
    P[i, 4] += fy * invm * hdt
    P[i, 5] += fz * invm * hdt
    P[i, 6] += tx * inv_i * hdt
    P[i, 7] += ty * inv_i * hdt
    P[i, 8] += tz * inv_i * hdt


@njit(cache=True, parallel=True, fastmath=FMA)
def gather_pass(
    n, P, F, IA, nown, pf, nrev, rev_o, rev_k, use_acc, acc, bounds,
    planes, cyls, whist, mint, mflt, mcnt,
    pt, dom, per, grav, dt, t,
):  # fmt: skip
    """Pass 2: total force/torque on each particle (pairs, planes, cylinders, meshes, gravity,
    summed in that order); half kick. The mesh contacts' forces come from
    :func:`twin_core.dem.mesh_contacts.mesh_pass` (``mint``, ``mflt``, ``mcnt``).

    Pair sums: with ``use_acc`` they are added from the chunk buffers ``acc`` (filled by
    :func:`twin_core.dem.pairs.pair_scatter`, chunk order); otherwise they are gathered from
    the slots ``pf`` of :func:`twin_core.dem.pairs.pair_pass` in the one-chunk scatter's order
    (bit-identical sums). Every particle writes only its own rows.
    """
    npl = planes.shape[0]
    for i in prange(n):
        if use_acc:
            fx, fy, fz, tx, ty, tz = chunk_sums(i, F, acc, bounds)
        else:
            fx, fy, fz, tx, ty, tz = gather_pair_slots(i, pf, nrev, rev_o, rev_k, nown)
        fx, fy, fz, tx, ty, tz = add_plane_contacts(
            i, P, IA, planes, whist, pt, dt, t, fx, fy, fz, tx, ty, tz
        )
        fx, fy, fz, tx, ty, tz = add_cylinder_contacts(
            i, P, IA, cyls, npl, whist, pt, dt, t, fx, fy, fz, tx, ty, tz
        )
        fx, fy, fz, tx, ty, tz = add_mesh_sums(i, mint, mflt, mcnt, fx, fy, fz, tx, ty, tz)
        _store_and_kick(i, P, F, grav, dt, fx, fy, fz, tx, ty, tz)


@njit(cache=True)
def _forces_and_kick(
    n, P, F, IA, whist, nb_b, hist_b, nown_b, rev_o, rev_k, nrev, pstart, nbf, live, clist,
    work, pf, acc, bounds, c,
    thist_b, tri_x, tri_mesh, mesh_par, mint, mflt, mcnt, mwork,
    planes, cyls, pt, dom, per, grav, dt, t, serial,
):  # fmt: skip
    """Forces at time t on the live lists ``c`` and the second half kick: the pair forces by the
    chunked scatter (``serial``) or pass 1, the mesh contacts
    (:func:`twin_core.dem.mesh_contacts.mesh_pass`), then pass 2 (:func:`gather_pass`)."""
    if serial:
        pair_scatter(
            n, P, IA, nbf, pstart, nown_b[c], hist_b[c], live, clist, work, F, acc, bounds, pt,
            dom, per, dt,
        )  # fmt: skip
    else:
        pair_pass(
            n, P, IA, nbf, pstart, nown_b[c], hist_b[c], live, clist, work, pf, bounds, pt, dom,
            per, dt,
        )  # fmt: skip
    if tri_x.shape[0] > 0:
        mesh_pass(
            n, P, IA, thist_b[c], tri_x, tri_mesh, mesh_par, pt, dom, per, dt, t, mint, mflt,
            mcnt, mwork,
        )  # fmt: skip
    gather_pass(
        n, P, F, IA, nown_b[c], pf, nrev, rev_o, rev_k, serial, acc, bounds,
        planes, cyls, whist, mint, mflt, mcnt,
        pt, dom, per, grav, dt, t,
    )  # fmt: skip


@njit(cache=True)
def advance(
    nsteps, step0, dt, n, P, F, IA, XB, rm, whist,
    nb_b, hist_b, nown_b, rev_o, rev_k, nrev, pstart, nbf, live, clist, work, pf, acc, bounds,
    cur, tri_nb_b, thist_b, ntri_b, mint, mflt, mcnt, mwork, tri_x0, tri_x, tri_xb, tri_mesh,
    mesh_par, any_moving,
    planes, cyls, sinks, pt, dom, per, grav, skin, rmax, removed, counters, serial,
):  # fmt: skip
    """Advance up to ``nsteps`` velocity-Verlet steps.

    Each step (LIGGGHTS' order): (1) half kick + drift, which also measures the largest
    displacement since the last build and the largest excursion past a closed wall; the
    particles out of the domain or in a sink flagged (only when one went past a wall or there
    are sinks); (2) move the meshes; (3) rebuild the lists if the skin criterion asks for it
    (:func:`twin_core.dem.partition.rebuild_due`), removing the flagged particles; (4) pass 1
    and pass 2 forces + half kick (``serial``: :func:`twin_core.dem.pairs.pair_scatter`,
    chunked, instead of pass 1). Returns (status, steps_done, n); status != 0 means a list must
    be enlarged (``counters[2]`` holds the needed size) before calling again: that step's drift
    is then done (``counters[3]`` = 1) and the next call goes on from its rebuild.
    """
    meshes_move = any_moving and tri_x.shape[0] > 0
    c = cur[0]
    flatten_pairs(n, nb_b[c], nown_b[c], hist_b[c], pstart, nbf, live)
    flatten_triangles(n, ntri_b[c], tri_nb_b[c], thist_b[c], mcnt, mint)
    for s in range(nsteps):
        t_new = (step0 + s + 1) * dt
        drifted = counters[3] != 0
        due = drifted
        if not drifted:
            dmax2, excursion = kick_drift(n, P, F, XB, dom, per, dt)
            flagged = 0
            if excursion > 0.0 or sinks.shape[0] > 0:
                flagged = flag_removals(n, P, rm, dom, per, sinks)
            if meshes_move:
                update_mesh(tri_x0, tri_x, tri_mesh, mesh_par, t_new)
            due = rebuild_due(dmax2, flagged, counters, skin, meshes_move, tri_x, tri_xb)
        if due:
            status, n_new, needed = rebuild(
                n, P, F, IA, XB, rm, whist,
                nb_b, hist_b, nown_b, rev_o, rev_k, nrev, cur,
                tri_nb_b, thist_b, ntri_b, tri_x, tri_xb,
                dom, per, skin, rmax, removed, not serial,
            )  # fmt: skip
            if status != 0:
                counters[2] = needed
                counters[3] = 1
                return status, s, n
            n = n_new
            c = cur[0]
            flatten_pairs(n, nb_b[c], nown_b[c], hist_b[c], pstart, nbf, live)
            flatten_triangles(n, ntri_b[c], tri_nb_b[c], thist_b[c], mcnt, mint)
            counters[0] = 0
            counters[1] += 1
            counters[3] = 0
        _forces_and_kick(
            n, P, F, IA, whist, nb_b, hist_b, nown_b, rev_o, rev_k, nrev, pstart, nbf, live,
            clist, work, pf, acc, bounds, cur[0],
            thist_b, tri_x, tri_mesh, mesh_par, mint, mflt, mcnt, mwork,
            planes, cyls, pt, dom, per, grav, dt, t_new, serial,
        )  # fmt: skip
    return 0, nsteps, n


@njit(cache=True)
def compute_forces(
    n, P, F, IA, whist, nb_b, hist_b, nown_b, rev_o, rev_k, nrev, pstart, nbf, live, clist,
    work, pf, acc, bounds, cur,
    tri_nb_b, thist_b, ntri_b, mint, mflt, mcnt, mwork, tri_x, tri_mesh, mesh_par,
    planes, cyls, pt, dom, per, grav, dt, t, serial,
):  # fmt: skip
    """Forces at the current state without moving (used once before the first step).

    The history increment of this evaluation is undone by restoring copies, and the half kick of
    pass 2 is undone, so the state is unchanged apart from ``F``."""
    c = cur[0]
    h = hist_b[c].copy()
    th = thist_b[c].copy()
    wh = whist.copy()
    v = P[:n, 3:9].copy()
    flatten_pairs(n, nb_b[c], nown_b[c], hist_b[c], pstart, nbf, live)
    flatten_triangles(n, ntri_b[c], tri_nb_b[c], thist_b[c], mcnt, mint)
    _forces_and_kick(
        n, P, F, IA, whist, nb_b, hist_b, nown_b, rev_o, rev_k, nrev, pstart, nbf, live, clist,
        work, pf, acc, bounds, c,
        thist_b, tri_x, tri_mesh, mesh_par, mint, mflt, mcnt, mwork,
        planes, cyls, pt, dom, per, grav, dt, t, serial,
    )  # fmt: skip
    hist_b[c][:] = h
    thist_b[c][:] = th
    whist[:] = wh
    P[:n, 3:9] = v
