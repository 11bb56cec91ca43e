"""Synthetic grid fields with exactly known, mass-conserving cell-face flows.

Used to develop and test the compartment model without DEM output.  The cross-section is
a partially filled drum (radius ``radius_m``, fill level ``fill``) periodic along x.  The
net cell-face mass flows are built so that their discrete divergence vanishes exactly:

* a y-z stream function per x-slice (radial circulation of the blades; its phase turns
  with x), discrete curl on the cell corners;
* an x-z stream function per y-plane (axial recirculation between slices);
* a through-flow per axial column, constant along x, positive near the bottom and
  negative near the free surface (backflow), summing to the throughput.

Stream functions vanish on every corner touching an empty cell, so walls carry no flow.
Gross crossings add an equal exchange flow ``D`` in both directions of every face between
two filled cells (dispersion), which leaves the net flows (and conservation) unchanged.
Discrete incompressibility: for every cell, sum of inflows = sum of outflows (to round-off).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin_core.compartment.fields import GridFields


@dataclass(frozen=True)
class SyntheticCase:
    """Synthetic fields plus their known truth.

    ``flows[axis]`` (nx,ny,nz,2) holds the exact mass flow (kg/s) through the + face of each
    cell along ``axis``: [...,0] in the + direction, [...,1] in the - direction (the layout
    of the ``crossings_*`` keys).  ``throughput_kg_s`` is the net flow through any x plane.
    """

    fields: GridFields
    flows: tuple[np.ndarray, np.ndarray, np.ndarray]
    mask: np.ndarray
    throughput_kg_s: float


def _corner_free(mask2: np.ndarray, periodic_first: bool) -> np.ndarray:
    """Corners (n0, n1+1) of a 2-D mask (n0, n1) that touch no empty/outside cell.

    Axis 0 of ``mask2`` is periodic (corner c lies between cells c and c+1 mod n0) when
    ``periodic_first``; otherwise it has n0+1 corners like axis 1.
    """
    n0, n1 = mask2.shape
    if periodic_first:
        a = np.pad(mask2, ((0, 0), (1, 1)), constant_values=False)
        b = np.roll(a, -1, axis=0)
        ok = a[:, :-1] & a[:, 1:] & b[:, :-1] & b[:, 1:]
        return ok
    a = np.pad(mask2, ((1, 1), (1, 1)), constant_values=False)
    return a[:-1, :-1] & a[1:, :-1] & a[:-1, 1:] & a[1:, 1:]


def synthetic_blender_fields(
    nx: int = 10,
    ny: int = 20,
    nz: int = 20,
    length_m: float = 0.04,
    radius_m: float = 0.04,
    fill: float = 0.6,
    solid_fraction: float = 0.55,
    particle_radius_m: float = 1e-3,
    particle_density: float = 1500.0,
    mean_residence_s: float = 4.0,
    circulation: float = 20.0,
    recirculation: float = 1.0,
    backflow: float = 1.5,
    exchange: float = 1.0,
    duration_s: float = 20.0,
    counts: str = "expected",
    seed: int | np.random.Generator | None = None,
) -> SyntheticCase:
    """Build a periodic blender section with known flows (see module docstring).

    Flow magnitudes are relative to the mean axial through-flow per filled column
    ``q = Q / n_columns`` where ``Q = holdup / mean_residence_s``: the y-z stream function has
    amplitude ``circulation * q``, the x-z one ``recirculation * q``, the column through-flow
    is ``q (1 + backflow * cos(pi * s))`` renormalised to sum to Q (s = 0 at the bottom,
    1 at the top of the bed), and every internal face exchanges ``exchange * q`` each way.

    ``counts="expected"`` stores the expected crossing counts (flows x duration / particle
    mass, non-integer); ``"poisson"`` draws Poisson counts with ``seed`` (a DEM-like sample).
    """
    for name, val in (("nx", nx), ("ny", ny), ("nz", nz)):
        if val < 3:
            raise ValueError(f"{name} must be >= 3, got {val}")
    if not 0 < fill <= 1:
        raise ValueError(f"fill must be in (0, 1], got {fill}")
    if mean_residence_s <= 0:
        raise ValueError(f"mean_residence_s must be > 0, got {mean_residence_s}")
    if counts not in ("expected", "poisson"):
        raise ValueError(f"counts must be 'expected' or 'poisson', got {counts!r}")
    x_edges = np.linspace(0.0, length_m, nx + 1)
    y_edges = np.linspace(-radius_m, radius_m, ny + 1)
    z_edges = np.linspace(-radius_m, radius_m, nz + 1)
    yc = 0.5 * (y_edges[1:] + y_edges[:-1])
    zc = 0.5 * (z_edges[1:] + z_edges[:-1])
    z_top = -radius_m + 2.0 * radius_m * fill
    yy, zz = np.meshgrid(yc, zc, indexing="ij")
    mask2 = (yy**2 + zz**2 < radius_m**2) & (zz < z_top)
    mask = np.broadcast_to(mask2, (nx, ny, nz)).copy()

    vol = np.diff(x_edges)[:, None, None] * np.diff(y_edges)[None, :, None]
    vol = vol * np.diff(z_edges)[None, None, :]
    pmass = particle_density * 4.0 / 3.0 * np.pi * particle_radius_m**3
    holdup = np.where(mask, solid_fraction * particle_density * vol, 0.0)
    Q = float(holdup.sum()) / mean_residence_s
    n_col = int(mask2.sum())
    q = Q / n_col

    fx = np.zeros((nx, ny, nz))
    fy = np.zeros((nx, ny, nz))
    fz = np.zeros((nx, ny, nz))

    # y-z stream function per slice, corners (ny+1, nz+1)
    ok_yz = _corner_free(mask2, periodic_first=False)
    yk = np.linspace(-radius_m, radius_m, ny + 1)
    zk = np.linspace(-radius_m, radius_m, nz + 1)
    yyk, zzk = np.meshgrid(yk, zk, indexing="ij")
    zb = np.clip((zzk + radius_m) / max(z_top + radius_m, 1e-12), 0.0, 1.0)
    for i in range(nx):
        theta = 2.0 * np.pi * i / nx
        psi = circulation * q * np.sin(np.pi * (yyk + radius_m) / radius_m + theta)
        psi = psi * np.sin(np.pi * zb) * ok_yz
        fy[i] += psi[1:, 1:] - psi[1:, :-1]
        fz[i] -= psi[1:, 1:] - psi[:-1, 1:]

    # x-z stream function per y-plane, corners (nx periodic, nz+1)
    xk = x_edges[1:]
    for j in range(ny):
        ok_xz = _corner_free(mask[:, j, :], periodic_first=True)
        xxk, zzj = np.meshgrid(xk, zk, indexing="ij")
        zbj = np.clip((zzj + radius_m) / max(z_top + radius_m, 1e-12), 0.0, 1.0)
        phi = recirculation * q * np.sin(2.0 * np.pi * xxk / length_m) * np.sin(np.pi * zbj)
        phi = phi * np.cos(0.5 * np.pi * yc[j] / radius_m) * ok_xz
        fx[:, j, :] += phi[:, 1:] - phi[:, :-1]
        fz[:, j, :] -= phi[:, 1:] - np.roll(phi, 1, axis=0)[:, 1:]

    # through-flow per column, constant along x
    zmin = np.array([zc[mask2[j]].min() if mask2[j].any() else 0.0 for j in range(ny)])
    zmax = np.array([zc[mask2[j]].max() if mask2[j].any() else 0.0 for j in range(ny)])
    span = np.maximum(zmax - zmin, 1e-12)[:, None]
    s = np.clip((zz - zmin[:, None]) / span, 0.0, 1.0)
    w = np.where(mask2, 1.0 + backflow * np.cos(np.pi * s), 0.0)
    col = Q * w / w.sum()
    fx += col[None, :, :]

    # gross flows: net split by sign plus symmetric exchange on filled-filled faces
    flows = []
    nbr_ok = [
        mask & np.roll(mask, -1, axis=0),
        mask & np.pad(mask[:, 1:, :], ((0, 0), (0, 1), (0, 0))),
        mask & np.pad(mask[:, :, 1:], ((0, 0), (0, 0), (0, 1))),
    ]
    for net, ok in zip((fx, fy, fz), nbr_ok):
        net = np.where(ok, net, 0.0)
        d = exchange * q * ok
        flows.append(np.stack([np.maximum(net, 0.0) + d, np.maximum(-net, 0.0) + d], axis=-1))

    # cell velocities from the net face fluxes (mean of the two faces / (rho_bulk A))
    rho = np.divide(holdup, vol, out=np.zeros_like(holdup), where=mask)
    dxw, dyw, dzw = np.diff(x_edges), np.diff(y_edges), np.diff(z_edges)
    area = [
        dyw[None, :, None] * dzw[None, None, :] * np.ones((nx, 1, 1)),
        dxw[:, None, None] * dzw[None, None, :] * np.ones((1, ny, 1)),
        dxw[:, None, None] * dyw[None, :, None] * np.ones((1, 1, nz)),
    ]
    vel = np.zeros((nx, ny, nz, 3))
    for axis in range(3):
        net = flows[axis][..., 0] - flows[axis][..., 1]
        if axis == 0:
            prev = np.roll(net, 1, axis=0)
        else:
            prev = np.roll(net, 1, axis=axis)
            idx = [slice(None)] * 3
            idx[axis] = 0
            prev[tuple(idx)] = 0.0
        mean_flux = 0.5 * (net + prev)
        vel[..., axis] = np.divide(
            mean_flux, rho * area[axis], out=np.zeros_like(mean_flux), where=mask
        )

    expected = [f * duration_s / pmass for f in flows]
    if counts == "poisson":
        rng = np.random.default_rng(seed)
        crossings = tuple(rng.poisson(e).astype(float) for e in expected)
    else:
        crossings = tuple(expected)
    sf = np.where(mask, solid_fraction, 0.0)
    fields = GridFields(
        x_edges=x_edges,
        y_edges=y_edges,
        z_edges=z_edges,
        velocity=vel,
        solid_fraction=sf,
        occupancy=holdup / pmass,
        duration_s=float(duration_s),
        particle_mass_kg=float(pmass),
        periodic=(True, False, False),
        crossings=crossings,  # type: ignore[arg-type]
    )
    return SyntheticCase(
        fields=fields,
        flows=(flows[0], flows[1], flows[2]),
        mask=mask,
        throughput_kg_s=Q,
    )


def cell_divergence(flows: tuple[np.ndarray, np.ndarray, np.ndarray], periodic) -> np.ndarray:
    """Net outflow (kg/s) of every cell from gross face flows in the crossings layout.

    outflow = sum over axes of [F+(own + face) + F-(own - face)] minus the inflows
    [F-(own + face) + F+(neighbour - face)].  Zero everywhere for a conserving field.
    """
    div = np.zeros(flows[0].shape[:3])
    for axis in range(3):
        fp, fm = flows[axis][..., 0], flows[axis][..., 1]
        fp_prev = np.roll(fp, 1, axis=axis)
        fm_prev = np.roll(fm, 1, axis=axis)
        if not periodic[axis]:
            idx = [slice(None)] * 3
            idx[axis] = 0
            fp_prev[tuple(idx)] = 0.0
            fm_prev[tuple(idx)] = 0.0
        div += fp + fm_prev - fm - fp_prev
    return div
