"""Repeat pulses of one system (``twin_core.rtd.repeats``, ``quality.analysis.analyze_repeats``,
``twin rtd analyze A B ...``). References: the standard normal (Stouffer's Z is N(0, 1) under
the null and N(delta sqrt(k), 1) under a common shift delta); the inverse-variance estimator's
sampling distribution (normal, sd (sum w)^-1/2); virtual profiles from ``rtd.virtual`` (the
two-zone PDE, a code path apart from the fitted models)."""

import json

import numpy as np
import pytest
from scipy import stats

from services.cli.main import main
from twin_core.quality.analysis import analyze_repeats
from twin_core.rtd import virtual as V
from twin_core.rtd.profiles import from_arrays
from twin_core.rtd.repeats import (
    JointLackOfFit,
    combine_repeat_tests,
    joint_lack_of_fit,
    pool,
    stouffer,
)

T = np.arange(0.0, 251.0)


def test_stouffer_is_uniform_under_the_null_and_adds_up_a_common_misfit():
    """30,000 triples of uniform p-values: the combined p rejects at 5 % in 5 % (+/- 0.4, 3 sd)
    and is uniform (KS p > 0.001); three repeats of a one-sided z test with noncentrality 1.5
    each reject at the analytic Phi(1.5 sqrt(3) - 1.645) = 83.0 % (one repeat: 44.2 %)."""
    rng = np.random.default_rng(11)
    p = rng.uniform(size=(30_000, 3))
    comb = stouffer(p)  # each row
    assert comb[0] == stouffer(list(p[0]))
    assert abs(np.mean(comb < 0.05) - 0.05) < 0.004
    assert stats.kstest(comb, "uniform").pvalue > 1e-3
    z = rng.normal(1.5, 1.0, size=(30_000, 3))
    comb = stouffer(stats.norm.sf(z))
    expected = stats.norm.cdf(1.5 * np.sqrt(3) - stats.norm.isf(0.05))
    assert abs(np.mean(comb < 0.05) - expected) < 0.007
    assert stouffer([0.0, 0.5]) < 1e-6 and stouffer([1.0, 1.0]) > 0.999  # clipped, finite


def test_joint_lack_of_fit_combines_each_test_then_weighs_them(shape_exchange_lof):
    """Each test is combined over the repeats (Stouffer), then the tests by the single-record
    weighted Bonferroni (shape 0.2 %, exchange 0.8 % of 1 %): two repeats each at p = 0.02 on
    the exchange test are not flagged alone but are jointly (combined p = 0.0023 < 0.008)."""
    lof = shape_exchange_lof
    runs = [lof(0.4, 0.02), lof(0.6, 0.02)]
    assert all(r.adequate for r in runs)
    j = joint_lack_of_fit(runs)
    assert j.combined["exchange"] == pytest.approx(stats.norm.sf(2 * stats.norm.isf(0.02) / 2**0.5))
    assert j.levels == pytest.approx({"shape": 0.002, "exchange": 0.008})
    assert not j.adequate and j.worst == "exchange"
    assert JointLackOfFit.from_p_values({"shape": [0.4, 0.6]}).adequate
    # a repeat that kept the linearised tail test: combined with the others' exchange test
    mixed = combine_repeat_tests(
        [
            {"shape": 0.4, "exchange": 0.02},
            {"shape": 0.6, "tail": 0.02},
            {"shape": 0.5, "exchange": 0.3},
        ]
    )
    assert set(mixed.combined) == {"shape", "exchange"}
    assert mixed.per_repeat["exchange"] == (0.02, 0.02, 0.3)


def test_pooled_interval_covers_with_and_without_run_to_run_variation():
    """Three repeats with unequal standard errors (0.5, 1, 2): the Hartung-Knapp interval covers
    the common value in 95 % (+/- 1.1, 3 sd of 4,000 draws; measured 95.1 %); with a
    between-repeat sd of 3 the repeats are flagged as disagreeing in most draws and the interval
    covers in >= 90 % (measured 91.8 %; the fixed-effect interval covered 81 %). Two repeats by
    hand: Q = 2, tau^2 = 1, SE = 1, t_1 quantile 12.706."""
    rng = np.random.default_rng(5)
    s = np.array([0.5, 1.0, 2.0])
    p = pool([10.0, 12.0], [1.0, 1.0])
    assert (p.value, p.stderr, p.q, p.tau2) == pytest.approx((11.0, 1.0, 2.0, 1.0))
    assert p.ci == pytest.approx((11.0 - 12.7062, 11.0 + 12.7062), rel=1e-5)
    cover = [pool(rng.normal(20.0, s), s).ci for _ in range(4000)]
    assert abs(np.mean([lo <= 20.0 <= hi for lo, hi in cover]) - 0.95) < 0.011
    het = [pool(rng.normal(20.0, np.sqrt(s**2 + 9.0)), s) for _ in range(4000)]
    assert np.mean([not h.agree for h in het]) > 0.6
    assert np.mean([h.ci[0] <= 20.0 <= h.ci[1] for h in het]) >= 0.90
    with pytest.raises(ValueError, match="stderrs must be finite and > 0"):
        pool([1.0, 2.0], [1.0, 0.0])


@pytest.fixture(scope="module")
def zone_files(tmp_path_factory):
    """Two repeat pulses (5 g) of a blender with a stagnant zone exchanging with the flow
    (two-zone PDE: r = 0.3, tau_x = 25 s), seed noise: a misfit of AD that one record shows
    in about 72 % of draws (docs/rtd.md)."""
    c = V.pulse_concentration(V.dispersion_pde(T, 10.0, 14.0, 10.0, 0.3, 25.0), 5.0)
    d = tmp_path_factory.mktemp("repeats")
    paths = []
    for i in range(2):
        y, _ = V.measure(c, V.SEED_NOISE, np.random.default_rng([3, i]))
        p = d / f"pulse_{i + 1}.csv"
        p.write_text("time [s],concentration [% w/w]\n" + "\n".join(
            f"{a:g},{b:.5f}" for a, b in zip(T, y)) + "\n")  # fmt: skip
        paths.append(p)
    return paths


def test_cli_analyzes_repeat_pulses_jointly(zone_files, tmp_path, capsys):
    """``twin rtd analyze A B``: the joint verdict, pooled estimates with per-repeat values,
    CSV and figure; the AD fit of the zone profiles is flagged jointly with the combined test
    named, and the pooled mean residence time lies between the repeats'.
    ``--fit all`` is refused for repeats (one model is tested and pooled)."""
    out = tmp_path / "rep"
    assert main(["rtd", "analyze", *map(str, zone_files), "--out", str(out)]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["repeats"] == 2 and rep["model"] == "ad_open"
    j = rep["joint_lack_of_fit"]
    assert rep["adequate"] is False and j["p_value"] < 0.01
    assert set(j["tests"]) == {"shape", "exchange"}
    m = rep["pooled"]["mean_residence_time_s"]
    vals = [v for v, _ in m["per_repeat"]]
    assert min(vals) <= m["value"] <= max(vals)
    assert m["ci"][0] < m["value"] < m["ci"][1]
    assert (out / "repeats.csv").exists() and (out / "repeats.png").exists()
    printed = capsys.readouterr().out
    assert "does not fit the 2 repeats jointly" in printed
    assert main(["rtd", "analyze", *map(str, zone_files), "--fit", "all", "--out", str(out)]) == 2
    assert "--fit must name one model" in capsys.readouterr().err


def test_repeats_need_two_profiles_and_one_model():
    prof = from_arrays(T, np.zeros_like(T), name="x")
    with pytest.raises(ValueError, match="at least 2 repeats"):
        analyze_repeats([prof])
    with pytest.raises(ValueError, match="must name one model"):
        analyze_repeats([prof, prof], model="all")
