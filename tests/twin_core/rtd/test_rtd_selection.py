"""Model choice that cannot run away (``rtd.likelihood`` ranking, ``rtd.derived`` averaging).

Truths are computed apart from the fitted model functions: axial dispersion from the PDE
(``rtd.virtual``), a CSTR after a plug-flow delay as its closed form written here
(Levenspiel 1999 ch. 12); noise is the seed's PAT noise (``rtd.virtual.measure``).
"""

import numpy as np
import pytest

from twin_core.rtd import virtual as V
from twin_core.rtd.derived import Estimate, model_average, model_grid, moment_estimates
from twin_core.rtd.likelihood import fit_candidates, fit_raw
from twin_core.rtd.models import get_model, record_bounds

T = np.arange(0.0, 251.0)
AD = (11.92, 16.37, 7.67)
#: Table 6.2's mean residence time, tau_d + tau (1 + 2 / Pe)
AD_MRT = AD[0] + AD[1] * (1 + 2 / AD[2])


@pytest.fixture(scope="module")
def drifting():
    """AD (Table 6.2, 10 g) whose baseline rises by 0.4 % w/w with a 60 s time constant, as an
    NIR probe warming up: back at a (new) baseline within the profile checks' tolerance."""
    c = V.pulse_concentration(V.dispersion_pde(T, *AD, nodes=200), 10.0)
    y, _ = V.measure(c, V.SEED_NOISE, np.random.default_rng(0))
    return y + 0.4 * (1.0 - np.exp(-T / 60.0))


def _mrt(fit) -> float:
    return moment_estimates(fit, model_grid(fit, T))["mean_residence_time_s"].value


def test_drifting_baseline_selects_no_runaway_model(drifting):
    """The drift was taken for a bypass whose CSTR has a time constant of 9.8e5 s carrying
    99.9 % of the flow, ranked first, mean residence time ~1e6 s (before). Time constants are
    bounded by twice the record (500 s); the bypass sits on that bound and is not selected;
    tanks in series are, with a mean residence time within 5 % of the truth."""
    r = fit_candidates(T, drifting, ["tis", "ad_open_bypass"])
    assert T[0] < _mrt(r.best) < T[-1]
    assert _mrt(r.best) == pytest.approx(AD_MRT, rel=0.05)
    assert "tau_bypass" in r.excluded["ad_open_bypass"]
    row = {x["model"]: x for x in r.as_dict()["ranking"]}["ad_open_bypass"]
    assert row["selectable"] is False and "bound" in row["not_selected_because"]


def test_bound_hitting_model_is_reported_not_selected(drifting):
    """Against a worse family (EMG) the bound-hitting bypass has the lower BIC: it is still
    not selected, and the analysis says why (before: the bypass was selected)."""
    from twin_core.rtd.pipeline import fit_profile
    from twin_core.rtd.profiles import from_arrays

    r = fit_candidates(T, drifting, ["emg", "ad_open_bypass"])
    assert r.fits[0].model == "ad_open_bypass" and r.best.model == "emg"
    bypass = r.fits[0]
    assert bypass.on_bound == {"tau_bypass": pytest.approx(2.0 * (T[-1] - T[0]))}
    s = fit_profile(from_arrays(T, drifting), ["emg", "ad_open_bypass"])
    assert s.fit.model == "emg"
    assert any("ad_open_bypass" in w and "not selected" in w for w in s.warnings)


def test_degenerate_delay_interval_is_the_profile_likelihoods():
    """A CSTR after a plug-flow delay (10.3 s, 20 s): the delay moves the exponential exactly
    as the amplitude scales it, so only the jump carries the delay; the fit sat at a sample
    time with a Wald interval of width 2e-6 s that missed the truth by 0.7-1.7 s (before).
    The interval is now the profile likelihood's, about one sampling step wide, and covers."""
    tp, tc = 10.3, 20.0
    e = np.where(T >= tp, np.exp(-(T - tp) / tc) / tc, 0.0)
    c = V.pulse_concentration(e, 10.0)
    for seed in (1, 2):
        y, _ = V.measure(c, V.SEED_NOISE, np.random.default_rng(seed))
        f = fit_raw(T, y, "cstr_pfr")
        lo, hi = f.ci["tau_pfr"]
        assert lo <= tp <= hi
        assert 0.5 < hi - lo < 5.0
        assert "tau_pfr" in f.profile_ci and f.identified


def test_record_bounds():
    """Time constants within half a step and twice the record, delays up to its end;
    dimensionless parameters keep the model's bounds."""
    lo, hi = record_bounds(get_model("ad_open_bypass"), np.arange(10.0, 110.0, 0.5))
    names = get_model("ad_open_bypass").params
    b = dict(zip(names, zip(lo, hi)))
    assert b["tau_d"] == (0.0, 109.5)
    assert b["tau"] == (0.25, 199.0) and b["tau_bypass"] == (0.25, 199.0)
    assert b["pe"] == (1e-3, np.inf) and b["fraction"] == (0.0, 1.0)
    lo, hi = record_bounds(get_model("emg"), np.arange(0.0, 101.0))
    assert (lo[0], hi[0]) == (-100.0, 100.0)


def test_model_average():
    """One model of weight 1 gives its own interval back; two models that disagree give an
    interval that holds both estimates, with the unconditional standard error
    sqrt(sum w (se^2 + (g - g_bar)^2)) (Burnham & Anderson 2002)."""
    z = 1.959963984540054
    a = Estimate(30.0, 1.0, (30.0 * np.exp(-z / 30), 30.0 * np.exp(z / 30)))
    b = Estimate(40.0, 1.0, (40.0 * np.exp(-z / 40), 40.0 * np.exp(z / 40)))
    one = model_average([a, b], [1.0, 0.0])
    assert one.value == 30.0 and one.ci == pytest.approx(a.ci, rel=1e-6)
    both = model_average([a, b], [0.5, 0.5])
    assert both.value == pytest.approx(35.0)
    assert both.stderr == pytest.approx(np.sqrt(1.0 + 25.0))
    assert both.ci[0] < 30.0 and both.ci[1] > 40.0
    with pytest.raises(ValueError):
        model_average([a], [0.0])
