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


def test_mirror_axis_is_an_involution_and_keeps_the_physics():
    """Reversing x twice gives the fields back; a mirrored field still balances every cell
    (discrete divergence 0) and the model orients itself along the net flow, giving the same
    RTD (the physics does not depend on the axis direction)."""
    from twin_core.compartment import CompartmentModel
    from twin_core.compartment.fields import mirror_axis
    from twin_core.compartment.synthetic import cell_divergence

    case = synthetic_blender_fields(5, 6, 6)
    m = mirror_axis(case.fields, 0)
    k = m.particle_mass_kg / m.duration_s
    assert np.abs(cell_divergence(tuple(c * k for c in m.crossings), m.periodic)).max() < 1e-15
    back = mirror_axis(m, 0)
    for a, b in zip(back.crossings, case.fields.crossings):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(back.velocity, case.fields.velocity)
    a = CompartmentModel().fit(case.fields)
    b = CompartmentModel().fit(m)
    assert not a.mirrored_ and b.mirrored_
    t = np.linspace(0, 40, 801)
    np.testing.assert_allclose(
        b.section_.impulse_response(t), a.section_.impulse_response(t), atol=1e-12
    )
    with pytest.raises(ValueError, match="axis must be"):
        mirror_axis(m, 3)
