"""Inter-compartment flows: recovery of known flows, exact conservation, the seed's Eq. (1)."""

import numpy as np
import pytest

from twin_core.compartment import (
    CompartmentModel,
    aggregate_flows,
    project_flows,
    rtd_moments,
    synthetic_blender_fields,
    to_blender_model,
)
from twin_core.compartment.fields import GridFields
from twin_core.compartment.flows import incidence, node_balance
from twin_core.compartment.synthetic import cell_divergence


@pytest.fixture(scope="module")
def case():
    return synthetic_blender_fields(6, 10, 10)


def test_synthetic_flows_are_divergence_free(case):
    """Reference: the discrete divergence of a discrete curl (stream functions) vanishes, and
    a column-constant axial flow is divergence-free; so every cell balances to round-off."""
    div = cell_divergence(case.flows, case.fields.periodic)
    assert np.abs(div).max() < 1e-12 * case.throughput_kg_s
    fx = case.flows[0]
    for i in range(case.fields.shape[0]):
        net = (fx[i, ..., 0] - fx[i, ..., 1]).sum()
        assert net == pytest.approx(case.throughput_kg_s, rel=1e-12)


def test_crossings_recover_known_flows(case):
    """Known truth: the generator's cell-face flows summed between compartments must be what
    the model returns from the crossing counts (expected counts, no noise)."""
    m = CompartmentModel(min_cells=1).fit(case.fields)
    truth = aggregate_flows(case.flows, m.labels_, case.fields.periodic)
    net = m.periodic_
    got = {(s, d, w): r for s, d, w, r in zip(net.src, net.dst, net.wrap, net.rate)}
    exp = {(s, d, w): r for s, d, w, r in zip(truth.src, truth.dst, truth.wrap, truth.rate)}
    assert got.keys() == exp.keys()
    err = max(abs(got[k] - exp[k]) for k in exp)
    assert err < 1e-12 * max(exp.values())
    assert m.throughput_kg_s_ == pytest.approx(case.throughput_kg_s, rel=1e-12)
    assert m.correction_rel_ < 1e-12


def test_product_flows_conserve_mass_exactly_seed_flows_do_not(case):
    """Product (b): row/column sums balance to 1e-10; the seed's Eq. (1) shows its imbalance."""
    noisy = synthetic_blender_fields(6, 10, 10, counts="poisson", seed=3)
    for fields in (case.fields, noisy.fields):
        m = CompartmentModel().fit(fields)
        scale = m.throughput_kg_s_
        assert np.abs(m.periodic_.balance()).max() < 1e-10 * scale
        assert np.abs(m.closed_section_.balance()).max() < 1e-10 * scale
        assert m.closed_section_.throughput == pytest.approx(m.throughput_kg_s_, rel=1e-12)
        assert np.all(m.periodic_.rate >= 0) and np.all(m.closed_section_.rate >= 0)
        assert m.seed_imbalance_["max_rel"] > 0.1
    assert m.raw_imbalance_["max_rel"] > 1e-3  # Poisson counts do not balance by themselves


def test_projection_is_nonexpansive_towards_the_truth():
    """Projection onto the closed convex set {C f = 0, f >= 0} (which holds the true flows) is
    non-expansive (Bauschke & Combettes 2011, Prop. 4.16): |P(f0) - f*| <= |f0 - f*|."""
    case = synthetic_blender_fields(5, 8, 8)
    m = CompartmentModel(min_cells=1).fit(case.fields)
    truth = aggregate_flows(case.flows, m.labels_, case.fields.periodic)
    rng = np.random.default_rng(7)
    C = incidence(truth.n, truth.src, truth.dst)
    for _ in range(3):
        f0 = truth.rate * (1 + 0.2 * rng.standard_normal(truth.rate.size))
        f = project_flows(C, np.zeros(truth.n), f0)
        assert np.abs(C @ f).max() < 1e-10 * truth.rate.max()
        assert f.min() >= 0
        assert np.linalg.norm(f - truth.rate) < np.linalg.norm(f0 - truth.rate)


def test_projection_small_cases():
    """Analytic minimal-norm corrections: a 3-cycle takes the mean flow; a 2-cycle whose
    unconstrained optimum is negative is clamped at zero (KKT of the QP)."""
    C = incidence(3, np.array([0, 1, 2]), np.array([1, 2, 0]))
    np.testing.assert_allclose(project_flows(C, np.zeros(3), np.array([1.0, 2.0, 3.0])), 2.0)
    C2 = incidence(2, np.array([0, 1]), np.array([1, 0]))
    np.testing.assert_allclose(project_flows(C2, np.zeros(2), np.array([1.0, -3.0])), 0.0)
    np.testing.assert_allclose(
        project_flows(C2, np.zeros(2), np.array([1.0, -0.5])), 0.25, rtol=1e-12
    )
    with pytest.raises(ValueError, match="f0 must have shape"):
        project_flows(C2, np.zeros(2), np.ones(3))


def _plug_flow_fields(v: float = 0.01) -> GridFields:
    nx, ny, nz = 5, 4, 4
    edges = [
        np.linspace(0, 0.04, nx + 1),
        np.linspace(0, 0.02, ny + 1),
        np.linspace(0, 0.02, nz + 1),
    ]
    vel = np.zeros((nx, ny, nz, 3))
    vel[..., 0] = v
    occ = np.full((nx, ny, nz), 10.0)
    return GridFields(
        *edges, vel, np.full((nx, ny, nz), 0.5), occ, 10.0, 1e-5, (True, False, False)
    )


def test_velocity_flows_and_seed_on_plug_flow():
    """Uniform plug flow: upwind flow between slices = rho_bulk A v (exact for constant v);
    the seed's Eq. (1) gives A (v_i - v_j) = 0 and loses the throughput entirely."""
    f = _plug_flow_fields()
    m = CompartmentModel(flow_source="velocity", min_cells=1).fit(f)
    rho = 10.0 * 1e-5 / (0.008 * 0.005 * 0.005)
    q = rho * 0.02 * 0.02 * 0.01
    assert m.n_compartments_ == 5
    assert m.throughput_kg_s_ == pytest.approx(q, rel=1e-12)
    np.testing.assert_allclose(m.periodic_.rate, q, rtol=1e-12)
    assert m.mean_residence_time_s_ == pytest.approx(0.04 / 0.01, rel=1e-12)
    assert m.seed_flows_.rate.size == 0
    with pytest.raises(ValueError, match="crossings"):
        CompartmentModel(flow_source="crossings").fit(f)


def test_velocity_flows_conserve_after_projection(case):
    m = CompartmentModel(flow_source="velocity").fit(case.fields)
    assert m.raw_imbalance_["max_rel"] > 1e-3
    bal = node_balance(m.periodic_.n, m.periodic_.src, m.periodic_.dst, m.periodic_.rate)
    assert np.abs(bal).max() < 1e-10 * m.throughput_kg_s_
    assert m.throughput_kg_s_ == pytest.approx(case.throughput_kg_s, rel=0.05)


def test_stagnant_pocket_is_reported_and_harmless():
    """A pocket of occupied cells that no particle leaves or enters (zero crossings, zero
    velocity) becomes isolated compartments: reported as stagnant holdup; the RTD of the
    rest still integrates to 1 with mean (V - V_stagnant) / Q (closed-vessel law on the
    flowing part)."""
    import dataclasses

    case = synthetic_blender_fields(5, 8, 8)
    f = case.fields
    pocket = np.zeros(f.shape, bool)
    pocket[:, 3:5, 0:2] = True
    pocket &= case.mask
    assert pocket.sum() > 0
    cr = []
    for axis, c in enumerate(f.crossings):
        c = c.copy()
        nb = np.roll(pocket, -1, axis=axis)
        touch = pocket | nb
        c[touch] = 0.0
        cr.append(c)
    vel = f.velocity.copy()
    vel[pocket] = 0.0
    f2 = dataclasses.replace(f, crossings=tuple(cr), velocity=vel)
    m = CompartmentModel(min_cells=1).fit(f2)
    assert m.isolated_holdup_kg_ == pytest.approx(f.holdup_kg[pocket].sum(), rel=1e-9)
    sec = m.closed_section_
    tau = (sec.total_holdup - m.isolated_holdup_kg_) / sec.throughput
    assert m.mean_residence_time_s_ == pytest.approx(tau, rel=1e-12)
    bm = to_blender_model(m, n_sections=2)
    assert bm.mean_residence_time_s == pytest.approx(2 * tau, rel=1e-9)
    t = np.linspace(0, 40 * tau, 6001)
    area, mean, _ = rtd_moments(t, sec.impulse_response(t))
    assert area == pytest.approx(1.0, abs=1e-6) and mean == pytest.approx(tau, rel=1e-5)
    area, mean, _ = rtd_moments(t, m.section_.impulse_response(t))
    assert area == pytest.approx(1.0, abs=1e-6) and mean == pytest.approx(tau, rel=2e-4)
    assert m.transit_section_.meta["truncated_crossings"] < 1e-4


def test_no_net_axial_flow():
    """Circulation without conveying: the periodic network still mixes (closed vessel), but
    there is no RTD; the export says so."""
    case = synthetic_blender_fields(4, 6, 6, backflow=0.0)
    f = case.fields
    cr = list(f.crossings)
    net = cr[0][..., 0] - cr[0][..., 1]
    col = net.mean(axis=0)  # the column through-flow, the same on every x face
    c = cr[0].copy()
    c[..., 0] = np.where(col > 0, c[..., 0] - col, c[..., 0])
    c[..., 1] = np.where(col < 0, c[..., 1] + col, c[..., 1])
    import dataclasses

    f2 = dataclasses.replace(f, crossings=(np.maximum(c, 0.0), cr[1], cr[2]))
    m = CompartmentModel().fit(f2)
    assert abs(m.throughput_kg_s_) < 1e-12 * case.throughput_kg_s
    assert m.section_ is None and m.mean_residence_time_s_ == float("inf")
    assert np.abs(m.periodic_.balance()).max() < 1e-10 * m.periodic_.rate.max()
    with pytest.raises(ValueError, match="no net axial flow"):
        to_blender_model(m)


def test_projection_leaves_no_round_off_trickles():
    """A dead end (a node with inflow but no outflow edge) must end with exactly zero inflow,
    not a round-off trickle that would make it a trap of the tracer network (KKT: the flow
    into a node that cannot pass it on is 0)."""
    # cycle 0 -> 1 -> 2 -> 0 plus a dead end 1 -> 3
    src, dst = np.array([0, 1, 2, 1]), np.array([1, 2, 0, 3])
    C = incidence(4, src, dst)
    f = project_flows(C, np.zeros(4), np.array([1.0, 0.9, 1.1, 0.05]))
    assert f[3] == 0.0
    np.testing.assert_allclose(f[:3], 1.0, rtol=1e-12)
