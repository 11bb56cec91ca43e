"""Every remaining bad-input path raises ValueError naming the field (developers' guide)."""

import numpy as np
import pytest

from twin_core.quality import funnel as QF
from twin_core.rtd import convolution as C
from twin_core.rtd import denoise as D
from twin_core.rtd import metrics as MT
from twin_core.rtd import noise as N
from twin_core.rtd import stats as S
from twin_core.rtd import truncation as TR
from twin_core.rtd.fitting import fit
from twin_core.rtd.models import axial_dispersion_open
from twin_core.rtd.outliers import hampel
from twin_core.rtd.profiles import load_csv
from twin_core.rtd.synthetic import generate_run

T = np.arange(0.0, 100.0, 0.5)
E = axial_dispersion_open(T, 11.92, 16.37, 7.67)
Y = E / E.max() + np.random.default_rng(0).normal(0, 0.01, T.size)

CASES = [
    (lambda: N.white_noise(10, -1.0), "std must be >= 0"),
    (lambda: N.pink_noise(1, 1.0), "n must be >= 2"),
    (lambda: N.synthesize(E, proportional=-0.1), "proportional must be >= 0"),
    (lambda: N.characterize(T, Y, Y[:-1]), "equal shape"),
    (lambda: QF.funnel(T, E, durations=[-1.0, 2.0]), "durations must be finite and >= 0"),
    (lambda: QF.funnel(T, E, intensities=[-1.0, 2.0]), "intensities must be >= 0"),
    (lambda: QF.funnel(T, E, durations=[1.0]), "durations and intensities must be 1-D"),
    (lambda: fit(T, Y, sigma=np.zeros_like(Y)), "sigma must be positive"),
    (lambda: fit(T, Y, alpha=1.5), "alpha must be in"),
    (lambda: S.compare_groups({"a": [1.0, 2.0]}), "at least|>= 2 groups"),
    (lambda: S.letters_from_pvalues(np.ones((2, 3))), "square matrix"),
    (lambda: generate_run(0.0, 1, np.random.default_rng(0)), "amount_g must be > 0"),
    (lambda: C.parallel([1.0], E, E), "one entry per RTD"),
    (lambda: C.parallel([0.5, 0.5], E, E[:-1]), "share one shape"),
    (lambda: C.frequency_response(T[::-1], E, [0.1]), "strictly increasing"),
    (lambda: TR.trim(T, E, end_loss=0.7), "end_loss must be in"),
    (lambda: TR.truncate_level(E, -1.0), "level must be finite and >= 0"),
    (lambda: TR.truncate_time(T, E, np.inf), "t_cut must be finite"),
    (lambda: TR.two_peak_profiles(T, main=(30.0, 0.0, 1.0)), "width must be > 0"),
    (lambda: TR.pat_level(T, E, -1.0, 50.0), "k must be >= 0"),
    (lambda: MT.denoise_metrics(T, Y, Y[:-1]), "denoised must have the shape"),
    (lambda: MT.fwhm(T, -np.abs(Y)), "positive maximum"),
    (lambda: hampel(Y, t=T[:-1]), "t must have the shape"),
    (lambda: hampel(Y, n_sigma=0), "n_sigma must be > 0"),
    (lambda: D.ebayes_posterior_median(Y, prior="gauss"), "prior must be"),
    (lambda: D.threshold_from_weight(0.0), "w must be in"),
    (lambda: D.wavelet(Y, level=0), "level must be >= 1"),
    (lambda: D.wavelet(Y, method="magic"), "method must be"),
    (lambda: D.wavelet(Y, mode="x", method="sure"), "mode must be"),
    (lambda: D.wavelet(Y, noise="x"), "noise must be"),
    (lambda: D.sliding_average(Y, 0), "window must be in"),
    (lambda: D.savitzky_golay(Y, 11, 11), "order must be in"),
    (lambda: D.savitzky_golay(Y[:9], 11), "window must be <= len"),
    (lambda: D.auto_fft(Y, sigma=0.0), "sigma must be > 0"),
]


@pytest.mark.parametrize("call,msg", CASES, ids=[m for _, m in CASES])
def test_error_paths(call, msg):
    """Each call raises ValueError with a message naming the offending field."""
    with pytest.raises(ValueError, match=msg):
        call()


def test_csv_errors(tmp_path):
    """Empty files, non-numeric cells and malformed headers are reported, naming line and column."""
    empty = tmp_path / "empty.csv"
    empty.write_text("# only a comment\n")
    with pytest.raises(ValueError, match="holds no rows"):
        load_csv(empty)
    bad = tmp_path / "bad.csv"
    bad.write_text("time [s],concentration [%]\n1,2\nx,3\n")
    with pytest.raises(ValueError, match=r"line 3, column 1 \(time \[s\]\): 'x' is not a number"):
        load_csv(bad)
    hdr = tmp_path / "hdr.csv"
    hdr.write_text("time [s],3concentration\n1,2\n")
    with pytest.raises(
        ValueError, match="line 1, column 2: header cell .* is not 'name \\[unit\\]'"
    ):
        load_csv(hdr)
