"""Real lab files: columns, units, delimiters, baselines, signals that never return, PAT
windows relative to the profile, preprocessing options."""

import numpy as np
import pytest

from twin_core.rtd import truncation as TR
from twin_core.rtd.models import axial_dispersion_open
from twin_core.rtd.pipeline import Preprocessing, parse_baseline, preprocess
from twin_core.rtd.profiles import canonical_conc_unit, canonical_time_unit, from_arrays, load_csv

T = np.arange(0.0, 251.0)
E = axial_dispersion_open(T, 11.92, 16.37, 7.67)


def _write(path, header, rows, sep=","):
    path.write_text(header + "\n" + "\n".join(sep.join(r) for r in rows) + "\n")
    return path


def test_header_units_and_conversion(tmp_path):
    """`Time (min),API (%w/w)`: minutes to s, % w/w kept; mg/g x 0.1 and fraction x 100 to
    % w/w; every source unit recorded in meta."""
    rows = [(f"{t / 60:.6f}", f"{10 + 100 * e:.6f}") for t, e in zip(T, E)]
    p = load_csv(_write(tmp_path / "a.csv", "Time (min),API (%w/w)", rows))
    assert p.t[60] == pytest.approx(60.0, abs=1e-3) and p.conc_unit == "% w/w"
    assert p.meta["source_time_unit"] == "min" and p.meta["conc_column"] == "API"
    rows = [(f"{t:g}", f"{1000 * e:.6f}") for t, e in zip(T, E)]
    q = load_csv(_write(tmp_path / "b.csv", "time [s],tracer [mg/g]", rows))
    np.testing.assert_allclose(q.c, 100 * E, rtol=1e-5, atol=1e-6)
    rows = [(f"{t / 3600:.8f}", f"{e:.8f}") for t, e in zip(T, E)]
    r = load_csv(_write(tmp_path / "c.csv", "t [h],x [fraction]", rows))
    np.testing.assert_allclose(r.c, 100 * E, rtol=1e-5, atol=1e-6)
    assert r.t[-1] == pytest.approx(250.0, abs=1e-3)


def test_columns_by_name_or_number_and_delimiters(tmp_path):
    """Semicolons with decimal commas; three columns chosen by name or by number (from 1);
    headerless files with the units given."""
    rows = [(f"{t:g}".replace(".", ","), "1,5", f"{e:.6f}".replace(".", ",")) for t, e in zip(T, E)]
    f = _write(tmp_path / "eu.csv", "Zeit (s);Temp (C);API (%)", rows, sep=";")
    with pytest.raises(ValueError, match="ambiguous among \\['Temp', 'API'\\]"):
        load_csv(f)
    a = load_csv(f, time_col="Zeit", conc_col="API")
    b = load_csv(f, time_col=1, conc_col="3")
    np.testing.assert_allclose(a.c, E, atol=1e-6)
    np.testing.assert_array_equal(a.c, b.c)
    with pytest.raises(ValueError, match="column 'Flow' is not in the header"):
        load_csv(f, conc_col="Flow")
    with pytest.raises(ValueError, match="column number must be 1..3, got 7"):
        load_csv(f, conc_col=7)
    bare = _write(tmp_path / "bare.csv", "0,0", [(f"{t:g}", f"{e:g}") for t, e in zip(T, E)][1:])
    with pytest.raises(ValueError, match="time_unit is not declared"):
        load_csv(bare)
    assert load_csv(bare, time_unit="s", conc_unit="%").t.size == T.size


def test_units_refused_and_spellings():
    """Accepted spellings map to one unit each; unknown units are refused naming them."""
    assert {canonical_conc_unit(u) for u in ("%w/w", "w/w %", "wt%", "% (w/w)")} == {"% w/w"}
    assert canonical_conc_unit("g/g") == "fraction" and canonical_time_unit("Minutes") == "min"
    with pytest.raises(ValueError, match="got 'ppm'"):
        canonical_conc_unit("ppm")
    with pytest.raises(ValueError, match="time unit must be one of s, ms, min, h, got 'd'"):
        canonical_time_unit("d")


def test_signal_that_never_returns_is_named():
    """A step (never back) and a record cut on the tail are refused with the signal's name;
    a profile on a constant offset passes."""
    step = 10.0 + 2.0 * (T > 40)
    with pytest.raises(ValueError, match="API does not return to its baseline"):
        TR.baseline_windows(T, step, "API")
    cut = E[:40] * 100
    with pytest.raises(ValueError, match="API does not return to its baseline within the record"):
        TR.baseline_windows(T[:40], cut, "API")
    w = TR.baseline_windows(T, 10.0 + 100 * E, "API")
    assert w.post.any() and w.height == pytest.approx(100 * E.max(), rel=0.02)
    late = TR.baseline_windows(T, 10.0 + 100 * np.interp(T - 40.0, T, E, left=0.0), "API")
    assert late.pre.any() and late.post.any() and not (late.pre & late.post).any()


def test_pat_window_relative_to_the_profile():
    """A 120 s record (the seed's absolute window t >= 120 s would be empty) gets a window
    starting 5 FWHM after the peak; the PAT level with the default k = 3 is mu + 3 sigma of
    that window."""
    t = T[:121]
    rng = np.random.default_rng(0)
    y = 100 * E[:121] + rng.normal(0, 0.1, t.size)
    w = TR.baseline_windows(t, y)
    assert w.t_post == pytest.approx(w.t_peak + TR.BASELINE_FWHM * w.fwhm)
    assert w.t_post < 120 and w.post.sum() >= TR.MIN_BASELINE_SAMPLES
    lvl, mu, sd = TR.pat_level(t, y)
    assert lvl == pytest.approx(mu + TR.PAT_K * sd)
    assert 0.0 < sd < 0.3
    assert TR.parse_spec("pat") == TR.TruncationSpec("pat", 3.0)
    with pytest.raises(ValueError, match="t_baseline leaves 0 baseline samples"):
        TR.pat_level(t, y, 3.0, 130.0)


def test_preprocessing_baselines():
    """--baseline auto estimates the offset (and says when the profile does not return to
    zero), a number is subtracted as given, none leaves the profile; bad values fail."""
    rng = np.random.default_rng(1)
    prof = from_arrays(T, 10.0 + 100 * E + rng.normal(0, 0.1, T.size), name="API")
    auto = preprocess(prof, Preprocessing(baseline="auto"))
    assert auto.baseline == pytest.approx(10.0, abs=0.05)
    assert "does not return to zero" in auto.notes[0]
    given = preprocess(prof, Preprocessing(denoise=None, truncate=None, baseline=9.5))
    assert given.baseline == 9.5 and given.baseline_source == "given"
    none = preprocess(prof, Preprocessing.none())
    np.testing.assert_array_equal(none.y, prof.c)
    assert parse_baseline(" 2.5 ") == 2.5
    with pytest.raises(ValueError, match="baseline must be auto, none or a number"):
        Preprocessing(baseline="zero")
