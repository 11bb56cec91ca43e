"""Size of the joint lack-of-fit test of repeat pulses (issue 36, item 7: "a three-repeat
analysis flagged a pure axial-dispersion repeat"). Pure repeats: records of one system with
independent noise; every flag is false. Reference: the truth is the open-open axial-dispersion
PDE (``rtd.virtual.dispersion_pde``, Table 6.2 parameters) and the noise the plant's NIR probe
(``plant.nir.add_nir_noise``: white, 1/f, proportional, Laplace outliers) at twice the seed's
level (``plant.nir.scaled_noise``), code paths apart from the fitted models and from the
likelihood's noise model. The full measurement (200 sets at the seed's noise and twice it, the
exchange test included) is ``benchmarks/rtd_repeat_size.py`` (docs/rtd.md)."""

import numpy as np

from schemas.line import NIRNoise
from twin_core.plant.nir import add_nir_noise, scaled_noise
from twin_core.plant.openworld_cases import clopper_pearson_upper
from twin_core.rtd import virtual as V
from twin_core.rtd.likelihood import fit_raw
from twin_core.rtd.repeats import joint_lack_of_fit

TABLE_6_2 = (11.92, 16.37, 7.67)
#: the seed of ``benchmarks/rtd_repeat_size.py``
BENCH_SEED = 20_261_208
#: the seed's tracer amounts, one per set in turn
AMOUNTS_G = (10.0, 7.5, 6.0, 5.0)


def _records(e: np.ndarray, amount_g: float, seed: list[int], k: int = 3) -> list[np.ndarray]:
    """``k`` records of a pulse of ``amount_g`` through the RTD ``e`` with the NIR probe's noise
    at twice the seed's level, seeded by ``seed`` + the repeat's index."""
    truth = V.pulse_concentration(e, amount_g)
    noise = scaled_noise(NIRNoise(), 2.0)
    return [add_nir_noise(truth, noise, np.random.default_rng([*seed, r]))[0] for r in range(k)]


def test_the_issues_pure_triple_is_not_flagged():
    """The benchmark's first set at twice the noise (10 g, 251 s): in its first repeat REML put
    the 1/f component at its bound under the spline alternative, and the shape test, whitening
    with white noise only and taking that component as known (Satterthwaite df 228), gave
    p = 1.5e-8 and the joint test p = 1.8e-3 with the exchange test (3e-5 without). A component
    at its bound keeps its sampling variance in the tests' df: the shape test's df falls to ~2,
    its p to ~0.09, and the triple passes."""
    t = np.arange(0.0, 251.0)
    ys = _records(V.dispersion_pde(t, *TABLE_6_2), 10.0, [BENCH_SEED, 20, 0])
    fits = [fit_raw(t, y, "ad_open", extension=False) for y in ys]
    shape = {x.name: x for x in fits[0].lack_of_fit.tests}["shape"]
    assert fits[0].lack_of_fit.noise.pink_var < 1e-4  # the 1/f component at its bound
    assert shape.p_value > 0.01 and shape.df[1] < 10
    assert joint_lack_of_fit([f.lack_of_fit for f in fits]).adequate


def test_joint_test_keeps_its_size_on_pure_repeats():
    """14 sets of three pure repeats at twice the seed's noise (10 / 7.5 / 6 / 5 g in turn, 126
    samples at 2 s; AD fitted with the shape and linearised tail tests: the exchange extension
    is the benchmark's part, too slow here): the joint test at 1 % flags at most 1 (now 0,
    Clopper-Pearson 95 % upper bound 19 %; before: 3 of 14, joint p 1.4e-3, 1.9e-5 and 3.3e-3,
    each with a repeat whose 1/f component sat at its bound; over sets 0-29: 4 of 30 before,
    0 after)."""
    t = np.arange(0.0, 251.0, 2.0)
    e = V.dispersion_pde(t, *TABLE_6_2)
    flagged = 0
    for s in range(14):
        ys = _records(e, AMOUNTS_G[s % 4], [36, s])
        fits = [fit_raw(t, y, "ad_open", extension=False) for y in ys]
        flagged += not joint_lack_of_fit([f.lack_of_fit for f in fits]).adequate
    bound = clopper_pearson_upper(flagged, 14)
    assert flagged <= 1, f"{flagged} of 14 pure sets flagged (95 % upper bound {bound:.1%})"
