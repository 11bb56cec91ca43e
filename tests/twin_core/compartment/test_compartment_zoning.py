"""Zoning and compartment maps (chapter 5.2.3 / 5.3.1-5.3.2)."""

import numpy as np
import pytest
from scipy import ndimage

from twin_core.compartment import CompartmentModel, synthetic_blender_fields
from twin_core.compartment.zoning import (
    combine_zones,
    compartment_slices,
    merge_small,
    overlay_maps,
    sign_zones,
    slice_components,
    threshold_zones,
)


def test_sign_zones_with_tolerance_band():
    """Seed 5.2.3: +1 above, -1 below the band, 0 inside, -2 empty."""
    v = np.array([-1.0, -0.1, -0.05, 0.0, 0.05, 0.1, 1.0])
    mask = np.ones(7, bool)
    mask[3] = False
    z = sign_zones(v, 0.1, mask)
    np.testing.assert_array_equal(z, [-1, 0, 0, -2, 0, 0, 1])
    # several thresholds generalise the sign zones
    w = np.array([-1.0, -0.09, 0.0, 0.09, 1.0])  # off the band edges
    m = np.ones(5, bool)
    np.testing.assert_array_equal(threshold_zones(w, [-0.1, 0.1], m), sign_zones(w, 0.1, m) + 1)
    with pytest.raises(ValueError, match="tol must be >= 0"):
        sign_zones(v, -1.0, mask)
    with pytest.raises(ValueError, match="strictly increasing"):
        threshold_zones(v, [0.1, -0.1], mask)


def test_slice_components_split_disconnected_zones():
    """A zone in two disconnected pieces gives two compartments; slices are labelled apart."""
    z = np.full((2, 5, 5), -1, dtype=np.int8)
    z[:, :, :] = -1
    z[:, 0:2, :] = 1
    z[:, 3:5, :] = 1  # separated from the first +1 piece by the -1 row 2
    z[1, 4, 4] = -2
    lab = slice_components(z, axis=0)
    assert lab.max() + 1 == 6  # per slice: two +1 pieces, one -1 row
    sl = compartment_slices(lab, axis=0)
    np.testing.assert_array_equal(sl, [0, 0, 0, 1, 1, 1])
    assert lab[1, 4, 4] == -1
    # every compartment is one connected region of one zone
    for c in range(lab.max() + 1):
        cells = lab == c
        assert len(np.unique(z[cells])) == 1
        assert ndimage.label(cells[sl[c]])[1] == 1


def test_overlay_is_intersection_of_maps():
    """Overlay of a left/right Y map and a top/bottom Z map gives the four quadrants."""
    shape = (1, 6, 6)
    y = np.zeros(shape, int)
    y[:, 3:, :] = 1
    z = np.zeros(shape, int)
    z[:, :, 3:] = 1
    lab = overlay_maps([y, z])
    assert lab.max() + 1 == 4
    for c in range(4):
        cells = lab == c
        assert cells.sum() == 9
        assert len(np.unique(y[cells])) == 1 and len(np.unique(z[cells])) == 1
    # combine_zones: empty in one map is empty
    y2 = y.copy()
    y2[0, 0, 0] = -2
    assert combine_zones([y2, z])[0, 0, 0] == -2


def test_merge_small_keeps_connected_compartments():
    lab = np.zeros((1, 4, 4), np.int32)
    lab[0, 1, 1] = 1  # a one-cell island inside compartment 0
    lab[0, 3, :] = 2
    out = merge_small(lab, 2)
    assert out.max() + 1 == 2
    assert out[0, 1, 1] == out[0, 0, 0]
    with pytest.raises(ValueError, match="min_cells"):
        merge_small(lab, 0)


def test_model_compartments_are_connected_and_homogeneous():
    """Without merging, each compartment is connected within its slice and has one zone tuple."""
    case = synthetic_blender_fields(4, 10, 10)
    m = CompartmentModel(min_cells=1).fit(case.fields)
    lab = m.labels_
    assert np.all((lab >= 0) == m.mask_)
    zones = np.stack([m.zones_[v] for v in m.variables], -1)
    for c in range(m.n_compartments_):
        cells = lab == c
        i = m.slice_index_[c]
        assert cells[i].sum() == cells.sum()
        assert ndimage.label(cells[i])[1] == 1
        assert len(np.unique(zones[cells], axis=0)) == 1
    merged = CompartmentModel(min_cells=4).fit(case.fields)
    assert merged.n_compartments_ < m.n_compartments_
    sizes = np.bincount(merged.labels_[merged.labels_ >= 0])
    # only compartments without a neighbour in their slice may stay below the minimum
    assert np.mean(sizes >= 4) > 0.95


def test_model_rejects_bad_parameters():
    case = synthetic_blender_fields(3, 5, 5)
    with pytest.raises(ValueError, match="variables must be among"):
        CompartmentModel(variables=("vq",)).fit(case.fields)
    with pytest.raises(ValueError, match="flow_source"):
        CompartmentModel(flow_source="magic").fit(case.fields)
    with pytest.raises(ValueError, match="tol_fraction"):
        CompartmentModel(tol_fraction=1.5).fit(case.fields)


def test_model_with_thresholds_and_other_variables():
    """Zones by several thresholds of several variables (5.2.3 generalised): a speed split in
    three bands and the occupancy in two give zone tuples; every compartment holds one tuple."""
    case = synthetic_blender_fields(4, 8, 8)
    speed_th = list(
        np.quantile(np.linalg.norm(case.fields.velocity, axis=-1)[case.mask], [0.3, 0.7])
    )
    m = CompartmentModel(
        variables=("speed", "occupancy"),
        thresholds={"speed": speed_th},
        min_cells=1,
    ).fit(case.fields)
    assert set(np.unique(m.zones_["speed"][m.mask_])) == {0, 1, 2}
    zones = np.stack([m.zones_["speed"], m.zones_["occupancy"]], -1)
    for c in range(m.n_compartments_):
        assert len(np.unique(zones[m.labels_ == c], axis=0)) == 1
