"""Feed-factor model (seed Eq. 2) and loss-in-weight feeder simulator."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.feeder import FeederConfig, loop_spectral_radius
from twin_core.feeder import LossInWeightFeeder, feed_factor, fit_feed_factor

QUIET = dict(flow_noise_rel=0.0, load_cell_noise_kg=0.0)


def test_feed_factor_limits_and_values():
    """Seed Eq. (2): FF(0) = FF_min, FF(inf) = FF_max, and one hand-computed value."""
    assert feed_factor(0.0, 6.0, 3.0, 0.5) == pytest.approx(3.0)
    assert feed_factor(1e6, 6.0, 3.0, 0.5) == pytest.approx(6.0)
    assert feed_factor(2.0, 6.0, 3.0, 0.5) == pytest.approx(6.0 - 3.0 * np.exp(-1.0))
    w = np.linspace(0, 5, 11)
    ff = feed_factor(w, 6.0, 3.0, 0.5)
    assert ff.shape == w.shape and np.all(np.diff(ff) > 0)
    with pytest.raises(ValueError, match="beta"):
        feed_factor(1.0, 6.0, 3.0, -1.0)


def test_fit_feed_factor_recovers_table_8_1_run_4():
    """Fit of Eq. (2) recovers the seed's Table 8.1 run 4 parameters from synthetic data
    (FF_max 0.05764, FF_min 0.00023, beta 6.68204) with 1 % noise, R^2 close to 1."""
    rng = np.random.default_rng(4)
    w = np.linspace(0.0, 0.9, 200)
    truth = (0.05764, 0.00023, 6.68204)
    y = feed_factor(w, *truth) * (1 + 0.01 * rng.standard_normal(w.size))
    fit = fit_feed_factor(w, y)
    assert fit.ff_max == pytest.approx(truth[0], rel=0.02)
    assert fit.beta == pytest.approx(truth[2], rel=0.05)
    assert abs(fit.ff_min - truth[1]) < 3 * fit.stderr["ff_min"] + 1e-3
    assert fit.r2 > 0.99
    assert fit.predict(0.5) == pytest.approx(feed_factor(0.5, fit.ff_max, fit.ff_min, fit.beta))
    with pytest.raises(ValueError, match="at least 4"):
        fit_feed_factor([1, 2, 3], [1, 2, 3])
    with pytest.raises(ValueError, match="constant"):
        fit_feed_factor([1, 1, 1, 1, 1], [1, 2, 3, 4, 5])


def test_gravimetric_steady_flow_equals_setpoint():
    """Closed loop with integral action: steady flow equals the set point (zero offset),
    here with FF constant (beta = 0) and no refills."""
    f = LossInWeightFeeder(beta_per_kg=0.0, refill_enabled=False, setpoint_kg_h=9.0, **QUIET)
    tr = f.simulate(300.0, 0.1, seed=0)
    late = tr.t_s > 200
    assert np.allclose(tr.mass_flow_kg_h[late], 9.0, rtol=1e-6)
    # a set-point step is followed too
    f = LossInWeightFeeder(
        beta_per_kg=0.0,
        refill_enabled=False,
        setpoint_kg_h=9.0,
        setpoint_schedule=[(100.0, 11.0)],
        **QUIET,
    )
    tr = f.simulate(400.0, 0.1, seed=0)
    assert np.allclose(tr.mass_flow_kg_h[tr.t_s > 300], 11.0, rtol=1e-5)
    assert np.allclose(tr.mass_flow_kg_h[(tr.t_s > 60) & (tr.t_s < 100)], 9.0, rtol=1e-5)


def test_gravimetric_mean_flow_with_noise_and_draining_hopper():
    """With process and load-cell noise and FF(W) falling as the hopper drains, the mass
    dispensed in gravimetric mode matches set point x time within 1 % (mass balance)."""
    f = LossInWeightFeeder(refill_enabled=False, initial_mass_kg=5.0)
    tr = f.simulate(900.0, 0.1, seed=3)
    t0, t1 = 60.0, 900.0
    assert tr.dispensed_kg(t0, t1) == pytest.approx(12.0 * (t1 - t0) / 3600, rel=0.01)
    # the hopper mass balance closes exactly
    lost = tr.hopper_mass_kg[0] - tr.hopper_mass_kg[-1]
    assert lost == pytest.approx(tr.dispensed_kg(), rel=2e-3)
    # the screw speed rises as FF falls: w = F / FF
    assert tr.screw_speed_rpm[-1] > tr.screw_speed_rpm[600]


def test_refill_surge_matches_feed_factor_ratio():
    """Refill in volumetric mode at constant screw speed: flow rises by FF(W_high)/FF(W_low)
    (seed Eqs. 1-2), then gravimetric control brings it back to the set point."""
    cfg = FeederConfig(initial_mass_kg=2.0, refill_low_kg=1.5, refill_high_kg=5.0, **QUIET)
    f = LossInWeightFeeder(cfg)
    tr = f.simulate(600.0, 0.1, seed=0)
    assert len(tr.refills) == 1
    start, stop = tr.refills[0]
    i, j = np.searchsorted(tr.t_s, [start, stop])
    assert tr.refilling[i:j].all() and not tr.refilling[: i - 1].any()
    # speed is held during the refill
    held = tr.screw_speed_rpm[i + 30 : j]
    assert np.ptp(held) < 1e-4 * held.mean()
    assert np.allclose(
        tr.mass_flow_kg_h[i + 30 : j], held * 0.06 * f.feed_factor(tr.hopper_mass_kg[i + 30 : j])
    )
    ratio = tr.mass_flow_kg_h[j] / tr.mass_flow_kg_h[i - 1]
    expected = f.feed_factor(tr.hopper_mass_kg[j]) / f.feed_factor(tr.hopper_mass_kg[i - 1])
    assert ratio == pytest.approx(expected, rel=1e-3)
    assert ratio > 1.1
    # refill adds the right mass at the configured rate
    assert stop - start == pytest.approx((5.0 - 1.5) / 0.5, abs=0.5)
    # back to the set point long after the refill
    assert tr.mass_flow_kg_h[-1] == pytest.approx(12.0, rel=0.01)
    assert not tr.volumetric[-1]


def test_volumetric_mode_flow_follows_feed_factor():
    """Open loop at fixed speed: F = w FF(W) * 60/1000 kg/h (seed Eq. 1)."""
    f = LossInWeightFeeder(
        mode="volumetric", volumetric_speed_rpm=40.0, refill_enabled=False, **QUIET
    )
    tr = f.simulate(120.0, 0.1, seed=0)
    expected = 40.0 * f.feed_factor(tr.hopper_mass_kg) * 0.06
    assert np.allclose(tr.mass_flow_kg_h[20:], expected[20:], rtol=1e-9)


def test_seeded_noise_is_reproducible():
    a = LossInWeightFeeder().simulate(60.0, 0.1, seed=7)
    b = LossInWeightFeeder().simulate(60.0, 0.1, seed=7)
    c = LossInWeightFeeder().simulate(60.0, 0.1, seed=8)
    assert np.array_equal(a.mass_flow_kg_h, b.mass_flow_kg_h)
    assert not np.array_equal(a.mass_flow_kg_h, c.mass_flow_kg_h)
    assert set(a.to_frame().columns) >= {"t_s", "mass_flow_kg_h", "refilling", "feed_factor_g_rev"}


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(kp=-1.0), "kp"),
        (dict(kp=0.0, ki=0.0), "kp > 0 or ki > 0"),
        (dict(refill_low_kg=5.0, refill_high_kg=2.0), "refill_low_kg"),
        (dict(ff_min_g_rev=7.0), "ff_min_g_rev"),
        (dict(screw_min_rpm=200.0), "screw_min_rpm"),
        (dict(setpoint_kg_h=100.0), "unreachable"),
        (dict(flow_window_s=0.1), "flow_window_s"),
        (dict(setpoint_schedule=[(10.0, 5.0), (5.0, 6.0)]), "increasing"),
        (dict(bogus=1), "bogus"),
        (dict(kp=3.0, ki=0.1), "unstable"),
        (dict(refill_rate_kg_s=0.001), "never refills"),
        (dict(kp=0.3, ki=1.0), "unstable"),
    ],
)
def test_bad_controller_config_raises_clear_error(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LossInWeightFeeder(**kwargs)


def test_stability_check_agrees_with_simulation():
    """The linearised-loop spectral radius (discrete-time stability, |z| < 1) predicts the
    simulated response to a set-point step: decaying below 1, growing (to a limit cycle at the
    speed limits) above 1."""
    base = FeederConfig(
        beta_per_kg=0.0, refill_enabled=False, setpoint_schedule=[(50.0, 10.0)], **QUIET
    )
    for kp, ki, stable in [
        (0.3, 0.1, True),
        (1.0, 0.3, True),
        (3.0, 0.1, False),
        (0.3, 1.0, False),
    ]:
        cfg = base.model_copy(update=dict(kp=kp, ki=ki))  # model_copy skips validation
        assert (loop_spectral_radius(cfg) < 1.0) == stable
        f = LossInWeightFeeder.__new__(LossInWeightFeeder)
        f.config = cfg
        tr = f.simulate(600.0, 0.1, seed=0)
        late = np.abs(tr.mass_flow_kg_h[tr.t_s > 500] - 10.0).max()
        assert (late < 0.05) == stable, (kp, ki, late)


def test_loop_gain_independent_of_feed_factor_scale():
    """Gain scheduling through FF(W): a powder with a 10x larger feed factor is controlled
    as well with the same gains (set point held, no oscillation)."""
    f = LossInWeightFeeder(ff_max_g_rev=60.0, ff_min_g_rev=35.0, refill_enabled=False, **QUIET)
    tr = f.simulate(300.0, 0.1, seed=0)
    assert np.allclose(tr.mass_flow_kg_h[tr.t_s > 150], 12.0, rtol=2e-3)


def test_bad_simulation_arguments():
    f = LossInWeightFeeder()
    with pytest.raises(ValueError, match="duration_s"):
        f.simulate(-1.0)
    with pytest.raises(ValueError, match="dt_s"):
        f.simulate(10.0, dt_s=1.0)
