"""Definitive screening designs (Jones & Nachtsheim 2011, 2017) against the seed's Table 3.2."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from twin_core.calibration import (
    SEED_FACTORS,
    SEED_LEVELS,
    coded_to_physical,
    conference_matrix,
    correlation_map,
    definitive_screening_design,
    dsd_properties,
    load_seed_table,
    physical_to_coded,
)


@pytest.mark.parametrize("n", [2, 4, 6, 8, 10, 12, 14, 18, 20, 26, 28])
def test_conference_matrix_definition(n):
    """Conference matrix: zero diagonal, +-1 off it, C^T C = (n-1) I (Paley 1933)."""
    c = conference_matrix(n)
    assert np.array_equal(c.T @ c, (n - 1) * np.eye(n, dtype=int))
    assert np.all(np.diag(c) == 0)
    assert np.all(np.abs(c[~np.eye(n, dtype=bool)]) == 1)


def test_conference_matrix_rejects_unconstructible_order():
    with pytest.raises(ValueError, match="n must be"):
        conference_matrix(16)


def test_seed_design_structure_21_runs_8_factors():
    """Table 3.2: 21 runs = 2*8 + 1 + 4 (Jones & Nachtsheim 2017), 10 fold-over pairs and one
    centre run, each factor at its middle level in exactly 3 runs; our design matches."""
    d = definitive_screening_design(SEED_LEVELS)
    assert d.n_runs == 21 and d.conference_order == 10 and d.n_fake == 2
    seed = physical_to_coded(load_seed_table("dsd")[SEED_FACTORS], SEED_LEVELS)
    for design in (d.coded, seed):
        x = design.to_numpy()
        assert x.shape == (21, 8)
        assert set(np.unique(x)) == {-1, 0, 1}
        assert np.all((x == 0).sum(axis=0) == 3)
        centre = np.all(x == 0, axis=1)
        assert centre.sum() == 1
        rest = x[~centre]
        pairs = sum(
            1 for i in range(20) for j in range(i + 1, 20) if np.array_equal(rest[i], -rest[j])
        )
        assert pairs == 10
    # physical levels of our design are exactly the seed's levels
    assert set(np.unique(d.physical["PP_RF"])) == {0.01, 0.04, 0.1}
    # the |r| colour maps (Fig. 3.4) of our design and the seed's design are the same multiset
    a = np.sort(correlation_map(d.coded).to_numpy().ravel())
    b = np.sort(correlation_map(seed).to_numpy().ravel())
    assert np.allclose(a, b, atol=1e-12)


@pytest.mark.parametrize("m", [2, 3, 4, 5, 6, 7, 8, 9, 10, 12])
def test_dsd_orthogonality_properties(m):
    """Main effects orthogonal to each other and to all two-factor interactions and
    quadratics; no 2FI completely confounded (|r| < 1); run counts 2m+5 / 2m+7 (odd m)."""
    d = definitive_screening_design(m)
    assert d.n_runs == (2 * m + 5 if m % 2 == 0 else 2 * m + 7)
    props = dsd_properties(d.coded)
    assert props["main_main"] < 1e-12
    assert props["main_2fi"] < 1e-12
    assert props["main_quad"] < 1e-12
    assert props["2fi_2fi"] < 1.0 - 1e-9
    assert props["quad_quad"] < 1.0 - 1e-9
    d0 = definitive_screening_design(m, extra_runs=False)
    assert d0.n_runs == (2 * m + 1 if m % 2 == 0 else 2 * m + 3)


def test_coded_physical_round_trip_and_randomisation():
    d = definitive_screening_design(SEED_LEVELS, randomize=True, seed=3)
    back = physical_to_coded(d.physical, SEED_LEVELS)
    assert np.allclose(back.to_numpy(), d.coded.to_numpy())
    d2 = definitive_screening_design(SEED_LEVELS, randomize=True, seed=3)
    assert d.coded.equals(d2.coded)
    # two-level bounds get the midpoint
    d3 = definitive_screening_design({"a": (0.0, 2.0), "b": (1.0, 5.0)})
    assert set(np.unique(d3.physical["a"])) == {0.0, 1.0, 2.0}
    phys = coded_to_physical(pd.DataFrame({"a": [-0.5]}), {"a": (0.0, 1.0, 4.0)})
    assert phys["a"].iloc[0] == pytest.approx(0.5)


@pytest.mark.parametrize(
    "factors, match",
    [
        (1, "factors must be >= 2"),
        ({"a": (1, 0, 2), "b": (0, 1)}, "levels of 'a'"),
        (["a", "a"], "distinct"),
    ],
)
def test_bad_design_requests(factors, match):
    with pytest.raises(ValueError, match=match):
        definitive_screening_design(factors)
