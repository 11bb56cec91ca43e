"""Particle transitions at a lag as compartment flows (twin_core.compartment.transitions).

References: the Kolmogorov forward equation of a continuous-time Markov chain (transition
probabilities expm(K tau)); the mean first-passage time of a biased walk on a ring (L / v);
and an independent particle simulator (``layer_walk``: a conveyed layer over a rattling bed,
transit times recorded every step), whose transits the models must reproduce.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from layer_walk import simulate_layer_walk
from scipy.linalg import expm

from twin_core.compartment import CompartmentModel
from twin_core.compartment.build import BuildOptions, build_blender_model
from twin_core.compartment.fields import GridFields, load_fields, mirror_axis, save_fields
from twin_core.compartment.flows import wrap_directions
from twin_core.compartment.transitions import (
    count_transitions,
    unwrap_periodic,
)


def test_unwrap_follows_a_particle_faster_than_half_a_period_per_frame():
    L, dt, v = 0.04, 0.1, 0.28  # 0.7 L per frame
    t = np.arange(6) * dt
    x_true = 0.005 + v * t
    x = np.mod(x_true, L)[:, None]
    vel = np.full_like(x, v)
    u = unwrap_periodic(x, vel, np.diff(t), L)
    assert np.allclose(u[:, 0], x_true)
    naive = np.diff(x[:, 0])
    naive -= L * np.round(naive / L)  # minimum image: goes the wrong way
    assert np.all(naive < 0)


def _ring_walk(a: float, b: float, n_cells: int, n_part: int, times: np.ndarray, seed: int):
    """Exact (Gillespie) biased walk on a ring of cells: rate a to the + neighbour, b to the -
    one; positions (unwrapped cell index) at ``times``."""
    rng = np.random.default_rng(seed)
    pos = rng.integers(0, n_cells, n_part).astype(float)
    out = np.empty((times.size, n_part))
    t = np.zeros(n_part)
    for k, tk in enumerate(times):
        active = np.ones(n_part, dtype=bool)
        while active.any():
            wait = rng.exponential(1.0 / (a + b), n_part)
            move = active & (t + wait <= tk)
            active &= move  # a particle whose next jump falls after tk is done
            step = np.where(rng.random(n_part) < a / (a + b), 1.0, -1.0)
            pos[move] += step[move]
            t[move] += wait[move]
        out[k] = pos
        t[:] = tk  # memoryless: the next jump counts from the frame time
    return out


def _ring_fields(n_cells: int, h: float, occupancy: float) -> GridFields:
    shape = (n_cells, 1, 1)
    return GridFields(
        x_edges=np.linspace(0, n_cells * h, n_cells + 1),
        y_edges=np.array([0.0, h]),
        z_edges=np.array([0.0, h]),
        velocity=np.zeros((*shape, 3)),
        solid_fraction=np.full(shape, 0.3),
        occupancy=np.full(shape, occupancy),
        duration_s=1.0,
        particle_mass_kg=1e-6,
        periodic=(True, False, False),
    )


def test_counts_follow_the_kolmogorov_transition_probabilities_and_the_drift():
    a, b, nc, h, n_part, tau = 3.0, 1.0, 10, 0.004, 400, 0.1
    times = np.arange(301) * tau
    cells = _ring_walk(a, b, nc, n_part, times, seed=1)
    pos = np.zeros((times.size, n_part, 3))
    pos[:, :, 0] = np.mod((cells + 0.5) * h, nc * h)
    pos[:, :, 1:] = 0.5 * h
    vel = np.zeros_like(pos)
    vel[:, :, 0] = (a - b) * h  # drift: the unwrapping hint
    tr = count_transitions(
        times,
        pos,
        vel,
        (np.linspace(0, nc * h, nc + 1), np.array([0.0, h]), np.array([0.0, h])),
        lag_frames=1,
    )
    assert tr.dropped == 0 and tr.origins == times.size - 1
    # reference: P(tau) = expm(K tau) of the ring's generator
    K = np.zeros((nc, nc))
    for i in range(nc):
        K[i, (i + 1) % nc] += a
        K[i, (i - 1) % nc] += b
        K[i, i] = -(a + b)
    P = expm(K * tau)
    n_from = n_part * tr.origins / nc  # uniform occupancy
    for d in (1, -1, 2):
        sel = (tr.dst - tr.src) % nc == d % nc
        got = tr.count[sel].sum() / (n_from * nc)
        expect = P[0, d % nc]
        se = np.sqrt(expect * (1 - expect) / (n_from * nc))
        assert abs(got - expect) < 5 * se + 1e-4, (d, got, expect)
    # net periods crossed per particle and second: (a - b) / n_cells (the walk's drift)
    net = float(np.sum(tr.count * tr.shift)) / (n_part * tr.origins * tau)
    assert net == pytest.approx((a - b) / nc, rel=0.05)
    # the model of the cells: throughput m_p N (a - b) / n_cells, mean first passage
    # n_cells / (a - b) (the ring's exact mean passage time)
    f = replace(_ring_fields(nc, h, n_part / nc), transitions=tr)
    m = CompartmentModel(flow_source="transitions", resolution="cells").fit(f)
    assert m.throughput_kg_s_ == pytest.approx(1e-6 * n_part * (a - b) / nc, rel=0.05)
    assert m.mean_residence_time_s_ == pytest.approx(nc / (a - b), rel=0.05)
    t = np.linspace(0, 40, 4001)
    e = m.section_.impulse_response(t)
    assert np.trapezoid(t * e, t) == pytest.approx(nc / (a - b), rel=0.06)


def test_transitions_round_trip_mirror_and_bad_keys(tmp_path):
    nc, h = 10, 0.004
    times = np.arange(21) * 0.1
    cells = _ring_walk(3.0, 1.0, nc, 50, times, seed=2)
    pos = np.zeros((times.size, 50, 3))
    pos[:, :, 0] = np.mod((cells + 0.5) * h, nc * h)
    pos[:, :, 1:] = 0.5 * h
    vel = np.zeros_like(pos)
    vel[:, :, 0] = 2 * h
    f0 = _ring_fields(nc, h, 5.0)
    tr = count_transitions(times, pos, vel, f0.edges)
    f = replace(f0, transitions=tr)
    g = load_fields(save_fields(tmp_path / "f.npz", f))
    assert np.array_equal(g.transitions.count, tr.count)
    assert g.transitions.lag_s == pytest.approx(tr.lag_s)
    mm = mirror_axis(mirror_axis(g, 0), 0).transitions
    order = np.lexsort((mm.shift, mm.dst, mm.src))
    ref = np.lexsort((tr.shift, tr.dst, tr.src))
    assert np.array_equal(mm.src[order], tr.src[ref]) and np.array_equal(
        mm.shift[order], tr.shift[ref]
    )
    assert np.sum(mirror_axis(g, 0).transitions.shift * tr.count) == -np.sum(tr.shift * tr.count)
    d = f.to_dict()
    d["transition_shift"] = d["transition_shift"] * 3
    np.savez(tmp_path / "bad.npz", **d)
    with pytest.raises(ValueError, match="transition_shift"):
        load_fields(tmp_path / "bad.npz")
    d = f.to_dict()
    del d["transition_count"]
    np.savez(tmp_path / "bad2.npz", **d)
    with pytest.raises(ValueError, match="transition_count"):
        load_fields(tmp_path / "bad2.npz")


def test_wrap_directions_of_jumps_across_the_periodic_face():
    slices = np.array([0, 1, 8, 9])
    src, dst = np.array([2, 3, 0, 1]), np.array([1, 0, 3, 2])
    fwd, bwd = wrap_directions(slices, src, dst, np.ones(4, dtype=bool))
    assert fwd.tolist() == [True, True, False, False]
    assert bwd.tolist() == [False, False, True, True]
    with pytest.raises(ValueError, match="two different axial slices"):
        wrap_directions(slices, np.array([0]), np.array([0]), np.array([True]))


@pytest.fixture(scope="module")
def rattling_bed():
    w = simulate_layer_walk(seed=0, d_axial=2e-4)
    tr = count_transitions(w.times, w.positions, w.velocities, w.fields.edges, lag_frames=2)
    return w, replace(w.fields, transitions=tr)


def test_kinetic_model_follows_the_particles_over_a_rattling_bed(rattling_bed):
    """A third of the particles lie in a bed that exchanges with the conveyed layer at
    0.05 / s and rattles across the cell faces above it every few ms.  Face crossings count
    the rattling as exchange and mix the bed into the flow; transitions at 0.2 s filter it.
    Measured over seeds 0-3 (layer_walk defaults, d_axial 2e-4): censored KS distance to
    the simulator's transits 0.098-0.102 (transitions) against 0.140-0.144 (crossings)."""
    w, f = rattling_bed
    res = build_blender_model(
        f,
        BuildOptions(
            transit_times=w.transit_s, transit_window_s=w.window_s, rsd_source="compartments"
        ),
    )
    cand = res.report["flow_source_candidates"]
    assert res.report["flow_source"] == "transitions"
    assert cand["transitions"]["censored_ks"] < cand["crossings"]["censored_ks"] - 0.02
    assert cand["transitions"]["censored_ks"] < 0.13
    assert res.report["rtd_validation"]["ks"] == pytest.approx(cand["transitions"]["censored_ks"])


def test_closed_side_pools_are_stagnant_not_traps():
    """A thin bed (2 % of the particles) leaves cell pairs that only trade rattling particles
    across the periodic face: stagnant holdup of the model, not a singular RTD."""
    w = simulate_layer_walk(seed=0, d_axial=2e-4, bed_fraction=0.02, jitter_m=2e-4)
    m = CompartmentModel(flow_source="crossings").fit(w.fields)
    assert m.isolated_.size > 0
    t = np.linspace(0, 20, 2001)
    e = m.section_.impulse_response(t)
    assert np.trapezoid(e, t) == pytest.approx(1.0, abs=0.02)
