"""Velocity fields and the homogeneity index of particle attributes on sampling grids.

References: a rigid rotation ``v = omega x r`` about a cylinder's axis has tangential velocity
``omega r`` and no radial or axial component; a linear field ``v = G x + b`` averaged over a
cell equals the field at the cell's particle centroid; the homogeneity index (Windows-Yule et
al. 2022) of the height on a bed of equal layers is the standard deviation of the layer
heights, ``dz sqrt((n^2 - 1) / 12)``, and of an attribute spread at random it falls as
``sigma / sqrt(n)`` with ``n`` particles per cell.
"""

import numpy as np
import pytest

from twin_core.dem.frames import Frame
from twin_core.mixing.fields import (
    cell_means,
    homogeneity_index,
    homogeneity_series,
    velocity_fields,
)
from twin_core.mixing.grid import CylindricalGrid, GridSpec


def cylinder_bed(n, seed=0):
    rng = np.random.default_rng(seed)
    rho = 0.03 * np.sqrt(rng.random(n))
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), rng.uniform(0, 0.05, n)], axis=1)


def test_rigid_rotation_in_cylindrical_components():
    omega = 3.0
    pos = cylinder_bed(20_000)
    vel = np.cross([0.0, 0.0, omega], pos)
    frames = [Frame(float(t), np.arange(len(pos)), np.zeros(len(pos), int), np.full(len(pos), 5e-4),
                    pos, vel) for t in (0.0, 0.1)]  # fmt: skip
    grid = CylindricalGrid((0.0, 0.0), 0.03, 0.0, 0.05, (8, 4, 3))
    fields = velocity_fields(frames, grid)
    assert fields.labels == ("v_r", "v_theta", "v_z")
    _, rho, _ = grid.polar(pos)
    mean_rho, _ = cell_means(grid, pos, np.full(len(pos), 5e-4), rho)
    assert np.allclose(fields.mean[:, 1], omega * mean_rho, rtol=1e-12)
    assert np.allclose(fields.mean[:, [0, 2]], 0.0, atol=1e-12)
    assert fields.per_frame.shape == (2, grid.n_cells, 3)
    table = fields.mean_table(grid)
    assert list(table.columns[-3:]) == ["v_r_m_s", "v_theta_m_s", "v_z_m_s"]


@pytest.mark.parametrize("mapping", ["point", "fractional"])
def test_linear_field_cell_means_are_the_field_at_the_cell_centroid(mapping):
    rng = np.random.default_rng(1)
    n = 5000
    pos = rng.random((n, 3)) * 0.04
    radii = rng.uniform(3e-4, 9e-4, n)
    G = np.array([[0.0, 1.0, 0.0], [-2.0, 0.0, 0.5], [0.0, 0.0, 0.3]])
    vel = pos @ G.T + [0.1, 0.0, -0.2]
    grid = GridSpec((0, 0, 0), (0.04, 0.04, 0.04), (4, 4, 4))
    means, amount = cell_means(grid, pos, radii, vel, weight="volume", mapping=mapping)
    centroid, _ = cell_means(grid, pos, radii, pos, weight="volume", mapping=mapping)
    assert np.allclose(means, centroid @ G.T + [0.1, 0.0, -0.2], atol=1e-12)
    assert amount.sum() == pytest.approx(4 / 3 * np.pi * np.sum(radii**3))


def test_homogeneity_of_height_on_equal_layers():
    """A lattice of 6 equal layers, one layer per cell along z: the cell means of z are the
    layer heights, whose rms deviation from the bulk mean is dz sqrt((6^2 - 1) / 12)."""
    g = np.stack(np.meshgrid(np.arange(8), np.arange(8), np.arange(6), indexing="ij"), -1)
    pos = (g.reshape(-1, 3) + 0.5) * 0.002
    n = len(pos)
    frame = Frame(0.0, np.arange(n), np.zeros(n, int), np.full(n, 4e-4), pos, np.zeros((n, 3)))
    grid = GridSpec((0, 0, 0), (0.016, 0.016, 0.012), (2, 2, 6))
    hi = homogeneity_series([frame], ["z", "radius"], grid)
    assert hi["HI_z"].iloc[0] == pytest.approx(0.002 * np.sqrt(35 / 12), rel=1e-12)
    assert hi["HI_radius"].iloc[0] == pytest.approx(0.0, abs=1e-15)


def test_homogeneity_of_a_random_attribute_falls_as_one_over_root_n():
    rng = np.random.default_rng(2)
    pos = rng.random((64_000, 3))
    sigma = 2.0
    value = rng.normal(5.0, sigma, len(pos))
    grid = GridSpec((0, 0, 0), (1, 1, 1), (4, 4, 4))
    means, amount = cell_means(grid, pos, np.zeros(len(pos)), value)
    hi = homogeneity_index(means, value.mean())
    assert hi == pytest.approx(sigma / np.sqrt(amount.mean()), rel=0.25)
    with pytest.raises(ValueError, match="unknown attribute"):
        homogeneity_series([], ["colour"], grid)


def test_velocity_and_homogeneity_figures(tmp_path):
    """The cross-section figure of a rotating bed shows tangential arrows (perpendicular to the
    radius at every bin centre); the Cartesian figure averages over the thin axis."""
    import matplotlib.pyplot as plt

    from twin_core.mixing.plots import homogeneity_figure, save_figure, velocity_figure

    pos = cylinder_bed(20_000, seed=3)
    vel = np.cross([0.0, 0.0, 2.0], pos)
    n = len(pos)
    frames = [Frame(0.0, np.arange(n), np.zeros(n, int), np.full(n, 5e-4), pos, vel)]
    grid = CylindricalGrid((0.0, 0.0), 0.03, 0.0, 0.05, (8, 4, 5)).slab("z", 0.025, 0.01)
    fig = velocity_figure(velocity_fields(frames, grid), grid)
    q = fig.axes[0].collections[0]
    xy, uv = q.XY, np.stack([q.U, q.V], axis=1)
    assert np.allclose(np.sum(xy * uv, axis=1), 0.0, atol=1e-12)
    assert save_figure(fig, tmp_path / "v.png").stat().st_size > 5_000
    box = GridSpec((-0.03, -0.03, 0.0), (0.03, 0.03, 0.05), (6, 6, 1))
    fig = velocity_figure(velocity_fields(frames, box), box)
    assert len(fig.axes[0].collections[0].U) == 36  # every cell of the 6 x 6 plane holds particles
    plt.close(fig)
    hi = homogeneity_series(frames, ["radius", "speed"], box)
    assert save_figure(homogeneity_figure(hi), tmp_path / "h.png").stat().st_size > 5_000
