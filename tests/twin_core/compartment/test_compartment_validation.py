"""Validation tools: particle-walk surrogate, RTD distances, RSD (Eq. 2) and Eq. (10)."""

import numpy as np
import pytest
from scipy import stats

from twin_core.compartment import (
    CompartmentModel,
    CompartmentNetwork,
    blender_rsd_profile,
    blender_rtd,
    compare_rtd,
    first_passage_network,
    fit_rsd_decay,
    rsd,
    rsd_decay,
    rtd_moments,
    section_rsd,
    split_initial,
    synthetic_blender_fields,
)
from twin_core.compartment.flows import cell_flows_from_crossings
from twin_core.compartment.network import chain_periodic
from twin_core.compartment.radial import grid_rsd_from_compartments, section_concentrations
from twin_core.compartment.surrogate import (
    cell_network,
    coarse_index,
    grid_rsd_from_particles,
    walk_snapshots,
    walk_transit_times,
)


@pytest.fixture(scope="module")
def small():
    case = synthetic_blender_fields(5, 7, 7)
    model = CompartmentModel().fit(case.fields)
    cells, _ = cell_network(case.fields, cell_flows_from_crossings(case.fields), model.mask_)
    return case, model, cells


def _cdf(t, e):
    return np.concatenate([[0.0], np.cumsum(0.5 * (e[1:] + e[:-1]) * np.diff(t))])


def test_walk_matches_its_exact_transit_time_law(small):
    """The Gillespie walk samples the Markov chain whose record-passage transit law is the
    first-passage network's E(t) (Norris 1997): a KS test must not reject it, and the mean
    transit equals V/Q (renewal-reward theorem: net advance of one period per V/Q)."""
    _, _, cells = small
    tt = walk_transit_times(cells, 4000, seed=11)
    assert np.all(np.isfinite(tt))
    tau = cells.total_holdup / small[0].throughput_kg_s
    t = np.linspace(0, 25 * tau, 5001)
    e = first_passage_network(cells, 2).impulse_response(t)
    p = stats.kstest(tt, lambda x: np.interp(x, t, _cdf(t, e))).pvalue
    assert p > 1e-3
    m = np.trapezoid(t * e, t)
    assert m == pytest.approx(tau, rel=2e-3)
    assert abs(tt.mean() - tau) < 4 * tt.std() / np.sqrt(tt.size)


def test_compartment_rtd_against_surrogate(small):
    """Compartment-model section RTD vs the exact particle-walk RTD (the DEM surrogate):
    pinned so that a regression shows (honest numbers in docs/compartment.md)."""
    _, model, cells = small
    tau = model.mean_residence_time_s_
    t = np.linspace(0, 25 * tau, 5001)
    e_ref = first_passage_network(cells, 2).impulse_response(t)
    r = compare_rtd(t, model.section_.impulse_response(t), e_ref=e_ref)
    assert abs(r["mean_rel_err"]) < 0.01
    assert -0.3 < r["var_rel_err"] < 0.1
    assert r["w1_rel"] < 0.06 and r["ks"] < 0.06
    # the conserving closed-closed cut loses the backflow through the face: more error
    rc = compare_rtd(t, model.closed_section_.impulse_response(t), e_ref=e_ref)
    assert rc["w1_rel"] > r["w1_rel"]


def test_compare_rtd_exponentials():
    """Two exponential RTDs (tau 2 and 3): W1 = |tau1 - tau2| = 1 (CDFs ordered) and
    KS = max |exp(-t/2) - exp(-t/3)| at t* = 6 ln 1.5."""
    t = np.linspace(0, 200, 200001)
    r = compare_rtd(t, np.exp(-t / 2) / 2, e_ref=np.exp(-t / 3) / 3)
    assert r["w1_s"] == pytest.approx(1.0, rel=1e-4)
    ts = 6 * np.log(1.5)
    assert r["ks"] == pytest.approx(np.exp(-ts / 3) - np.exp(-ts / 2), rel=1e-4)
    assert r["mean_rel_err"] == pytest.approx(-1 / 3, rel=1e-4)
    samples = stats.expon(scale=3).rvs(20000, random_state=1)
    rs = compare_rtd(t, np.exp(-t / 3) / 3, samples=samples)
    assert abs(rs["model_mean"] - rs["ref_mean"]) < 4 * rs["ref_mean_se"]
    with pytest.raises(ValueError, match="exactly one"):
        compare_rtd(t, t, e_ref=t, samples=samples)


def test_rsd_is_eq2():
    """Eq. (2): sample standard deviation (N - 1) over the mean."""
    c = np.array([[1.0, 2.0, 3.0, 6.0], [2.0, 2.0, 2.0, 2.0]])
    np.testing.assert_allclose(rsd(c, axis=1), [np.std(c[0], ddof=1) / 3.0, 0.0])
    np.testing.assert_allclose(rsd(c[0], weights=np.ones(4)), np.std(c[0], ddof=1) / 3.0)


def test_closed_section_mixes_to_uniform_seed_flows_do_not(small):
    """A conserving closed network mixes to a uniform concentration (its stationary law is
    proportional to the holdups), so RSD -> 0; the seed's Eq. (1) flows break the balance and
    leave a non-uniform steady state (an RSD plateau)."""
    case, model, _ = small
    c0 = split_initial(case.fields, model.labels_, axis=1)
    assert 0 < c0.mean() < 1
    t = np.linspace(0, 20 * model.mean_residence_time_s_, 41)
    r = section_rsd(model.periodic_, c0, t)
    assert r[0] > 0.5 and r[-1] < 1e-6
    seed = model.seed_flows_
    seed_net = CompartmentNetwork(model.holdup_kg_, seed.src, seed.dst, seed.rate)
    r_seed = section_rsd(seed_net, c0, t)
    assert r_seed[-1] > 0.05


def test_fit_rsd_decay_recovers_parameters():
    """Eq. (10), time form: a noisy profile with known RSD_ss, RSD_0, k_b is fitted back
    within a few standard errors."""
    t = np.linspace(0, 10, 200)
    rng = np.random.default_rng(5)
    y = rsd_decay(t, 0.1, 0.9, 0.8) + 0.003 * rng.standard_normal(t.size)
    fit = fit_rsd_decay(t, y)
    for k, v in (("rsd_ss", 0.1), ("rsd_0", 0.9), ("k_b", 0.8)):
        assert abs(fit[k] - v) < 5 * fit[f"{k}_se"] + 1e-3
    x = np.array([0.0, 1e3])
    prof = blender_rsd_profile(x, 0.1, 0.9, 0.8, v_x=0.01)
    np.testing.assert_allclose(prof, [0.9, 0.1], rtol=1e-9)
    with pytest.raises(ValueError, match="v_x must be > 0"):
        blender_rsd_profile(x, 0.1, 0.9, 0.8, v_x=0.0)


def test_whole_blender_against_face_coupled_cell_truth(small):
    """Whole blender of 4 sections: the cell-level surrogate with sections joined face to face
    (backflow between sections kept, closed ends) is the reference.  The product, the n-fold
    convolution of the transit-form section RTD (seed Eq. 8-9), must beat the convolution of
    closed-closed sections, whose cuts drop the backflow at every interface; the mean is
    n V / Q for all (closed-vessel law for the conserving reference)."""
    case, model, cells = small
    n = 4
    tau = n * model.mean_residence_time_s_
    t = np.linspace(0, 5 * tau, 2001)
    truth = chain_periodic(cells, n).impulse_response(t)
    assert rtd_moments(t, truth)[1] == pytest.approx(tau, rel=1e-4)
    prod = blender_rtd(model.section_, n, t)
    closed = blender_rtd(model.closed_section_, n, t)
    rp = compare_rtd(t, prod, e_ref=truth)
    rc = compare_rtd(t, closed, e_ref=truth)
    assert abs(rp["mean_rel_err"]) < 2e-3
    assert rp["w1_rel"] < rc["w1_rel"]
    assert rp["w1_rel"] < 0.03 and abs(rp["var_rel_err"]) < 0.15


def test_cell_network_grid_rsd_matches_walkers(small):
    """Radial mixing: the cell-resolution network's grid RSD plus the binomial sampling variance
    of a finite particle sample (seed Eq. B.1 on DEM) equals the grid RSD of walkers of the same
    Markov chain (forward equation = network), within the sampling scatter."""
    case, _, cells = small
    f = case.fields
    net = CompartmentModel(resolution="cells").fit(f)
    assert net.n_compartments_ == int(net.mask_.sum())
    y_mid = 0.5 * (f.y_edges[0] + f.y_edges[-1])
    rng = np.random.default_rng(4)
    n_part = 20000
    start = rng.choice(cells.n, size=n_part, p=cells.holdup / cells.holdup.sum())
    tracer = cells.centroid[start, 1] < y_mid
    tau = net.mean_residence_time_s_
    tm = np.linspace(0, 0.5 * tau, 9)
    bins = (5, 3, 3)
    coarse = coarse_index(f, net.mask_, bins)
    r_walk = grid_rsd_from_particles(walk_snapshots(cells, start, tm, seed=5), tracer, coarse, 45)
    c0 = (cells.centroid[:, 1] < y_mid).astype(float)
    c = section_concentrations(net.periodic_, c0, tm)
    ppk = n_part / float(f.holdup_kg[net.mask_].sum())
    _, r_net = grid_rsd_from_compartments(c, net.labels_, f.holdup_kg, coarse, 45, ppk)
    assert r_walk[0] == pytest.approx(r_net[0], abs=0.05)
    assert np.abs(r_walk - r_net).max() < 0.06
    assert r_net[-1] < 0.5 * r_net[0]


def test_grid_rsd_from_positions():
    """Eq. (B.1) on a hand-made snapshot: two sampling cells with tracer fractions 1 and 0 give
    RSD = std([1, 0], ddof=1) / 0.5 = sqrt(2); positions past the periodic end wrap."""
    from twin_core.compartment.radial import grid_rsd_from_positions

    f = synthetic_blender_fields(4, 4, 4).fields
    lx = f.x_edges[-1]
    pos = np.array([[0.25 * lx, 0, 0], [0.3 * lx + lx, 0, 0], [0.75 * lx, 0, 0], [0.8 * lx, 0, 0]])
    r = grid_rsd_from_positions(pos, np.array([True, True, False, False]), f, bins=(2, 1, 1))
    assert r == pytest.approx(np.sqrt(2.0), rel=1e-12)
    with pytest.raises(ValueError, match="positions must have shape"):
        grid_rsd_from_positions(pos[:, :2], np.ones(4, bool), f)


def test_initial_from_particles_and_window_censoring():
    """Tracer fraction per compartment from a snapshot (periodic wrap, empty compartments at
    the overall fraction); the window-censored law E(t) (W - t)+ / norm (Cox 1962) of an
    exponential E integrates to 1 and has the closed-form mean of that density."""
    from twin_core.compartment.radial import initial_from_particles
    from twin_core.compartment.validation import window_censored

    f = synthetic_blender_fields(3, 4, 4).fields
    labels = np.arange(48, dtype=np.int32).reshape(3, 4, 4)
    x, y, z = (c[0] for c in f.centers)
    pos = np.array([[x, y, z], [x, y, z], [x + f.x_edges[-1], y, z]])  # last wraps onto cell 0
    c = initial_from_particles(pos, np.array([True, False, True]), f, labels)
    assert c[0] == pytest.approx(2 / 3) and c[1] == pytest.approx(2 / 3)  # empty -> mean
    t = np.linspace(0, 10, 100001)
    tau, w = 1.0, 2.0
    ew = window_censored(t, np.exp(-t / tau) / tau, w)
    assert np.trapezoid(ew, t) == pytest.approx(1.0, abs=1e-9)
    # closed form: int_0^W t e^-t (W - t) dt / int_0^W e^-t (W - t) dt for tau = 1
    num = w * (1 - np.exp(-w) * (1 + w)) - (2 - np.exp(-w) * (w**2 + 2 * w + 2))
    den = w - (1 - np.exp(-w))
    assert np.trapezoid(t * ew, t) == pytest.approx(num / den, rel=1e-6)
    with pytest.raises(ValueError, match="window_s must be > 0"):
        window_censored(t, ew, 0.0)
