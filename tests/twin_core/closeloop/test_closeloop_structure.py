"""Structure beyond the library (``twin_core.closeloop.structure``).

Validated against: the dense covariance the innovations whiten (the whitener itself is checked
against the simulator's noise by Monte Carlo in test_closeloop) and Monte Carlo of the sandwich
covariance; the F(2, 2K-2)
null law of Thomson's harmonic F-test; the declared model's own prediction (the kernel
linearisation and its identity X e = c0); the analytic mean residence time of a two-zone
exchange blender (matrix exponential vs the scipy ODE integration); and validation records made
independently of the searches (``structure_cases``: a flow pulsation, a throughput-dependent
tau by piecewise simulation, a two-zone blender integrated as an ODE). Rates over many records
are the benchmark's (benchmarks/closeloop_structure.py, docs/closeloop.md).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal, stats
from scipy.integrate import solve_ivp

from schemas.closeloop import CloseLoopReport, StructureEntry
from schemas.line import NIRNoise
from twin_core.closeloop import make_split
from twin_core.closeloop import structure_cases as sc
from twin_core.closeloop.noise import NoiseWhitener, pink_autocorrelation
from twin_core.closeloop.plots import structure_figures
from twin_core.closeloop.report import close_loop
from twin_core.closeloop.structure import StructureOptions, find_structure
from twin_core.closeloop.structure_base import residual_context, weighted_fit
from twin_core.closeloop.structure_kernel import (
    hat_basis,
    hat_convolutions,
    kernel_design,
    kernel_length_s,
)
from twin_core.closeloop.structure_periodic import coherence_at, multitaper_ftest
from twin_core.plant.nir import add_nir_noise, noise_sd
from twin_core.rtd.profiles import moments

DURATION = 3600.0


@pytest.fixture(scope="module")
def const_run():
    return sc.base_run(DURATION, seed=11)


@pytest.fixture(scope="module")
def vary_run():
    return sc.base_run(DURATION, seed=12, vary_throughput=True)


def _search(case, **opt):
    sp = make_split(case.data.t_s)
    found = find_structure(
        case.data, case.model, train=sp.train, heldout=sp.heldout, options=StructureOptions(**opt)
    )
    return found, sp


def _first_of_kind(case, kind):
    """The first finding of ``kind`` in the search of ``case`` (asserted to exist), all
    findings and the split."""
    found, sp = _search(case)
    of_kind = [f for f in found if f.kind == kind]
    assert of_kind, [f.summary for f in found]
    return of_kind[0], found, sp


def test_gram_is_the_covariance_the_innovations_whiten():
    """``NoiseWhitener.gram`` (the sandwich covariances' A'CA) against the dense covariance
    S R S built from the pink autocorrelation (Toeplitz), and against the whitener itself: with
    a predictor as long as the record the innovations are exact, W S^-1 C S^-1 W' = I."""
    from scipy.linalg import toeplitz

    rng = np.random.default_rng(0)
    n = 300
    pred = 10 + rng.standard_normal(n)
    noise = NIRNoise(outlier_prob=0.0, baseline_offset=0.0)
    sigma = noise_sd(pred, noise)
    whiten = NoiseWhitener(sigma, noise)
    c = whiten.gram(np.eye(n))
    r = (1 - whiten.share) * np.eye(n) + whiten.share * toeplitz(pink_autocorrelation(n, n - 1))
    assert np.allclose(c, sigma[:, None] * r * sigma[None, :], rtol=0, atol=1e-12)
    w = np.column_stack([whiten(col) for col in np.eye(n)])
    m = w @ (c / np.outer(sigma, sigma)) @ w.T
    assert np.allclose(m, np.eye(n), atol=1e-9)
    a = rng.standard_normal((n, 3))
    assert np.allclose(whiten.gram(a), a.T @ c @ a, atol=1e-12)


def test_sandwich_covariance_matches_monte_carlo_of_the_simulated_noise(const_run):
    """Coefficients of a weighted fit on records of the simulator's NIR noise (white + 1/f +
    proportional): their spread over 300 records equals the sandwich covariance A'CA within
    the Monte-Carlo error, and is larger than the white-noise formula for the slow column."""
    case = sc.none_case(const_run, 0)
    sp = make_split(case.data.t_s)
    ctx = residual_context(case.data, case.model, sp.train, sp.heldout, None)
    t = ctx.t
    cols = np.column_stack([np.ones_like(t), np.cos(2 * np.pi * t / 60.0), (t - t.mean()) / 1e3])
    noise = ctx.noise.model_copy(update={"baseline_offset": 0.0, "outlier_prob": 0.0})
    rng = np.random.default_rng(1)
    betas = []
    for _ in range(300):
        e, _ = add_nir_noise(ctx.pred, noise, rng)
        betas.append(weighted_fit(ctx, cols, e - ctx.pred, ctx.train)[0])
    mc = np.var(np.array(betas), axis=0, ddof=1)
    _, sandwich = weighted_fit(ctx, cols, np.zeros_like(t), ctx.train)
    ratio = mc / np.diag(sandwich)
    # variance ratio of 300 draws: chi2(299)/299 within about +-25 % (99.9 %)
    assert np.all((ratio > 0.72) & (ratio < 1.3)), ratio
    wx = np.where(ctx.train[:, None], cols * ctx.weight[:, None], 0.0)
    white = np.diag(np.linalg.inv(wx.T @ cols))
    assert mc[2] > 1.5 * white[2]  # the 1/f noise inflates the slow (trend) column


def test_harmonic_f_test_follows_its_null_law_under_coloured_noise():
    """Without a line, Thomson's F at a fixed frequency is F(2, 2K-2) under white + 1/f +
    proportional noise (KS test), and the Bonferroni search rarely fires."""
    rng = np.random.default_rng(2)
    noise = NIRNoise(outlier_prob=0.0, baseline_offset=0.0)
    signal = np.full(2000, 10.0)
    p_fixed, fired = [], 0
    for _ in range(200):
        x, _ = add_nir_noise(signal, noise, rng)
        lines = multitaper_ftest(x - x.mean(), 1.0, 4.0)
        j = int(np.argmin(np.abs(lines.freqs_hz - 0.05)))
        p_fixed.append(stats.f.sf(lines.f_stat[j], 2, lines.dof))
        band = (lines.freqs_hz > 0.01) & (lines.freqs_hz < 0.49)
        p_min = stats.f.sf(lines.f_stat[band].max(), 2, lines.dof)
        fired += p_min * 0.48 * 2000 < 0.01
    assert stats.kstest(p_fixed, "uniform").pvalue > 0.001
    assert fired <= 6  # expected <= 2 of 200 at the 1 % level


def test_multitaper_recovers_a_sinusoid_in_coloured_noise():
    rng = np.random.default_rng(3)
    n, f0, amp = 3000, 1 / 37.0, 0.15
    t = np.arange(n, dtype=float)
    x, _ = add_nir_noise(np.full(n, 10.0), NIRNoise(outlier_prob=0.0, baseline_offset=0.0), rng)
    x = x - 10.0 + amp * np.cos(2 * np.pi * f0 * t + 0.4)
    lines = multitaper_ftest(x - x.mean(), 1.0, 4.0)
    j = int(np.argmax(lines.f_stat))
    assert abs(lines.freqs_hz[j] - f0) < 4.0 / n
    assert 2 * abs(lines.mu[j]) == pytest.approx(amp, rel=0.3)
    assert stats.f.sf(lines.f_stat[j], 2, lines.dof) * n / 2 < 1e-3


def test_coherence_at_one_bin_equals_scipy_welch_coherence():
    """Against ``scipy.signal.coherence`` (Hann, non-overlapping, linear detrend) at every
    bin, on a pair sharing a sinusoid and a trend."""
    rng = np.random.default_rng(5)
    n, nper = 2000, 128
    t = np.arange(n, dtype=float)
    common = np.sin(2 * np.pi * t / 40.0)
    x = common + 0.01 * t + rng.standard_normal(n)
    u = 0.5 * common - 0.02 * t + rng.standard_normal(n)
    f, c = signal.coherence(x, u, fs=1.0, window="hann", nperseg=nper, noverlap=0, detrend="linear")
    ours = np.array([coherence_at(x, u, nper, k) for k in range(f.size)])
    np.testing.assert_allclose(ours, c, atol=1e-10)
    assert ours[int(round(nper / 40.0))] > 0.5  # the shared line


def test_hat_convolutions_equal_direct_convolution_with_the_basis():
    rng = np.random.default_rng(4)
    m = rng.random(400)
    basis = hat_basis(12, 3)
    past = np.full(basis.shape[0], 0.7)
    direct = np.column_stack(
        [
            np.convolve(np.concatenate([past, m]), basis[:, k])[past.size : past.size + m.size]
            for k in range(12)
        ]
    )
    np.testing.assert_allclose(hat_convolutions(m, 0.7, 12, 3), direct, atol=1e-12)


def test_kernel_linearisation_reproduces_the_declared_model(const_run):
    """X e = c0 (the concentration is homogeneous of degree 0 in the kernel, so only the mass
    term remains) and X (e' - e) is the first-order change of the declared model's prediction
    when its E(t) changes (extra delay, dead zone, back-mixing)."""
    case = sc.none_case(const_run, 0)
    model, data = case.model, case.data
    length = kernel_length_s(model, 1.0, None)
    d = kernel_design(model, data, length, 3.0)
    c0 = model.outlet(data.inputs)["api"]
    assert np.max(np.abs(d.x @ d.e_knots - c0)) < 0.02  # of ~10 % w/w (hat interpolation)
    for eff in (
        {"name": "extra_delay", "params": {"delay_s": 2.0}},
        {"name": "dead_zone", "params": {"fraction": 0.1, "tau_s": 30.0}},
        {"name": "back_mixing", "params": {"pe_factor": 0.8}},
    ):
        aug = model.augmented([eff])
        change = aug.predict(data.inputs) - model.predict(data.inputs)
        lin = d.x @ (kernel_design(aug, data, length, 3.0).e_knots - d.e_knots)
        rms = np.sqrt(np.mean(change**2))
        assert np.sqrt(np.mean((lin - change) ** 2)) < 0.3 * rms, eff["name"]


def test_two_zone_outlet_matches_scipy_ode_integration():
    """The exact per-interval integration of the two-zone blender against scipy's
    ``solve_ivp`` of the same mass balances, flows stepping in API and in total."""
    dt, n, h1, h2, k, shift = 1.0, 400, 0.0667, 0.04, 0.001, 10
    t = np.arange(n) * dt
    m_tot = np.where(t < 150, 12.0, 14.0) / 3600.0
    m_c = m_tot * np.where(t < 60, 0.10, np.where(t < 250, 0.12, 0.09))
    got = sc.two_zone_outlet(m_c, m_tot, dt, h1, h2, k, shift)

    def rhs(tt, x):
        j = min(max(int(tt / dt + 1e-9) - shift, 0), n - 1)
        c1, c2 = x[0] / h1, x[1] / h2
        return [m_c[j] - m_tot[j] * c1 - k * (c1 - c2), k * (c1 - c2)]

    sol = solve_ivp(
        rhs, (0.0, t[-1]), [0.1 * h1, 0.1 * h2], t_eval=t, max_step=dt, rtol=1e-8, atol=1e-12
    )
    np.testing.assert_allclose(got, sol.y[0] / h1, atol=1e-5)
    assert np.ptp(got) > 0.02  # the steps reach the outlet


def test_two_zone_generator_matches_its_analytic_rtd(const_run):
    """The two-zone blender's impulse response (matrix exponential) has unit mass and mean
    residence time delay + (H1 + H2) / Q, and the outlet of ``two_zone_case`` equals the inlet
    concentration convolved with that response where the throughput is constant."""
    q = 12.0 / 3600.0
    # from the delay on: the response jumps there, which the trapezoid rule would smear
    lag = np.arange(10.0, 1500.0, 0.5)
    e = sc.two_zone_rtd(lag, q, 20.0 * q, 0.04, 0.001, 10.0)
    m = moments(lag, e)
    assert m.area == pytest.approx(1.0, abs=2e-3)
    assert m.mean == pytest.approx(10.0 + (20.0 * q + 0.04) / q, rel=5e-3)
    case = sc.two_zone_case(const_run, 0, stagnant_kg=0.04, exchange_kg_h=3.6)
    assert case.truth["mean_residence_time_s"] == pytest.approx(10.0 + 20.0 + 0.04 / q)
    flows = case.data.inputs.flows_kg_h
    c_in = 100 * flows["api"] / (flows["api"] + flows["excipient"])
    e1 = sc.two_zone_rtd(np.arange(0.0, 600.0), q, 20.0 * q, 0.04, 0.001, 10.0)
    e1 = e1 / e1.sum()  # unit mass on the 1 s grid (the response jumps at the delay)
    conv = np.convolve(np.concatenate([np.full(600, c_in[0]), c_in]), e1)[600 : 600 + c_in.size]
    baseline = case.model.config.sensor.noise.baseline_offset
    # the flows vary a little (feeder noise, steps of 10 % of the API): agreement to 0.05 % w/w
    assert np.median(np.abs(case.signal - baseline - conv)[700:]) < 0.05


def test_no_structure_in_effect_free_records(const_run, vary_run):
    for run in (const_run, vary_run):
        for scale, seed in ((1.0, 21), (2.0, 22)):
            case = sc.none_case(sc.with_noise_scale(run, scale), seed)
            found, _ = _search(case)
            assert found == [], [f.summary for f in found]


def test_pulsation_carried_by_the_screw_speed_is_found_and_attributed(const_run):
    case = sc.pulsation_case(const_run, 5, 0.02, period_s=75.0, screw_shows_it=True)
    f, _, sp = _first_of_kind(case, "periodic")
    v, lo, hi = f.estimates["frequency_hz"]
    assert abs(v - 1 / 75.0) <= f.evidence["bandwidth_hz"]
    assert f.estimates["amplitude_pct_w_w"][0] == pytest.approx(
        case.truth["amplitude_pct_w_w"], rel=0.3
    )
    assert "coherent with api:screw_speed" in f.summary
    assert f.evidence["heldout_p_value"] < 0.01
    # the correction brings the held-out prediction closer to the noise-free truth
    pred = case.model.predict(case.data.inputs)
    corr = f.correction(case.data, case.model)
    ho = sp.heldout
    assert np.sqrt(np.mean((pred + corr - case.signal)[ho] ** 2)) < 0.7 * np.sqrt(
        np.mean((pred - case.signal)[ho] ** 2)
    )
    StructureEntry.model_validate(f.to_dict())


def test_screw_locked_pulsation_is_matched_to_the_screw_rotation(const_run):
    case = sc.pulsation_case(const_run, 6, 0.2)
    f, _, _ = _first_of_kind(case, "periodic")
    assert (
        abs(f.estimates["frequency_hz"][0] - case.truth["frequency_hz"])
        <= f.evidence["bandwidth_hz"]
    )
    assert "screw rotation of api" in f.summary


def test_throughput_dependent_tau_is_found_with_its_sign(vary_run):
    case = sc.throughput_tau_case(vary_run, 7, exponent=1.0)
    f, _, sp = _first_of_kind(case, "parameter_dependence")
    named = [f"{f.curves['param']} vs {f.curves['covariate']}", *f.alternatives]
    assert any(
        n.startswith(("blender.tau vs throughput", "blender.tau vs excipient")) for n in named
    )
    assert f.curves["slope"] < 0 if f.curves["param"].startswith("blender.tau") else True
    assert f.evidence["constant_p_value"] < 0.01 and f.evidence["heldout_p_value"] < 0.01
    pred = case.model.predict(case.data.inputs)
    corr = f.correction(case.data, case.model)
    ho = sp.heldout
    assert np.sqrt(np.mean((pred + corr - case.signal)[ho] ** 2)) < np.sqrt(
        np.mean((pred - case.signal)[ho] ** 2)
    )
    StructureEntry.model_validate(f.to_dict())


def test_two_zone_blender_gives_a_kernel_correction_usable_on_another_record(const_run):
    case = sc.two_zone_case(const_run, 8, stagnant_kg=0.04)
    f, found, sp = _first_of_kind(case, "kernel_correction")
    mean, lo, hi = f.estimates["mean_residence_time_s"]
    declared = f.evidence["declared_mean_residence_time_s"]
    assert lo > declared  # the stagnant zone lengthens the residence time
    assert f.estimates["tail_fraction"][1] > f.evidence["declared_tail"]
    # the kernel found on this record corrects the prediction of another one (same blender)
    other_run = sc.base_run(DURATION, seed=13)
    other = sc.two_zone_case(other_run, 9, stagnant_kg=0.04)
    pred = other.model.predict(other.data.inputs)
    corr = f.correction(other.data, other.model)
    err_before = np.sqrt(np.mean((pred - other.signal)[600:] ** 2))
    err_after = np.sqrt(np.mean((pred + corr - other.signal)[600:] ** 2))
    assert err_after < 0.6 * err_before
    StructureEntry.model_validate(f.to_dict())
    figs = structure_figures(found)
    assert len(figs) == len(found) and all(k.endswith(".png") for k in figs)


def test_the_report_lists_the_structure_the_library_left(const_run):
    """``close_loop`` fills the report's ``structure`` with ``find_structure`` on what the
    library left: an API pulsation at the screw's rotation (no candidate is periodic) is
    reported as a periodic entry at the true frequency (inside its 95 % interval), valid as
    ``CloseLoopReport``; the effect-free record of the same line gives no entry."""
    pulsed = sc.pulsation_case(const_run, 6, 0.2)
    rep = close_loop(pulsed.data, pulsed.model).to_dict()
    CloseLoopReport.model_validate(rep)
    periodic = [s for s in rep["structure"] if s["kind"] == "periodic"]
    assert periodic, rep["structure"]
    _, lo, hi = periodic[0]["estimates"]["frequency_hz"]
    assert lo <= pulsed.truth["frequency_hz"] <= hi
    assert periodic[0]["summary"] in rep["remaining"]
    clean = sc.none_case(const_run, 0)
    rep0 = close_loop(clean.data, clean.model).to_dict()
    assert rep0["structure"] == []


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="kinds must be among"):
        StructureOptions(kinds=("wavelets",))
    with pytest.raises(ValueError, match="alpha must be in"):
        StructureOptions(alpha=1.5)
    with pytest.raises(ValueError, match="interval|ci95_low"):
        StructureEntry(kind="periodic", summary="x", estimates={"a": (1.0, 2.0, 3.0)})


def test_masks_are_checked(const_run):
    case = sc.none_case(const_run, 0)
    n = case.data.t_s.size
    with pytest.raises(ValueError, match="train must be a boolean mask of shape"):
        find_structure(case.data, case.model, train=np.ones(3, bool), heldout=np.ones(n, bool))
    with pytest.raises(ValueError, match="must not overlap"):
        find_structure(case.data, case.model, train=np.ones(n, bool), heldout=np.ones(n, bool))


def test_a_window_too_short_for_the_kernel_cross_validation_gives_no_kernel_not_an_error():
    """A 300 s live window (150 s skipped) holds a single cross-validation block of the
    kernel search: lambda cannot be chosen, so no kernel correction is sought (before: a
    division by the empty training fold's weight, 'array must not contain infs or NaNs', and
    the window's finding was lost). A 12 % API feed bias is still found."""
    from twin_core.closeloop import RunData
    from twin_core.closeloop.report import online_finding
    from twin_core.closeloop.scenarios import effect_spec, standard_scenario
    from twin_core.plant import LineModel, simulate_line

    cfg, dist = standard_scenario(300.0)
    run = simulate_line(
        cfg, 300.0, seed=3, disturbances=dist, effects=[effect_spec("feed_bias", 1)]
    )
    d = RunData.from_line_run(run)
    f = online_finding(d.t_s, d.measured, d.inputs, LineModel(cfg))
    assert [e["name"] for e in f.effects][:1] == ["feed_bias"]
    assert not any(s.get("kind") == "kernel_correction" for s in f.structure)
