"""Loader/validator of the grid-field npz format (twin_core.compartment.fields)."""

import numpy as np
import pytest

from twin_core.compartment import (
    load_fields,
    save_fields,
    synthetic_blender_fields,
    validate_fields,
)


@pytest.fixture(scope="module")
def case():
    return synthetic_blender_fields(5, 6, 6)


def test_roundtrip(tmp_path, case):
    path = save_fields(tmp_path / "f.npz", case.fields)
    f = load_fields(path)
    assert f.shape == (5, 6, 6)
    assert f.periodic == (True, False, False)
    np.testing.assert_array_equal(f.velocity, case.fields.velocity)
    for a, b in zip(f.crossings, case.fields.crossings):
        np.testing.assert_array_equal(a, b)
    assert f.holdup_kg.sum() == pytest.approx(case.fields.holdup_kg.sum())
    # cell volumes tile the box
    assert f.cell_volume.sum() == pytest.approx(0.04 * 0.08 * 0.08)


def test_without_crossings(case):
    d = case.fields.to_dict()
    for k in ("crossings_x", "crossings_y", "crossings_z"):
        d.pop(k)
    assert not validate_fields(d).has_crossings


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda d: d.pop("velocity"), "missing key 'velocity'"),
        (lambda d: d.__setitem__("velocity", np.zeros((5, 6, 6))), "'velocity' must have shape"),
        (lambda d: d.__setitem__("occupancy", -np.ones((5, 6, 6))), "'occupancy' must be >= 0"),
        (lambda d: d.__setitem__("solid_fraction", -np.ones((5, 6, 6))), "'solid_fraction'"),
        (lambda d: d.__setitem__("duration_s", 0.0), "'duration_s' must be > 0"),
        (lambda d: d.__setitem__("x_edges", np.array([0.0, 1.0, 0.5, 2, 3, 4])), "increasing"),
        (lambda d: d.pop("crossings_y"), "missing \\['crossings_y'\\]"),
        (lambda d: d.__setitem__("crossings_z", np.ones((5, 6, 6, 2))), "'crossings_z': axis 2"),
        (lambda d: d.__setitem__("periodic", np.array([True, False])), "'periodic'"),
        (lambda d: d["velocity"].__setitem__((0, 0, 0, 0), np.nan), "non-finite"),
    ],
)
def test_bad_input_names_the_key(case, mutate, match):
    d = {
        k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in case.fields.to_dict().items()
    }
    mutate(d)
    with pytest.raises(ValueError, match=match):
        validate_fields(d)


def test_missing_file(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        load_fields(tmp_path / "nope.npz")
