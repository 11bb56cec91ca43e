"""The open world of the plant simulator: the finite-volume blender, the open-world effects, the
data faults, the look-alike pairs and the scoring of a report (twin_core.plant.blender_fv,
openworld, faults, openworld_cases).

Validated against: the closed-form open-open axial-dispersion E(t) and its moments
(twin_core.rtd.models, Levenspiel ch. 13), the mobile-immobile E(t) by Talbot inversion
(twin_core.rtd.models.axial_dispersion_open_dead_volume, van Genuchten & Wierenga 1976), the
transfer function at s = k for a first-order loss, mass balances, and the effects' own
analytic definitions.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from test_plant import QUIET, ideal_line

from schemas.line import NIRNoise, TracerPulse
from twin_core.plant import EFFECTS, make_effect, simulate_line
from twin_core.plant.blender_fv import FiniteVolumeBlender, WallFilm
from twin_core.plant.faults import TIMING_KINDS, DataFault, apply_faults, random_timing_fault
from twin_core.plant.messages import run_messages
from twin_core.plant.openworld import OPEN_WORLD, make_open_world
from twin_core.plant.openworld_cases import (
    LOOKALIKE_PAIRS,
    Case,
    clopper_pearson_upper,
    match_probe,
    score_report,
)
from twin_core.plant.simulate import FlowDisturbance
from twin_core.rtd.models import (
    axial_dispersion_open,
    axial_dispersion_open_dead_volume,
    transfer_function,
)

TAU_D, TAU, PE = 11.92, 16.37, 7.67


def pulse_response(
    fv: FiniteVolumeBlender, n: int = 600, at: int = 10
) -> tuple[np.ndarray, np.ndarray]:
    """Outflow rate at the probe (1/s) after a unit mass entering over the tick at ``at`` (t
    from the pulse) into an empty vessel."""
    q = np.zeros(n)
    q[at] = 1.0 / fv.dt_s
    res = fv.simulate({"x": q})
    return np.arange(n) - at, res.probe_density["x"] / fv.tau


def bin_mean(f, t: np.ndarray) -> np.ndarray:
    """Mean of f over the tick bin [t - 1/2, t + 1/2] (the inlet convention)."""
    return np.mean([f(t - u) for u in np.linspace(-0.5, 0.5, 41)], axis=0)


# ---------------------------------------------------------------------------------------------
# finite-volume blender
# ---------------------------------------------------------------------------------------------
def test_fv_pulse_response_is_the_open_open_rtd():
    """Against the closed form (seed Table 6.2): the finite-volume pulse response matches
    E(t) to 0.3 % of its peak, holds the pulse's mass and has the mean residence time
    tau_d + tau (1 + 2/Pe) = 32.56 s."""
    fv = FiniteVolumeBlender(TAU_D, TAU, PE)
    t, y = pulse_response(fv)
    e = bin_mean(lambda s: axial_dispersion_open(s, TAU_D, TAU, PE), t.astype(float))
    assert np.max(np.abs(y - e)) < 3e-3 * e.max()
    assert y.sum() == pytest.approx(1.0, abs=1e-5)
    assert (t * y).sum() / y.sum() == pytest.approx(TAU_D + TAU * (1 + 2 / PE), abs=0.02)


def test_fv_line_matches_the_declared_convolution():
    """Peer check of the two code paths on a line with flow steps and tracer pulses: the
    independent finite-volume outlet is within 0.005 % w/w RMS (0.06 at the pulse peaks) of the
    declared convolution."""
    cfg = ideal_line(tracers=[TracerPulse(t_s=200.0, mass_kg=0.01, component="api")])
    dist = [FlowDisturbance("api", 100.0, 0.3), FlowDisturbance("excipient", 400.0, 2.0, 150.0)]
    a = simulate_line(cfg, 700.0, seed=0, disturbances=dist)
    b = simulate_line(cfg, 700.0, seed=0, disturbances=dist, blender="fv")
    d = b.sensor_true_pct_w_w - a.sensor_true_pct_w_w
    assert np.sqrt(np.mean(d**2)) < 5e-3 and np.abs(d).max() < 0.06
    assert b.blender == "fv" and a.blender == "convolution"


def test_in_list_unit_effects_reach_the_vessel_in_both_code_paths():
    """An in-list unit-stage effect (API lost in the unit, fraction l) changes what enters the
    vessel in the finite-volume path as in the declared convolution (peer check within the
    paths' 0.005 % w/w RMS), and the steady outlet is the mass balance 100 (1 - l) q_a /
    ((1 - l) q_a + q_e); the feeders' delivered flows are not changed by it."""
    lam = 0.05
    loss = [{"name": "component_loss", "target": "api", "params": {"fraction": lam}}]
    cfg = ideal_line()
    a = simulate_line(cfg, 400.0, seed=0, effects=loss)
    b = simulate_line(cfg, 400.0, seed=0, effects=loss, blender="fv")
    d = b.sensor_true_pct_w_w - a.sensor_true_pct_w_w
    assert np.sqrt(np.mean(d**2)) < 5e-3
    qa, qe = 1.2 * (1 - lam), 10.8
    for run in (a, b):
        assert run.outlet_true_pct_w_w["api"][-1] == pytest.approx(100 * qa / (qa + qe), rel=2e-4)
        assert run.feeders["api"].delivered_kg_h[-1] == pytest.approx(1.2)


def test_fv_stagnant_zone_is_the_mobile_immobile_rtd_and_holds_more():
    """Against the Talbot-inverted mobile-immobile E(t): the response matches to 1 % of the
    peak, its mean is tau_d + (1 + r) tau (1 + 2/Pe), and the steady hold-up is (1 + r) tau Q
    (mean convective time = V / Q with the stagnant volume counted)."""
    r, tx = 0.5, 40.0
    fv = FiniteVolumeBlender(TAU_D, TAU, PE, dead_ratio=r, dead_tau_s=tx)
    t, y = pulse_response(fv, n=1500)
    e = bin_mean(
        lambda s: axial_dispersion_open_dead_volume(np.maximum(s, 0), TAU_D, TAU, PE, r, tx),
        t.astype(float),
    )
    assert np.max(np.abs(y - e)) < 1e-2 * e.max()
    mean = (t * y).sum() / y.sum()
    assert mean == pytest.approx(TAU_D + (1 + r) * TAU * (1 + 2 / PE), rel=2e-3)
    q = 12.0 / 3600.0
    steady = fv.simulate({"x": np.full(50, q)})
    assert steady.holdup_kg["x"][-1] / q == pytest.approx((1 + r) * TAU, rel=1e-6)


def test_fv_velocity_factor_scales_the_residence_time():
    """A velocity factor v divides the convective time: hold-up / Q = tau / v at steady state
    and the pulse mean is tau_d + (tau / v)(1 + 2/Pe)."""
    fv = FiniteVolumeBlender(TAU_D, TAU, PE)
    q = np.zeros(600)
    q[10] = 1.0
    v = math.exp(0.2)  # on the propagators' velocity lattice (blender_fv.VELOCITY_STEP)
    y = fv.simulate({"x": q}, velocity=np.full(600, v)).probe_density["x"] * v / TAU
    t = np.arange(600) - 10
    assert (t * y).sum() / y.sum() == pytest.approx(TAU_D + TAU / v * (1 + 2 / PE), abs=0.03)
    steady = fv.simulate({"x": np.full(20, 0.01)}, velocity=np.full(20, v))
    assert steady.holdup_kg["x"][-1] / 0.01 == pytest.approx(TAU / v, rel=1e-3)


@pytest.mark.parametrize(
    "film",
    [
        WallFilm("api", 0.01),
        WallFilm("api", 0.002, capacity_kg=2e-3, release_s=(300.0,), release_tau_s=20.0),
    ],
    ids=["linear loss", "film with capacity and release"],
)
def test_fv_api_mass_balance(film):
    """Mass balance of the API: what entered = change of the mass in the domain + what left
    it + what was lost or held on the walls (to 1e-9 of the input)."""
    n = 600
    rng = np.random.default_rng(0)
    q = {"api": 1.2 / 3600 * (1 + 0.3 * (np.arange(n) > 200)) + 1e-5 * rng.random(n),
         "excipient": np.full(n, 10.8 / 3600)}  # fmt: skip
    fv = FiniteVolumeBlender(TAU_D, TAU, PE)
    res = fv.simulate(q, films=[film])
    a, b = fv._delayed_pieces(q["api"])
    entered = np.concatenate([[0.0], np.cumsum(fv.delay_frac * a + (1 - fv.delay_frac) * b)[:-1]])
    film_kg = res.film_kg.get("api", np.zeros(n))
    held = (
        res.domain_kg["api"] - res.domain_kg["api"][0] + res.outflow_kg["api"] + res.lost_kg["api"]
        + film_kg - film_kg[0]
    )  # fmt: skip
    np.testing.assert_allclose(held, entered, atol=1e-9 * entered[-1])
    if film.linear:
        assert res.lost_kg["api"][-1] > 0
    else:
        assert film_kg.max() <= film.capacity_kg * (1 + 1e-9)
        # built up towards its capacity, then emptied by the release (deposition goes on)
        assert film_kg[299] > 0.5 * film.capacity_kg
        assert film_kg[300:400].min() < 0.5 * film_kg[299] and film_kg[-1] > film_kg[399]


def test_api_wall_loss_loses_the_stated_fraction():
    """A first-order loss k in the dispersed vessel leaves G_AD(k) of the API (transfer
    function at s = k, the closed form of twin_core.rtd.models); ApiWallLoss chooses k for the
    stated fraction, and the outlet API content is the mass balance of what is left."""
    lam = 0.05
    eff = make_open_world({"name": "api_wall_loss", "params": {"loss_fraction": lam}})
    k = eff.rate_per_s(TAU, PE)
    g = transfer_function("axial_dispersion_open", k, tau_d=0.0, tau=TAU, pe=PE).real
    assert 1 - g == pytest.approx(lam, rel=1e-9)
    run = simulate_line(ideal_line(), 400.0, seed=0, open_world=[eff], blender="fv")
    qa, qe = 1.2 * (1 - lam), 10.8
    assert run.outlet_true_pct_w_w["api"][-1] == pytest.approx(100 * qa / (qa + qe), rel=2e-4)
    assert run.feeders["api"].flow_kg_h[-1] == pytest.approx(1.2)  # reported: unchanged


# ---------------------------------------------------------------------------------------------
# open-world effects
# ---------------------------------------------------------------------------------------------
def test_open_world_effects_are_not_candidates():
    """The open-world registry is disjoint from the close-loop's candidates; ten effects, each
    documented, with a product or probe side."""
    assert len(OPEN_WORLD) >= 10 and not set(OPEN_WORLD) & set(EFFECTS)
    for cls in OPEN_WORLD.values():
        assert cls.side in ("product", "probe") and cls.__doc__ and cls.params
    with pytest.raises(ValueError, match="effect name must be one of"):
        make_effect({"name": "api_wall_loss"})


def test_load_cell_span_error_delivers_more_than_reported():
    """delivered = (1 + b) reported; the outlet settles at the delivered ratio (mass balance)
    while the reported flow and the declared model do not move."""
    eff = {"name": "load_cell_span_error", "target": "api", "params": {"bias": 0.05}}
    run = simulate_line(ideal_line(), 300.0, seed=0, open_world=[eff])
    f = run.feeders["api"]
    np.testing.assert_allclose(f.delivered_kg_h, 1.05 * f.flow_kg_h)
    assert run.outlet_true_pct_w_w["api"][-1] == pytest.approx(100 * 1.26 / 12.06, rel=1e-6)
    np.testing.assert_allclose(run.predicted_declared(), 10.0 + QUIET.baseline_offset, rtol=1e-9)
    assert run.open_world[0]["name"] == "load_cell_span_error"
    assert run.open_world[0]["side"] == "product"


def test_screw_pulsation_frequency_and_amplitude():
    """A pulsation of n pulses per revolution at 6 rpm is a line at n x 0.1 Hz in the delivered
    flow, of amplitude a sinc(pi f dt) (the tick mean of the sine), mean flow unchanged."""
    n_t = 3000
    t = np.arange(n_t, dtype=float)
    rec = SimpleNamespace(id="api", screw_speed_rpm=np.full(n_t, 6.0))
    for pulses in (1.0, 2.0):
        eff = make_open_world(
            {"name": "screw_pulsation", "params": {"amplitude": 0.2, "pulses_per_rev": pulses}}
        )
        q = eff.apply_feeder(t, np.ones(n_t), rec)
        f_hz = eff.frequency_hz(6.0)
        spec = np.abs(np.fft.rfft(q - q.mean())) * 2 / n_t
        freqs = np.fft.rfftfreq(n_t)
        assert freqs[np.argmax(spec)] == pytest.approx(f_hz, abs=1 / n_t)
        assert spec.max() == pytest.approx(0.2 * np.sinc(f_hz), rel=1e-2)
        assert q.mean() == pytest.approx(1.0, abs=1e-3)


def test_chute_clogging_conserves_mass_and_blocks_the_flow():
    """Episodes block the flow completely, the slugs return the held mass: total delivered =
    total reported; the episodes are reproducible from the seed."""
    t = np.arange(7200.0)
    spec = {"name": "chute_clogging", "params": {"rate_per_h": 6.0, "seed": 4.0}}
    eff = make_open_world(spec)
    q = np.full(t.size, 1.2 / 3600)
    out = eff.apply_feeder(t, q, SimpleNamespace(id="api"))
    eps = eff.episodes(t)
    assert len(eps) >= 3 and eps == make_open_world(spec).episodes(t)
    assert out.sum() == pytest.approx(q.sum(), rel=1e-12)
    for i, k in eps:
        assert np.all(out[i : i + k] == 0.0) and out[i + k] > q[0]


def test_probe_fouling_loss_and_growing_lag():
    """Before t0 the reading is the concentration; a late step is followed with the lag
    tau_max s(t) (63 % after one time constant) and scaled by 1 - phi_max s(t)."""
    eff = make_open_world({"name": "probe_fouling", "params": {
        "t_start_s": 100.0, "growth_s": 200.0, "loss_max": 0.1, "lag_max_s": 20.0}})  # fmt: skip
    t = np.arange(3000.0)
    c = np.where(t < 2500, 10.0, 12.0)
    y = eff.apply_sensor(t, c)
    np.testing.assert_allclose(y[:100], 10.0)
    s = 1 - math.exp(-2400 / 200)
    assert y[2499] == pytest.approx(10.0 * (1 - 0.1 * s), rel=1e-6)
    gain = 1 - 0.1 * s
    rise = (y[2500 + 20] / gain - 10.0) / 2.0
    assert rise == pytest.approx(1 - math.exp(-1), abs=0.02)


def test_nonlinear_calibration_and_humidity_step():
    """The curved calibration reads the truth at its centre and kappa d^2 high at +-d; the
    humidity step is 0 before t_s and delta (1 - 1/e) one time constant after."""
    cal = make_open_world({"name": "nonlinear_calibration", "params": {"curvature": 0.04}})
    t = np.arange(3.0)
    np.testing.assert_allclose(cal.apply_sensor(t, np.array([10.0, 8.0, 12.0])),
                               [10.0, 8.16, 12.16])  # fmt: skip
    hum = make_open_world(
        {"name": "humidity_step", "params": {"t_s": 100.0, "offset": 0.5, "tau_s": 50.0}}
    )
    t = np.arange(400.0)
    y = hum.apply_sensor(t, np.zeros(400))
    assert np.all(y[:101] == 0.0) and y[150] == pytest.approx(0.5 * (1 - math.exp(-1)))


def test_open_world_runs_keep_the_reported_inputs_and_reuse_feeders():
    """Hidden effects change the truth, never the twin's inputs; a run from another run's
    feeder records is the same run; bad input is refused with the field named."""
    from twin_core.plant import seed_line

    cfg = seed_line(tracer_g=(), tracer_times_s=())
    base = simulate_line(cfg, 300.0, seed=3, blender="fv")
    eff = [{"name": "api_buildup_release", "params": {"deposition_per_s": 0.01}},
           {"name": "humidity_step", "params": {"t_s": 100.0, "offset": 0.3}}]  # fmt: skip
    run = simulate_line(cfg, 300.0, seed=3, open_world=eff, blender="fv")
    again = simulate_line(cfg, 300.0, seed=3, open_world=eff, blender="fv",
                          feeder_records=base.feeders)  # fmt: skip
    for k in base.feeders:
        np.testing.assert_array_equal(run.feeders[k].flow_kg_h, base.feeders[k].flow_kg_h)
    np.testing.assert_array_equal(again.measured_pct_w_w, run.measured_pct_w_w)
    assert not np.allclose(run.sensor_true_pct_w_w, base.sensor_true_pct_w_w)
    with pytest.raises(ValueError, match="open-world effect name"):
        simulate_line(cfg, 100.0, open_world=[{"name": "nope"}])
    with pytest.raises(ValueError, match="need blender='fv'"):
        simulate_line(cfg, 100.0, open_world=[eff[0]])
    with pytest.raises(ValueError, match="act on E\\(t\\)"):
        simulate_line(cfg, 100.0, effects=[{"name": "dead_zone"}], blender="fv")


# ---------------------------------------------------------------------------------------------
# data faults
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def messages():
    cfg = ideal_line(noise=NIRNoise())
    run = simulate_line(cfg, 600.0, seed=1)
    return cfg, run_messages(run, cfg)


def _stream(msgs, key_part, field):
    return [(k, m) for k, m in msgs if key_part in k and hasattr(m, field)]


def test_stuck_and_gap_faults(messages):
    """A stuck stretch holds identical readings (the first of the stretch) for its whole
    duration; a gap removes exactly its messages; nothing else changes."""
    cfg, msgs = messages
    out, truth = apply_faults(msgs, [DataFault("stuck", "nir", t_s=100.0, duration_s=120.0)], cfg)
    nir = _stream(out, "/pat/", "concentration_pct_w_w")
    vals = np.array([m.concentration_pct_w_w for _, m in nir])
    t = np.array([m.t for _, m in nir])
    inside = (t >= 100) & (t < 220)
    assert np.all(vals[inside] == vals[inside][0]) and inside.sum() == 120
    orig = np.array(
        [m.concentration_pct_w_w for _, m in _stream(msgs, "/pat/", "concentration_pct_w_w")]
    )
    np.testing.assert_array_equal(vals[~inside], orig[~inside])
    assert truth == [{"kind": "stuck", "stream": "nir", "t_start_s": 100.0, "t_end_s": 219.0,
                      "n_samples": 120}]  # fmt: skip
    out, truth = apply_faults(msgs, [DataFault("gap", "api", t_s=50.0, duration_s=30.0)], cfg)
    assert len(msgs) - len(out) == 30 and truth[0]["n_samples"] == 30
    assert not any(m.t >= 50 and m.t < 80 for k, m in out if k.endswith("/api/flow"))


def test_clip_spike_and_time_faults(messages):
    """Clipping keeps every reading inside the range and lists the clipped stretches; spikes
    touch only the burst's interval; a time jump shifts the stamps from t_s on, in order;
    duplicate stamps give pairs of readings one stamp."""
    cfg, msgs = messages
    orig = [m for _, m in _stream(msgs, "/pat/", "concentration_pct_w_w")]
    out, truth = apply_faults(msgs, [DataFault("clip", "nir", low=0.0, high=10.1)], cfg)
    vals = np.array(
        [m.concentration_pct_w_w for _, m in _stream(out, "/pat/", "concentration_pct_w_w")]
    )
    assert vals.max() <= 10.1
    assert sum(x["n_samples"] for x in truth) == sum(m.concentration_pct_w_w > 10.1 for m in orig)
    fault = DataFault("spike_burst", "api", "flow", t_s=200.0, duration_s=60.0, size=0.5)
    out, truth = apply_faults(msgs, [fault], cfg)
    a = [m for k, m in out if k.endswith("/api/flow")]
    b = [m for k, m in msgs if k.endswith("/api/flow")]
    changed = [x.t for x, y in zip(a, b) if x.mass_flow_kg_h != y.mass_flow_kg_h]
    assert len(changed) == truth[0]["n_samples"] > 5 and all(200 <= c < 260 for c in changed)
    out, truth = apply_faults(msgs, [DataFault("time_jump", "nir", t_s=300.0, size=-120.0)], cfg)
    t = np.array([m.t for _, m in _stream(out, "/pat/", "concentration_pct_w_w")])
    np.testing.assert_array_equal(t[300:], np.arange(300.0, 601.0) - 120.0)
    np.testing.assert_array_equal(t[:300], np.arange(300.0))
    out, _ = apply_faults(
        msgs, [DataFault("duplicate_stamps", "nir", t_s=10.0, duration_s=10.0)], cfg
    )
    t = np.array([m.t for _, m in _stream(out, "/pat/", "concentration_pct_w_w")])
    np.testing.assert_array_equal(t[10:20], [10, 10, 12, 12, 14, 14, 16, 16, 18, 18])
    with pytest.raises(ValueError, match="fault kind"):
        DataFault("melted")


def test_timing_faults_move_stamps_and_values_not_the_readings(messages):
    """Timing faults (TIMING_KINDS): a shift moves one field by whole messages; a clock offset
    moves every stamp and keeps the arrival order (stamps below 0 dropped); jitter stays within
    its size in order; irregular sampling keeps the intervals within 1 +- fraction periods, each
    reading the original one nearest in time, sequence numbers anew; dropped ticks are isolated; a re-sent tick
    is an identical copy right after its original; a random fault is drawn from its seed."""
    cfg, msgs = messages
    whole = dict(duration_s=math.inf)

    def flows(out):
        return [m for k, m in out if k.endswith("/api/flow")]

    def nir(out):
        return [m for _, m in _stream(out, "/pat/", "concentration_pct_w_w")]

    b = flows(msgs)
    out, truth = apply_faults(msgs, [DataFault("shift", "api", "flow", size=2, **whole)], cfg)
    a = flows(out)
    assert [m.mass_flow_kg_h for m in a[2:]] == [m.mass_flow_kg_h for m in b[:-2]]
    assert [m.t for m in a] == [m.t for m in b] and truth[0]["field"] == "mass_flow_kg_h"
    out, truth = apply_faults(msgs, [DataFault("clock_offset", "nir", size=-2.5, **whole)], cfg)
    t = np.array([m.t for m in nir(out)])
    np.testing.assert_allclose(t, np.arange(3.0, 601.0) - 2.5)
    assert truth[0]["n_lost"] == 3
    pos = [i for i, (k, _) in enumerate(out) if "/pat/" in k]
    pos0 = [i for i, (k, _) in enumerate(msgs) if "/pat/" in k][3:]
    assert [p - q for p, q in zip(pos, pos0)] == [-3 * 1] * len(pos)  # same place, 3 fewer before
    out, _ = apply_faults(msgs, [DataFault("jitter", "nir", size=0.4, seed=2, **whole)], cfg)
    e = np.array([m.t for m in nir(out)]) - np.arange(0.0, 601.0)
    assert np.abs(e).max() <= 0.4 and np.abs(e).max() > 0.3
    out, truth = apply_faults(
        msgs, [DataFault("irregular", "nir", fraction=0.4, seed=3, **whole)], cfg
    )
    m2 = nir(out)
    d = np.diff([m.t for m in m2])
    assert d.min() >= 0.6 - 1e-9 and d.max() <= 1.4 + 1e-9
    assert [m.seq for m in m2] == list(range(len(m2))) and truth[0]["n_samples"] == len(m2)
    c0 = np.array([m.concentration_pct_w_w for m in nir(msgs)])
    nearest = np.round([m.t for m in m2]).astype(int)  # the original reading nearest in time
    np.testing.assert_array_equal([m.concentration_pct_w_w for m in m2], c0[nearest])
    assert all(x.t <= y.t for x, y in zip([m for _, m in out], [m for _, m in out][1:]))
    out, truth = apply_faults(
        msgs, [DataFault("drop_ticks", "api", fraction=0.1, seed=4, **whole)], cfg
    )
    seq = np.array([m.seq for m in flows(out)])
    assert np.all(np.diff(seq) <= 2) and len(b) - seq.size == truth[0]["n_samples"] > 20
    out, truth = apply_faults(
        msgs, [DataFault("duplicate_ticks", "api", fraction=0.1, seed=5, **whole)], cfg
    )
    a = flows(out)
    twins = [i for i in range(1, len(a)) if a[i] == a[i - 1]]
    assert len(twins) == truth[0]["n_samples"] == len(a) - len(b) > 20
    assert random_timing_fault(7, ["api", "excipient"]) == random_timing_fault(
        7, ["api", "excipient"]
    )
    kinds = {f[-1].kind for f in (random_timing_fault(s, ["api"]) for s in range(60))}
    assert kinds == set(TIMING_KINDS)
    with pytest.raises(ValueError, match="whole number"):
        DataFault("shift", "api", size=1.5, **whole)


# ---------------------------------------------------------------------------------------------
# look-alikes and scoring
# ---------------------------------------------------------------------------------------------
def test_lookalike_probe_reproduces_the_product_reading():
    """The probe-side partner fitted to API lost in the blender is a gain of about
    1 - lambda (1 - c), and its noise-free reading is within 0.01 % w/w RMS of the product
    run's, far below the seed's NIR noise (0.23 % w/w at 10 % API)."""
    cfg = ideal_line()
    dist = [FlowDisturbance("api", 200.0, 0.3, 200.0)]
    pair = LOOKALIKE_PAIRS["api_wall_loss~sensor_gain"]
    product = simulate_line(cfg, 600.0, seed=0, open_world=[pair.product], disturbances=dist,
                            blender="fv")  # fmt: skip
    spec, rms = match_probe(product, pair.probe)
    assert rms < 0.01
    assert spec["params"]["gain"] == pytest.approx(1 - 0.05 * 0.9, abs=3e-3)
    case = Case.lookalike("api_wall_loss~sensor_gain", "probe")
    assert case.truth_name() == "sensor_gain" and case.blender == "fv"


def test_score_report_reads_old_and_new_report_fields():
    """The scoring reads the report as a dict: today's report (status explained, alternatives)
    and the fields another branch adds (equivalents with scores, product_at_risk, a
    discriminating measurement, data_quality); a missing field is a failure."""
    truth = {"family": "lookalike", "truth": "api_wall_loss",
             "truth_names": ["api_wall_loss", "api_loss"]}  # fmt: skip
    old = {"status": "explained", "effects": [{"name": "sensor_gain", "alternatives": []}]}
    s = score_report(old, truth)
    assert s["outcome"] == "wrong_confident" and s["product_at_risk"] is None
    assert not s["both_listed"] and not s["lookalike_ok"]
    new = {
        "status": "partly_explained",
        "effects": [{"name": "sensor_gain", "equivalents": [
            {"label": "api_loss", "delta_loglik": 0.4}, "feed_factor_drift[api]"]}],
        "product_at_risk": True,
        "discriminating_measurement": {"text": "assay 6 tablets", "power": 0.9},
        "data_quality": [],
    }  # fmt: skip
    s = score_report(new, truth)
    assert s["outcome"] == "right_equivalent" and s["equivalents_field"] == "equivalents"
    assert s["both_listed"] and s["lookalike_ok"]
    fault = {"family": "fault", "truth": "none", "truth_names": ["none"],
             "faults": [{"kind": "stuck", "t_start_s": 100.0, "t_end_s": 200.0}]}  # fmt: skip
    dq = {"status": "data_quality", "effects": [],
          "data_quality": [{"kind": "flatline", "t_start_s": 95.0, "t_end_s": 205.0, "n_samples": 111}]}  # fmt: skip
    s = score_report(dq, fault)
    assert s["flagged"] and s["status_data_quality"] and s["outcome"] == "no_claim"
    s = score_report({"status": "explained", "effects": [{"name": "dead_zone"}]}, fault)
    assert not s["flagged"] and s["outcome"] == "claim"


def test_clopper_pearson_upper_bound():
    """k = 0 of n: 1 - 0.05^(1/n) (the 'rule of three' ~ 3/n)."""
    assert clopper_pearson_upper(0, 200) == pytest.approx(1 - 0.05 ** (1 / 200))
    assert clopper_pearson_upper(5, 100) > 0.05 and clopper_pearson_upper(100, 100) == 1.0
