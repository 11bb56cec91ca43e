"""An independent particle simulator for the compartment-model tests: a conveyed layer over a
bed that barely moves, in a periodic section (not DEM, not a compartment network).

* Conveyed particles (z above the bed): axial drift ``u`` with dispersion ``d_axial``, a
  random walk across the section (``d_cross``), reflected at the walls and at the bed top.
* Bed particles sit at anchors and rattle about them (an Ornstein-Uhlenbeck jitter of
  ``jitter_m`` with correlation time ``jitter_tau_s``), so those near the bed top cross the
  cell face above them many times a second without going anywhere: the situation of the
  seed-size blender's bottom layer.
* Real exchange: at rate ``exchange_per_s`` per bed particle a bed particle and a conveyed
  particle swap roles (the conveyed one settles into the bed where it is).

Outputs what a DEM run gives the compartment model: grid fields with face crossings counted
every step, frames every ``frame_s`` and every particle's transit times (successive first
passages of new multiples of the section length, recorded every step).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin_core.compartment.fields import GridFields


@dataclass(frozen=True)
class LayerWalk:
    fields: GridFields
    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    transit_s: np.ndarray
    window_s: float


def simulate_layer_walk(
    seed: int = 0,
    n: int = 2400,
    bed_fraction: float = 1 / 3,
    u: float = 0.03,
    d_axial: float = 1e-5,
    d_cross: float = 3e-4,
    jitter_m: float = 5e-4,
    jitter_tau_s: float = 0.005,
    exchange_per_s: float = 0.05,
    duration_s: float = 20.0,
    dt: float = 0.004,
    frame_s: float = 0.1,
) -> LayerWalk:
    rng = np.random.default_rng(seed)
    L, H, h, zb = 0.04, 0.024, 0.004, 0.008
    edges = (np.linspace(0, L, 11), np.linspace(0, H, 7), np.linspace(0, H, 7))
    shape = (10, 6, 6)
    bed = np.zeros(n, dtype=bool)
    bed[: int(round(bed_fraction * n))] = True
    xu = rng.uniform(0, L, n)  # unwrapped axial coordinate (of the anchor for bed particles)
    y = rng.uniform(0, H, n)
    z = np.where(bed, rng.uniform(0, zb, n), rng.uniform(zb, H, n))
    jit = rng.normal(0, jitter_m, (n, 3))
    rho = np.exp(-dt / jitter_tau_s)

    def pos() -> np.ndarray:
        p = np.stack([xu, y, z], axis=1)
        p[bed] += jit[bed]
        p[:, 1] = np.clip(p[:, 1], 0, H - 1e-9)
        p[:, 2] = np.clip(p[:, 2], 0, H - 1e-9)
        return p

    def cells(p: np.ndarray) -> np.ndarray:
        i = np.floor(np.mod(p[:, 0], L) / h).astype(int) % 10
        j = np.minimum((p[:, 1] / h).astype(int), 5)
        k = np.minimum((p[:, 2] / h).astype(int), 5)
        return np.stack([i, j, k], axis=1)

    steps = int(round(duration_s / dt))
    every = int(round(frame_s / dt))
    cross = [np.zeros((*shape, 2)) for _ in range(3)]
    occ = np.zeros(shape)
    vel = np.zeros((*shape, 3))
    p = pos()
    c = cells(p)
    best = np.floor(p[:, 0] / L)
    last = np.full(n, np.nan)
    transits: list[np.ndarray] = []
    times, frames_p, frames_v = [], [], []
    for s in range(1, steps + 1):
        t = s * dt
        # roles swap (exchange between bed and conveyed layer)
        nb = int(rng.poisson(exchange_per_s * dt * bed.sum()))
        if nb:
            b = rng.choice(np.flatnonzero(bed), nb, replace=False)
            cv = rng.choice(np.flatnonzero(~bed), nb, replace=False)
            xu[b] += jit[b, 0]
            z[b] = zb + rng.uniform(0, 0.002, nb)
            bed[b] = False
            z[cv] = rng.uniform(0, zb, nb)
            jit[cv] = 0.0
            bed[cv] = True
        m = ~bed
        xu[m] += u * dt + np.sqrt(2 * d_axial * dt) * rng.standard_normal(m.sum())
        y[m] += np.sqrt(2 * d_cross * dt) * rng.standard_normal(m.sum())
        z[m] += np.sqrt(2 * d_cross * dt) * rng.standard_normal(m.sum())
        y[m] = np.abs(y[m])
        y[m] = np.where(y[m] > H, 2 * H - y[m], y[m])
        z[m] = np.where(z[m] < zb, 2 * zb - z[m], z[m])
        z[m] = np.where(z[m] > H, 2 * H - z[m], z[m])
        jit = rho * jit + np.sqrt(1 - rho**2) * jitter_m * rng.standard_normal((n, 3))
        p_new = pos()
        c_new = cells(p_new)
        # face crossings along x, then y, then z (unit moves; x periodic)
        cur = c.copy()
        for a in range(3):
            d = c_new[:, a] - cur[:, a]
            if a == 0:
                d = (d + 5) % 10 - 5
            for sign in (1, -1):
                while True:
                    mv = np.flatnonzero(np.sign(d) == sign)
                    if mv.size == 0:
                        break
                    if sign == 1:
                        np.add.at(cross[a], (cur[mv, 0], cur[mv, 1], cur[mv, 2], 0), 1)
                    else:
                        nxt = cur[mv].copy()
                        nxt[:, a] = (nxt[:, a] - 1) % 10 if a == 0 else nxt[:, a] - 1
                        np.add.at(cross[a], (nxt[:, 0], nxt[:, 1], nxt[:, 2], 1), 1)
                    cur[mv, a] = (cur[mv, a] + sign) % 10 if a == 0 else cur[mv, a] + sign
                    d[mv] -= sign
        v_inst = (p_new - p) / dt
        v_inst[:, 0] = (p_new[:, 0] - p[:, 0]) / dt
        np.add.at(occ, (c_new[:, 0], c_new[:, 1], c_new[:, 2]), 1)
        np.add.at(vel, (c_new[:, 0], c_new[:, 1], c_new[:, 2]), v_inst)
        p, c = p_new, c_new
        level = np.floor(p[:, 0] / L)
        up = level > best
        if up.any():
            i = np.flatnonzero(up)
            ok = np.isfinite(last[i])
            transits.append(t - last[i][ok])
            last[i] = t
            best[i] = level[i]
        if s % every == 0:
            times.append(t)
            q = p.copy()
            q[:, 0] = np.mod(q[:, 0], L)
            frames_p.append(q)
            v = np.zeros((n, 3))
            v[~bed, 0] = u
            frames_v.append(v)
    occ_mean = occ / steps
    velocity = np.where(occ[..., None] > 0, vel / np.maximum(occ[..., None], 1), 0.0)
    vp = 4 / 3 * np.pi * 1e-3**3
    fields = GridFields(
        x_edges=edges[0],
        y_edges=edges[1],
        z_edges=edges[2],
        velocity=velocity,
        solid_fraction=occ_mean * vp / h**3,
        occupancy=occ_mean,
        duration_s=duration_s,
        particle_mass_kg=vp * 1500.0,
        periodic=(True, False, False),
        crossings=(cross[0], cross[1], cross[2]),
    )
    return LayerWalk(
        fields=fields,
        times=np.asarray(times),
        positions=np.asarray(frames_p),
        velocities=np.asarray(frames_v),
        transit_s=np.concatenate(transits) if transits else np.zeros(0),
        window_s=duration_s,
    )
