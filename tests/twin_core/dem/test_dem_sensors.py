"""Sensors on synthetic trajectories with analytic answers (no DEM engine needed)."""

from __future__ import annotations

import numpy as np
import pytest

from twin_core.dem.sensors import (
    BoxFlowSensor,
    ContactSensor,
    EnergySensor,
    GridFieldSensor,
    PeriodicTransitSensor,
    PlaneFlowSensor,
    ResidenceTimeSensor,
    State,
    contacts_by_type,
    particle_masses,
)

R = 1e-3
RHO = 1500.0
M = 4 / 3 * np.pi * R**3 * RHO


def _state(t, pos, vel=None, ids=None, types=None, omega=None):
    pos = np.atleast_2d(np.asarray(pos, float))
    n = len(pos)
    return State(
        t,
        np.arange(n) if ids is None else np.asarray(ids),
        np.ones(n, int) if types is None else np.asarray(types),
        np.full(n, R),
        pos,
        np.zeros((n, 3)) if vel is None else np.atleast_2d(np.asarray(vel, float)),
        omega,
    )


def test_plane_crossing_times_and_flux():
    """Particles on a line x_i(t) = x0_i + v t cross x = 0 at t_i = -x0_i / v (analytic): the
    interpolated event times match and the binned rate equals n m v / spacing."""
    v, spacing = 0.2, 0.004
    x0 = -spacing * np.arange(100) - 0.0013
    types = 1 + (np.arange(100) % 2)
    s = PlaneFlowSensor([0, 0, 0], [1, 0, 0], RHO)
    for t in np.arange(0, 2.0001, 0.003):
        x = x0 + v * t
        s.update(_state(t, np.c_[x, np.zeros(100), np.zeros(100)], types=types))
    ev = s.events_
    assert len(ev["t"]) == 100 and np.all(ev["n"] == 1)
    np.testing.assert_allclose(np.sort(ev["t"]), np.sort(-x0 / v), atol=1e-9)
    tc, flow = s.flow(0.5, 0.0, 2.0)
    assert flow.shape == (4, 3)
    # full bins inside the stream: 0.5 s * v / spacing = 25 particles per bin
    np.testing.assert_allclose(flow[:3, 2], 25 * M / 0.5, rtol=1e-12)
    np.testing.assert_allclose(flow[:3, 0] + flow[:3, 1], flow[:3, 2])
    assert s.total_mass() == pytest.approx(100 * M)


def test_plane_reverse_window_and_periodic():
    """A particle going back counts -1; the window filters crossing points; a particle moving
    3.5 periods through a plane normal to a periodic axis crosses it 3 or 4 times (exact)."""
    s = PlaneFlowSensor([0, 0, 0], [0, 0, 1], RHO, window=([-0.01, -0.01, -1], [0.01, 0.01, 1]))
    s.update(_state(0.0, [[0, 0, 0.01], [0.05, 0, 0.01]]))
    s.update(_state(0.1, [[0, 0, -0.01], [0.05, 0, -0.01]]))
    s.update(_state(0.2, [[0, 0, 0.01], [0.05, 0, 0.01]]))
    assert list(s.events_["n"]) == [-1, 1]
    assert s.total_mass() == pytest.approx(0.0)
    L = 0.04
    p = PlaneFlowSensor([0.01, 0, 0], [1, 0, 0], RHO, periodic_lengths=[L, 0, 0])
    u = 0.1  # m/s; 3.5 periods in 1.4 s, start at x = 0
    for t in np.arange(0, 1.4001, 0.01):
        p.update(_state(t, [[np.mod(u * t, L), 0, 0]]))
    ev = p.events_
    expected = [0.1 + k * 0.4 for k in range(4)]  # (0.01 + k L) / u
    np.testing.assert_allclose(ev["t"], expected, atol=1e-9)


def test_box_entries_exits_and_content():
    """One particle passes through a box: one entry, one exit; content counts by type."""
    b = BoxFlowSensor([0, -1, -1], [1, 1, 1], RHO)
    for t in range(6):
        b.update(_state(float(t), [[-0.5 + 0.4 * t, 0, 0], [0.5, 0, 0]], types=[1, 2]))
    t, n, m = b.content_series()
    assert list(n) == [1, 1, 2, 2, 1, 1]
    _, n2, _ = b.content_series(type_id=2)
    assert list(n2) == [1] * 6
    tc, rin = b.inflow(1.0, 0.0, 6.0)
    tc, rout = b.outflow(1.0, 0.0, 6.0)
    assert rin.sum() == pytest.approx(M) and rout.sum() == pytest.approx(M)
    assert tc[np.argmax(rin)] == 1.5 and tc[np.argmax(rout)] == 3.5


def test_grid_field_uniform_translation_periodic():
    """Particles translating at v along a periodic x axis: velocity field = v where occupied,
    each particle crosses each x face once per period (x crossings = n_periods per face per
    particle), no y/z crossings, occupancy sums to N, solid fraction = N V_p / V_grid."""
    L, v = 0.04, 0.05
    ex = np.linspace(0, L, 11)
    ey = np.linspace(-0.01, 0.01, 5)
    ez = np.linspace(0, 0.02, 5)
    rng = np.random.default_rng(0)
    n = 30
    p0 = np.c_[rng.random(n) * L, rng.uniform(-0.009, 0.009, n), rng.uniform(0.001, 0.019, n)]
    g = GridFieldSensor(ex, ey, ez, RHO, periodic=(True, False, False))
    dt, T = 0.01, 1.6  # 2 periods, displacement 0.5 mm << 4 mm cell
    for t in np.arange(0, T + 1e-9, dt):
        pos = p0 + [v * t, 0, 0]
        pos[:, 0] = np.mod(pos[:, 0], L)
        g.update(_state(t, pos, vel=np.tile([v, 0, 0], (n, 1))))
    f = g.fields()
    occ = f["occupancy"] > 0
    np.testing.assert_allclose(f["velocity"][occ], np.tile([v, 0, 0], (occ.sum(), 1)))
    assert f["occupancy"].sum() == pytest.approx(n)
    total_sf = (f["solid_fraction"] * (np.diff(ex)[0] * 0.005 * 0.005)).sum()
    assert total_sf == pytest.approx(n * 4 / 3 * np.pi * R**3)
    cx = f["crossings_x"]
    assert cx[..., 1].sum() == 0 and f["crossings_y"].sum() == 0 and f["crossings_z"].sum() == 0
    # each particle crosses the 10 x-faces v T / (L/10) = 20 times in total
    assert cx[..., 0].sum() == n * 20
    assert f["duration_s"] == pytest.approx(T) and f["particle_mass_kg"] == pytest.approx(M)
    assert list(f["periodic"]) == [True, False, False]


def test_grid_crossings_conserve_particles():
    """Random walks in a closed/periodic grid: for every cell, (initial count) + inflow -
    outflow through its faces = final count (mass conservation of the crossing counts)."""
    rng = np.random.default_rng(5)
    ex, ey, ez = np.linspace(0, 1, 6), np.linspace(0, 1, 5), np.linspace(0, 1, 4)
    n = 200
    pos = rng.random((n, 3))
    g = GridFieldSensor(ex, ey, ez, RHO, periodic=(True, True, False))
    first = None
    for t in range(300):
        step = rng.normal(0, 0.03, (n, 3))
        pos = pos + step
        pos[:, 2] = np.clip(pos[:, 2], 1e-6, 1 - 1e-6)
        pos[:, :2] = np.mod(pos[:, :2], 1.0)
        g.update(_state(float(t), pos))
        if first is None:
            first = g.cell_index(pos)[0]
    last = g.cell_index(pos)[0]
    shape = g.shape
    c0 = np.zeros(shape)
    np.add.at(c0, tuple(first.T), 1)
    c1 = np.zeros(shape)
    np.add.at(c1, tuple(last.T), 1)
    net = np.zeros(shape)
    for ax, cr in enumerate(g.crossings):
        f = cr[..., 0] - cr[..., 1]  # net + flow through the + face of each cell
        net -= f
        net += (
            np.roll(f, 1, axis=ax)
            if g.periodic[ax]
            else np.concatenate(
                [np.zeros_like(f.take([0], axis=ax)), f.take(range(shape[ax] - 1), axis=ax)],
                axis=ax,
            )
        )
    np.testing.assert_array_equal(c0 + net, c1)
    assert g.crossings[2][:, :, -1].sum() == 0


def test_contacts_by_type_lattice():
    """Simple cubic lattice at spacing 1.98 r: 3 n^2 (n - 1) contacts (analytic); with a
    checkerboard of two types every contact is AB; with x periodic, n^2 more contacts wrap."""
    n = 5
    a = 1.98 * R
    ijk = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pos = (ijk + 0.5) * a
    types = 1 + ijk.sum(axis=1) % 2
    radii = np.full(len(pos), R)
    pairs, delta, C = contacts_by_type(pos, radii, types)
    assert len(pairs) == 3 * n * n * (n - 1)
    assert C[0, 0] == 0 and C[1, 1] == 0 and C[0, 1] == len(pairs)
    np.testing.assert_allclose(delta, 0.02 * R, rtol=1e-9)
    pairs_p, _, _ = contacts_by_type(
        pos, radii, types, box=([0, 0, 0], [n * a, 1, 1]), periodic=(True, False, False)
    )
    assert len(pairs_p) == 3 * n * n * (n - 1) + n * n
    s = ContactSensor()
    s.update(_state(0.0, pos, types=types))
    assert s.counts_[0] == {"AA": 0, "AB": len(pairs), "BB": 0}
    assert s.max_overlap_[0] == pytest.approx(0.02)


def test_residence_and_periodic_transit():
    """Constant velocity: residence time between planes a apart = a / v; transit time over a
    period L = L / v even with a superposed oscillation whose period divides L / v (the first
    passages shift by the same phase every period), backflow included."""
    v = 0.1
    r = ResidenceTimeSensor(([0.01, 0, 0], [1, 0, 0]), ([0.03, 0, 0], [1, 0, 0]))
    for t in np.arange(0, 1.0, 0.01):
        r.update(_state(t, [[v * t, 0, 0], [v * t - 0.005, 0, 0]]))
    np.testing.assert_allclose(r.residence_times_, [0.2, 0.2], atol=1e-9)
    L = 0.04
    s = PeriodicTransitSensor(0, L)
    for t in np.arange(0, 3.0, 0.002):
        x = v * t + 0.005 * np.sin(2 * np.pi * 5 * t)  # backflow: 0.157 > v
        s.update(_state(t, [[np.mod(x, L), 0, 0]]))
    tr = s.transit_times_
    assert len(tr) >= 5
    np.testing.assert_allclose(tr, L / v, atol=1e-3)


def _transit_run(s, t_grid, v, ids, late, L, start=0, stop=None):
    """Feed ``s`` particles ``ids`` moving at speeds v (+ and - along x, with backflow), the last
    ``late`` of them appearing halfway, over ``t_grid[start:stop]``."""
    for t in t_grid[start:stop]:
        x = v * t + 0.003 * np.sin(2 * np.pi * 20 * t + ids)  # period 0.05 s divides L / v
        keep = np.ones(len(ids), bool) if t >= t_grid[len(t_grid) // 2] else np.arange(
            len(ids)) < len(ids) - late  # fmt: skip
        pos = np.zeros((keep.sum(), 3))
        pos[:, 0] = np.mod(x[keep], L)
        s.update(_state(t, pos, ids=ids[keep]))


def test_periodic_transit_of_many_particles_in_any_id_order_and_after_a_resume():
    """Many particles, ids not in order, two of them appearing late, one moving backwards, all
    with backflow (an oscillation whose period divides L / v): each forward particle's transits
    are L / v (analytic), none for the backward one; the sensor
    pickled mid-run, or rebuilt from the per-particle dictionaries of earlier versions, continues
    to the same passages as the uninterrupted one."""
    import pickle

    L = 0.04
    ids = np.array([907, 3, 55, 12, 400, 8, 71])
    v = np.array([0.10, 0.08, -0.05, 0.16, 0.2, 0.05, 0.1])  # L / v: 0.4, 0.5, 0.25, 0.2, 0.8 s
    t_grid = np.arange(0, 3.0, 0.002)
    ref = PeriodicTransitSensor(0, L)
    _transit_run(ref, t_grid, v, ids, 2, L)
    by_id: dict[int, list[float]] = {}
    for pid, tp in ref.passages_:
        by_id.setdefault(pid, []).append(tp)
    for pid, vi in zip(ids, v):
        times = np.diff(by_id.get(int(pid), []))
        if vi < 0:
            assert len(times) == 0
        else:
            assert len(times) >= 1
            np.testing.assert_allclose(times, L / vi, atol=1e-3)
    half = len(t_grid) // 3
    a = PeriodicTransitSensor(0, L)
    _transit_run(a, t_grid, v, ids, 2, L, stop=half)
    resumed = pickle.loads(pickle.dumps(a))
    old = pickle.loads(pickle.dumps(a))
    state = dict(old.__dict__)
    state["_u"] = {int(i): float(u) for i, u in zip(old._ids, old._u)}
    state["_best"] = {int(i): int(b) for i, b in zip(old._ids, old._best)}
    del state["_ids"]
    legacy = PeriodicTransitSensor.__new__(PeriodicTransitSensor)
    legacy.__setstate__(state)
    for s in (resumed, legacy):
        _transit_run(s, t_grid, v, ids, 2, L, start=half)
        assert s.passages_ == ref.passages_
        assert s.transits_ == ref.transits_


def test_energy_sensor():
    """E_kin = m v^2 / 2, E_rot = (2/5) m r^2 w^2 / 2, E_pot = m g z (analytic)."""
    e = EnergySensor(RHO)
    e.update(_state(0.0, [[0, 0, 0.1]], vel=[[3.0, 4.0, 0.0]], omega=np.array([[0, 0, 10.0]])))
    assert e.kinetic_[0] == pytest.approx(0.5 * M * 25)
    assert e.rotational_[0] == pytest.approx(0.5 * 0.4 * M * R**2 * 100)
    assert e.potential_[0] == pytest.approx(M * 9.81 * 0.1)
    assert particle_masses([R], [2], {2: RHO})[0] == pytest.approx(M)
    with pytest.raises(ValueError, match="density"):
        particle_masses([R], [1], -1.0)
