"""Network model: RTD laws, analytic limits, sections in series, outlet prediction, export."""

import numpy as np
import pytest
from scipy import stats

from schemas.blender_model import BlenderModel
from twin_core.compartment import (
    CompartmentModel,
    CompartmentNetwork,
    blender_model_flow_scale,
    blender_model_predict,
    blender_model_rsd_profile,
    blender_model_rtd,
    blender_rtd,
    chain_sections,
    predict_outlet,
    rtd_moments,
    synthetic_blender_fields,
    to_blender_model,
)
from twin_core.compartment.network import chain_periodic


@pytest.fixture(scope="module")
def model():
    return CompartmentModel().fit(synthetic_blender_fields(6, 8, 8).fields)


def test_one_compartment_is_a_cstr():
    """Reference: ideal CSTR, E(t) = exp(-t/tau)/tau, tau = V/Q (Levenspiel ch. 11)."""
    net = CompartmentNetwork(holdup=[2.0], src=[], dst=[], rate=[], feed=[0.5], discharge=[0.5])
    t = np.linspace(0, 40, 801)
    np.testing.assert_allclose(net.impulse_response(t), np.exp(-t / 4.0) / 4.0, rtol=1e-10)
    np.testing.assert_allclose(net.cumulative(t), 1 - np.exp(-t / 4.0), atol=1e-12)


def test_equal_compartments_in_series_are_tanks_in_series():
    """Reference: N equal CSTRs in series give the gamma (Erlang) density with shape N and
    scale tau/N (tanks-in-series model, Levenspiel ch. 14; also the peer rtd.models code)."""
    n, q, v = 5, 0.2, 1.0
    net = CompartmentNetwork(
        holdup=np.full(n, v),
        src=np.arange(n - 1),
        dst=np.arange(1, n),
        rate=np.full(n - 1, q),
        feed=np.eye(n)[0] * q,
        discharge=np.eye(n)[-1] * q,
    )
    t = np.linspace(0, 100, 2001)
    ref = stats.gamma(a=n, scale=n * v / q / n).pdf(t)
    np.testing.assert_allclose(net.impulse_response(t), ref, atol=1e-12, rtol=1e-9)
    # peer implementation of the same law (twin_core.rtd, the RTD models of the line)
    from twin_core.rtd.models import tanks_in_series

    np.testing.assert_allclose(
        net.impulse_response(t), tanks_in_series(t, 0.0, n * v / q, n), atol=1e-12, rtol=1e-9
    )
    # the same law from the mixing-cup chain of 1-compartment sections
    cstr = CompartmentNetwork(holdup=[v], src=[], dst=[], rate=[], feed=[q], discharge=[q])
    np.testing.assert_allclose(chain_sections(cstr, n).impulse_response(t), ref, atol=1e-12)


def test_section_rtd_area_one_and_mean_v_over_q(model):
    """Closed-vessel law (Danckwerts 1953): for a conserving network (the closed-closed
    section, the face-coupled whole blender) the impulse response integrates to 1 and its mean
    is tau = holdup / throughput.  The transit (record-passage) form obeys the same mean by
    the renewal-reward theorem (net advance of one period per V/Q), up to the truncation of
    its upstream copies."""
    sec = model.closed_section_
    tau = sec.total_holdup / sec.throughput
    t = np.linspace(0, 40 * tau, 8001)
    area, mean, _ = rtd_moments(t, sec.impulse_response(t))
    assert area == pytest.approx(1.0, abs=1e-6)
    assert mean == pytest.approx(tau, rel=1e-5)
    assert model.mean_residence_time_s_ == pytest.approx(tau, rel=1e-12)
    assert sec.cumulative(t)[-1] == pytest.approx(1.0, abs=1e-9)
    area, mean, _ = rtd_moments(t, model.transit_section_.impulse_response(t))
    assert area == pytest.approx(1.0, abs=1e-6)
    assert mean == pytest.approx(tau, rel=2e-4)
    whole = chain_periodic(model.periodic_, 3)
    assert np.abs(whole.balance()).max() < 1e-10 * whole.throughput
    t3 = np.linspace(0, 15 * 3 * tau, 3001)
    area, mean, _ = rtd_moments(t3, whole.impulse_response(t3))
    assert area == pytest.approx(1.0, abs=1e-6)
    assert mean == pytest.approx(3 * tau, rel=1e-5)


def test_n_section_convolution_equals_chained_network(model):
    """Eq. (8-9): E of n sections by convolution equals the chained network's E."""
    sec = model.section_
    n = 8
    t = np.linspace(0, 4 * n * model.mean_residence_time_s_, 1201)
    e_chain = chain_sections(sec, n).impulse_response(t)
    e_conv = blender_rtd(sec, n, t)
    assert np.abs(e_chain - e_conv).max() < 1e-6 * e_chain.max()
    area, mean, _ = rtd_moments(t, e_conv)
    assert area == pytest.approx(1.0, abs=1e-5)
    assert mean == pytest.approx(n * model.mean_residence_time_s_, rel=1e-3)


def test_predict_step_pulse_and_dynamic_flows(model):
    """Step inlet -> outlet follows F(t) (Levenspiel: F is the step response); a pulse's
    tracer mass is conserved; flows scaled by s make the response s times faster (time warp
    of a constant-volume vessel)."""
    sec = model.section_
    n = 4
    tau = n * model.mean_residence_time_s_
    dt = 0.05
    t = np.arange(0, 6 * tau, dt)
    u = np.ones_like(t)
    u[0] = 0.0
    y = predict_outlet(sec, n, t, u, initial=0.0)
    F = chain_sections(sec, n).cumulative(t)
    # the inlet steps at t = dt, so the outlet is F(t - dt)
    np.testing.assert_allclose(y[1:], F[:-1], atol=2e-6)
    pulse = np.where((t >= 1.0) & (t < 2.0), 5.0, 0.0)
    yp = predict_outlet(sec, n, t, pulse)
    assert yp.sum() * dt == pytest.approx(pulse.sum() * dt, rel=1e-4)
    y_fast = predict_outlet(sec, n, t, u, initial=0.0, flow_scale=np.full(t.size, 2.0))
    half = t <= t[-1] / 2
    ref = np.interp(2 * t[half], t[:-1] + dt, F[:-1], left=0.0)
    np.testing.assert_allclose(y_fast[half], ref, atol=5e-3)
    y_stop = predict_outlet(sec, n, t, u, initial=0.3, flow_scale=np.zeros(t.size))
    np.testing.assert_allclose(y_stop, 0.3)
    np.testing.assert_allclose(predict_outlet(sec, n, t, np.full(t.size, 2.5)), 2.5, rtol=1e-9)
    with pytest.raises(ValueError, match="inlet must have the shape"):
        predict_outlet(sec, n, t, u[:-1])


def test_blender_model_export_roundtrip(model, tmp_path):
    bm = to_blender_model(model, n_sections=8, rpm_basis=100.0)
    assert bm.mean_residence_time_s == pytest.approx(8 * model.mean_residence_time_s_)
    path = bm.save(tmp_path / "m.json")
    bm2 = BlenderModel.load(path)
    t = np.arange(0, 120, 0.1)
    u = np.where(t < 10, 1.0, 2.0)
    np.testing.assert_allclose(
        blender_model_predict(bm2, t, u), blender_model_predict(bm, t, u), rtol=1e-12
    )
    e = blender_model_rtd(bm2, t)
    assert np.trapezoid(e, t) == pytest.approx(1.0, abs=1e-3)
    d = bm.model_dump()
    internal = d["flow_wrap"].index(False)
    d["flow_kg_s"][internal] *= 1.5
    with pytest.raises(ValueError, match="conserve mass"):
        BlenderModel.model_validate(d)
    d = bm.model_dump()
    d["flow_dst"][0] = 10**6
    with pytest.raises(ValueError, match="flow_dst must lie"):
        BlenderModel.model_validate(d)
    with pytest.raises(ValueError, match="rsd_profile needs"):
        blender_model_rsd_profile(bm, np.array([0.0]))


def test_rpm_law_from_runs_at_other_speeds():
    """The flow scale of dynamic runs from DEM runs at other blade speeds: the ratio of net
    axial flows (here two synthetic fields whose throughputs differ by 0.4), interpolated
    linearly through (0, 0) and (rpm_basis, 1), proportional beyond."""
    base = CompartmentModel().fit(synthetic_blender_fields(4, 6, 6, mean_residence_s=4.0).fields)
    slow = CompartmentModel().fit(synthetic_blender_fields(4, 6, 6, mean_residence_s=10.0).fields)
    bm = to_blender_model(base, n_sections=2, rpm_basis=100.0, rpm_runs={50.0: slow})
    ((r, sc),) = bm.rpm_flow_scale
    assert r == 50.0 and sc == pytest.approx(0.4, rel=1e-9)
    np.testing.assert_allclose(
        blender_model_flow_scale(bm, np.array([0.0, 25.0, 50.0, 75.0, 100.0, 200.0])),
        [0.0, 0.2, 0.4, 0.7, 1.0, 2.0],
        rtol=1e-9,
    )
    with pytest.raises(ValueError, match="rpm must be finite"):
        blender_model_flow_scale(bm, np.array([-1.0]))
