"""Sampling that follows the particles and the equipment: exact sphere-box volumes, fractional
(volume-split) mapping, cylindrical bins, slabs, the minimum-fill rule and species splits.

References: the analytic volumes of a ball cut by planes (cap ``pi (1 - a)^2 (2 + a) / 3``,
octant ``pi / 6``, segment between two planes ``pi (R^2 t - t^3 / 12)``), an independent
numerical integration of chord lengths (scipy ``quad``), symmetry (a sphere on a face or a
corner splits into equal parts) and the cell volumes of an annulus sector.
"""

import math

import numpy as np
import pytest
from scipy.integrate import quad

from twin_core.mixing.grid import (
    CylindricalGrid,
    GridSpec,
    cell_amounts,
    occupied_cells,
    parse_bins,
    sphere_volumes,
)
from twin_core.mixing.overlap import BALL, ball_quadrature, box_volume, orthant_volume
from twin_core.mixing.species import split_species

INF = np.inf


def cap(a):
    return math.pi * (1 - a) ** 2 * (2 + a) / 3


def test_ball_volumes_cut_by_planes_are_analytic():
    assert orthant_volume(0.0, 0.0, 0.0) == pytest.approx(math.pi / 6, abs=1e-14)
    assert orthant_volume(-INF, 0.0, 0.0) == pytest.approx(math.pi / 3, abs=1e-14)
    assert orthant_volume(-INF, -INF, -INF) == pytest.approx(BALL, abs=1e-14)
    for a in (-0.9, -0.3, 0.0, 0.45, 0.99):
        assert orthant_volume(a, -INF, -INF) == pytest.approx(cap(a), abs=1e-14)
        assert orthant_volume(-INF, -INF, a) == pytest.approx(cap(a), abs=1e-14)
    assert box_volume(-INF, -INF, -0.2, INF, INF, 0.3) == pytest.approx(cap(-0.2) - cap(0.3))
    assert box_volume(-2, -2, -2, 2, 2, 2) == pytest.approx(BALL, abs=1e-13)
    assert orthant_volume(0.6, 0.6, 0.6) == 0.0  # the corner lies outside the ball


def _chord_volume(lo, hi):
    """|B ∩ box| by integrating the chord length of the ball along z over (x, y)."""

    def chord(y, x):
        h = 1 - x * x - y * y
        if h <= 0:
            return 0.0
        r = math.sqrt(h)
        return max(0.0, min(r, hi[2]) - max(-r, lo[2]))

    def row(x):
        y0, y1 = max(lo[1], -1.0), min(hi[1], 1.0)
        return quad(chord, y0, y1, args=(x,), limit=100, epsabs=1e-10)[0] if y1 > y0 else 0.0

    x0, x1 = max(lo[0], -1.0), min(hi[0], 1.0)
    return quad(row, x0, x1, limit=100, epsabs=1e-9)[0] if x1 > x0 else 0.0


@pytest.mark.filterwarnings("ignore::scipy.integrate.IntegrationWarning")
def test_sphere_box_volume_matches_numerical_integration():
    rng = np.random.default_rng(2)
    for k in range(4):
        lo = rng.uniform(-1.1, 0.7, 3)
        hi = lo + rng.uniform(0.2, 1.4, 3)
        if k == 2:
            lo[0] = -INF
        if k == 3:
            hi[2] = INF
        assert box_volume(*lo, *hi) == pytest.approx(_chord_volume(lo, hi), abs=1e-5)


def test_cells_of_a_partition_add_up_to_the_ball():
    e = [-INF, -0.37, 0.21, 0.6, INF]
    total = sum(
        box_volume(e[i], e[j], e[k], e[i + 1], e[j + 1], e[k + 1])
        for i in range(4)
        for j in range(4)
        for k in range(4)
    )
    assert total == pytest.approx(BALL, abs=1e-12)


GRID = GridSpec((0.0, 0.0, 0.0), (0.04, 0.04, 0.04), (4, 4, 4))
R = 1e-3


def _volumes(grid, pos, radii, box=None):
    return cell_amounts(
        grid, np.atleast_2d(pos), np.atleast_1d(radii), np.zeros(len(np.atleast_1d(radii))), [0],
        weight="volume", mapping="fractional", box=box,
    )[:, 0]  # fmt: skip


def test_fractional_mapping_splits_by_volume():
    v = 4 / 3 * math.pi * R**3
    on_face = _volumes(GRID, [0.01, 0.015, 0.015], R)  # on the x = 0.01 face
    assert np.count_nonzero(on_face) == 2
    assert on_face[on_face > 0] == pytest.approx([v / 2, v / 2], rel=1e-12)
    corner = _volumes(GRID, [0.01, 0.02, 0.03], R)  # on a corner of 8 cells
    assert np.count_nonzero(corner) == 8
    assert corner[corner > 0] == pytest.approx(np.full(8, v / 8), rel=1e-12)
    near = _volumes(GRID, [0.0097, 0.015, 0.015], R)  # 0.3 R from the face
    assert np.sort(near[near > 0]) == pytest.approx([R**3 * cap(0.3), v - R**3 * cap(0.3)])


def test_fractional_share_moves_continuously_across_a_face():
    xs = np.linspace(0.0085, 0.0115, 31)
    cell = np.ravel_multi_index((0, 1, 1), GRID.shape)
    left_point = [cell_amounts(GRID, [[x, 0.015, 0.015]], [R], [0], [0])[cell, 0] for x in xs]
    left = [_volumes(GRID, [x, 0.015, 0.015], R)[cell] for x in xs]
    assert set(left_point) == {0.0, 1.0}  # point mapping jumps
    assert np.all(np.diff(left) <= 0) and np.max(np.abs(np.diff(left))) < 0.15 * left[0]


def test_clipped_and_periodic_edges_keep_every_particle_whole():
    v = 4 / 3 * math.pi * R**3
    outside = _volumes(GRID, [-0.0005, 0.015, 0.015], R)  # sticks out of the grid: clipped in
    assert outside.sum() == pytest.approx(v)
    box = (0.04, INF, INF)
    wrapped = _volumes(GRID, [0.0003, 0.015, 0.015], R, box)  # across the periodic x boundary
    assert wrapped.sum() == pytest.approx(v)
    first, last = wrapped.reshape(4, 4, 4)[0].sum(), wrapped.reshape(4, 4, 4)[-1].sum()
    assert last == pytest.approx(R**3 * cap(0.3)) and first == pytest.approx(v - last)


def test_slab_holds_the_segment_between_its_planes():
    t = 1.2e-3
    slab = GRID.slab("z", 0.02, t)
    assert slab.shape == (4, 4, 1) and not slab.clip
    inside = _volumes(slab, [0.015, 0.015, 0.02], R).sum()
    assert inside == pytest.approx(math.pi * (R**2 * t - t**3 / 12), rel=1e-12)
    assert cell_amounts(slab, [[0.015, 0.015, 0.03]], [R], [0], [0]).sum() == 0.0


def test_ball_quadrature_error_on_plane_cuts():
    """The equal-weight quadrature of the cylindrical fractional mapping: weights sum to the
    ball, and every plane cut is within 1.2 % of the ball volume of the exact cap."""
    points, weights = ball_quadrature()
    assert weights.sum() == pytest.approx(BALL, rel=1e-14)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    a = rng.uniform(-1, 1, 300)
    err = [weights[points @ n > off].sum() - cap(off) for n, off in zip(d, a)]
    assert np.max(np.abs(err)) < 0.012 * BALL


CYL = CylindricalGrid((0.0, 0.0), 0.03, 0.0, 0.05, (8, 3, 5), axis="z")


def test_cylindrical_bins_geometry_and_index():
    assert CYL.cell_volumes().sum() == pytest.approx(math.pi * 0.03**2 * 0.05)
    assert np.allclose(CYL.cell_volumes(), CYL.cell_volumes()[0])  # equal-area rings
    radius = CylindricalGrid((0.0, 0.0), 0.03, 0.0, 0.05, (8, 3, 5), radial="radius")
    assert radius.ring_edges() == pytest.approx([0, 0.01, 0.02, 0.03])
    e = CYL.ring_edges()
    assert np.diff(e**2) == pytest.approx(np.full(3, 0.03**2 / 3))
    # 45 degrees (second sector of 8), radius in the middle ring, axial bin 2
    r_mid = 0.5 * (e[1] + e[2])
    p = [[r_mid * math.cos(math.pi / 4 + 0.1), r_mid * math.sin(math.pi / 4 + 0.1), 0.025]]
    assert CYL.cell_index(np.array(p))[0] == np.ravel_multi_index((1, 1, 2), CYL.shape)
    assert CYL.cell_index(np.array([[0.031, 0.0, 0.01], [0.0, 0.0, 0.06]])).tolist() == [-1, -1]
    centres = CYL.cell_centres()
    assert np.all(CYL.cell_index(centres) == np.arange(CYL.n_cells))


def test_cylindrical_fractional_mapping_keeps_volume_and_splits_faces():
    """Shares add up to each sphere; a sphere cut by an axial face or a sector plane only splits
    exactly (caps); every share is within 1.5 % of the particle volume of a fine quadrature
    (30 shells x 600 directions) of the same sphere, near the axis and across rings included."""
    rng = np.random.default_rng(1)
    n = 300
    rho = 0.028 * np.sqrt(rng.random(n))
    phi = rng.uniform(0, 2 * math.pi, n)
    pos = np.stack([rho * np.cos(phi), rho * np.sin(phi), rng.uniform(0.002, 0.048, n)], axis=1)
    radii = np.full(n, R)
    part, cell, vol = CYL.shares(pos, radii)
    assert vol.sum() == pytest.approx(sphere_volumes(radii).sum(), rel=1e-12)
    points, weights = ball_quadrature(30, 600)
    v = 4 / 3 * math.pi * R**3
    worst = 0.0
    for p in range(n):
        cells = CYL.cell_index(pos[p] + R * points)
        ref = np.bincount(cells[cells >= 0], weights=weights[cells >= 0], minlength=CYL.n_cells)
        got = np.bincount(cell[part == p], weights=vol[part == p], minlength=CYL.n_cells)
        worst = max(worst, np.abs(got - ref * R**3).max() / v)
    assert worst < 0.015
    axial = _volumes(CYL, [0.01 * math.cos(0.2), 0.01 * math.sin(0.2), 0.02], R)  # z = 0.02
    assert np.sort(axial[axial > 0]) == pytest.approx([v / 2, v / 2], rel=1e-12)
    edge = math.pi / 4  # a sector plane, the sphere 0.4 R from it
    centre = 0.012 * np.array([math.cos(edge), math.sin(edge)])
    off = centre + 0.4 * R * np.array([math.sin(edge), -math.cos(edge)])
    sector = _volumes(CYL, [off[0], off[1], 0.0275], R)
    assert np.sort(sector[sector > 0]) == pytest.approx([R**3 * cap(0.4), v - R**3 * cap(0.4)])


def test_minimum_fill_follows_cell_volume():
    """Uniform bed, rings of equal width: the small inner cells hold few particles but their
    volume's share, so none is dropped (the mean-count rule would drop the inner ring)."""
    rng = np.random.default_rng(3)
    n = 40_000
    rho = 0.03 * np.sqrt(rng.random(n))
    phi = rng.uniform(0, 2 * math.pi, n)
    pos = np.stack([rho * np.cos(phi), rho * np.sin(phi), rng.uniform(0, 0.05, n)], axis=1)
    grid = CylindricalGrid((0.0, 0.0), 0.03, 0.0, 0.05, (4, 4, 2), radial="radius")
    counts = cell_amounts(grid, pos, np.zeros(n), np.zeros(n), [0])
    assert occupied_cells(grid, counts).all()
    assert (counts[:, 0] < 0.5 * n / grid.n_cells).sum() == 8  # inner ring under the mean rule
    low = pos[pos[:, 2] < 0.025]
    half = cell_amounts(grid, low, np.zeros(len(low)), np.zeros(len(low)), [0])
    assert occupied_cells(grid, half).sum() == grid.n_cells // 2  # the empty top half dropped


def test_parse_bins():
    g = parse_bins("cartesian:8x8x52", (0, 0, 0), (1, 1, 2))
    assert isinstance(g, GridSpec) and g.shape == (8, 8, 52)
    assert parse_bins("1x8x8", (0, 0, 0), (1, 1, 1)).shape == (1, 8, 8)
    c = parse_bins("cylindrical:6x4x10,axis=x,radial=radius", (0, -1, -2), (3, 1, 2), min_fill=0.3)
    assert isinstance(c, CylindricalGrid)
    assert (c.axis, c.centre, c.r_max, c.lo, c.hi) == (0, (0.0, 0.0), 1.0, 0.0, 3.0)
    assert c.shape == (6, 4, 10) and c.radial == "radius" and c.min_fill == 0.3
    with pytest.raises(ValueError, match="bins must be"):
        parse_bins("spherical:2x2x2", (0, 0, 0), (1, 1, 1))
    with pytest.raises(ValueError, match="grid must look like"):
        parse_bins("cylindrical:8by4", (0, 0, 0), (1, 1, 1))
    with pytest.raises(ValueError, match="unknown cylindrical bins option"):
        parse_bins("cylindrical:8x4x2,spin=1", (0, 0, 0), (1, 1, 1))
    with pytest.raises(ValueError, match="sliced across its axis"):
        c.slab("z", 0.0, 0.1)


def test_equal_volume_split_of_a_polydisperse_bed():
    rng = np.random.default_rng(5)
    n = 3000
    pos = rng.random((n, 3))
    radii = rng.choice(np.linspace(0.5, 1.5, 10), n) * 1e-3
    v = sphere_volumes(radii)
    types = split_species(pos, radii, by="y", weight="volume")
    assert abs(v[types == 0].sum() - v.sum() / 2) <= v.max() / 2
    assert np.all(pos[types == 0, 1] <= pos[types == 1, 1].min())
    by_number = split_species(pos, radii, by="y", weight="number")
    assert abs((by_number == 0).sum() - n / 2) <= 1
    small = split_species(pos, radii, by="radius", weight="volume")
    assert radii[small == 0].max() <= radii[small == 1].min()
    assert abs(v[small == 0].sum() - v.sum() / 2) <= v.max() / 2
    core = split_species(pos, radii, by="r", weight="volume", axis=2, centre=(0.5, 0.5))
    dist = np.hypot(pos[:, 0] - 0.5, pos[:, 1] - 0.5)
    assert dist[core == 0].max() <= dist[core == 1].min()
    with pytest.raises(ValueError, match="split must be one of"):
        split_species(pos, radii, by="w")
