"""Mixing indices of polydisperse beds: volume weighting and the sphere spreading index.

References: the variance of the volume fraction of a sample of a random mixture of unequal
particles (Stange 1954; Poole, Taylor & Wall 1964), ``Sr^2 = p (1 - p) / V_s [(1 - p) kappa_A +
p kappa_B]``, ``kappa = <v^2> / <v>``; pure cells (a bed split along a cell face) give every
index its segregated bound exactly; the mean distance of a uniform ball of radius ``a`` from its
centre is ``3 a / 4`` (sphere spreading index, Füvesi et al. 2025).
"""

import numpy as np
import pytest

from twin_core.dem.frames import Frame
from twin_core.mixing import GridSpec, MixingConfig, cell_amounts, compute_indices, occupied_cells
from twin_core.mixing import variance_indices as vi
from twin_core.mixing.distance_indices import sphere_spreading_index, spreading_radius
from twin_core.mixing.grid import sphere_volumes

SIZE = 0.06
GRID = GridSpec((0, 0, 0), (SIZE, SIZE, SIZE), (6, 6, 6))
N = 30_000


def random_bed(seed: int):
    """Uniformly random centres (a random mixture whatever the species) with ten radii."""
    rng = np.random.default_rng(seed)
    pos = rng.random((N, 3)) * SIZE
    radii = rng.choice(np.linspace(0.5, 1.5, 10), N) * 1e-3
    return rng, pos, radii


def frame(pos, radii, types):
    return Frame(0.0, np.arange(len(pos)), types, radii, pos, np.zeros_like(pos))


@pytest.mark.parametrize("split", ["independent", "by-size"])
def test_volume_weighted_variance_of_a_random_mixture_is_stanges(split):
    """The cell-volume-weighted variance of the volume fraction, averaged over ten random beds,
    equals Stange's random-mixture variance (within 4 standard errors), whether the species
    are independent of size or the small particles are the tracer; for independent species
    the count-based ``p (1 - p) / n`` misses it by the spread of particle volumes
    (``1 + c^2 = 1.65`` here)."""
    rng, pos, radii = random_bed(1)
    v = sphere_volumes(radii)
    ratios, naive = [], []
    for _ in range(10):
        pos = pos[rng.permutation(N)]
        if split == "independent":
            types = rng.integers(0, 2, N)
        else:
            types = (radii > np.median(radii)).astype(int)
        amounts = cell_amounts(GRID, pos, radii, types, [0, 1], weight="volume")
        kept = amounts[occupied_cells(GRID, amounts)]
        a, n = kept[:, 0], kept.sum(axis=1)
        p = a.sum() / n.sum()
        esi = vi.intensity_of_segregation(a, n, weights=n)
        kappa = [np.mean(v[types == k] ** 2) / np.mean(v[types == k]) for k in (0, 1)]
        sr2 = vi.random_mixture_variance(p, n.mean(), *kappa)
        ratios.append(esi**2 * p * (1 - p) / sr2)
        naive.append(esi**2 * n.mean() / v.mean())
    # the relative sd of a variance over 216 cells is sqrt(2/216) = 0.096 per bed
    assert np.mean(ratios) == pytest.approx(1.0, abs=4 * 0.096 / np.sqrt(10))
    if split == "independent":
        assert np.mean(naive) == pytest.approx(np.mean(v**2) / np.mean(v) ** 2, rel=0.15)


def test_volume_weighted_indices_at_their_bounds():
    """Pure cells: LI = 0, ESI = 1, DM = 0, ME = 0 exactly; a random bed: LI ~ 1, ME ~ 1."""
    rng, pos, radii = random_bed(2)
    cfg = MixingConfig(grid=GRID, weight="volume")
    names = ["LI", "ESI", "DM", "ME", "RSD", "MSI", "AH"]
    split = frame(pos, radii, (pos[:, 0] >= SIZE / 2).astype(int))  # on the x = 0.03 faces
    row = compute_indices([split], names, cfg).iloc[0]
    assert row["LI"] == pytest.approx(0.0, abs=1e-12)
    assert row["ESI"] == pytest.approx(1.0, abs=1e-12)
    assert row["DM"] == pytest.approx(0.0, abs=1e-12)
    assert row["ME"] == pytest.approx(0.0, abs=1e-12)
    p = sphere_volumes(radii)[split.types == 0].sum() / sphere_volumes(radii).sum()
    assert row["RSD"] == pytest.approx(np.sqrt((1 - p) / p), rel=1e-12)  # segregated bound
    mixed = compute_indices([frame(pos, radii, rng.integers(0, 2, N))], names, cfg).iloc[0]
    assert mixed["LI"] == pytest.approx(1.0, abs=0.01)
    assert mixed["ME"] > 0.99 and mixed["DM"] > 0.85
    assert mixed["AH"] == pytest.approx(1.0, abs=0.02)


def test_volume_weighted_average_height_of_a_bottom_half():
    """The tracer is the lower half of a uniform bed by volume: its centre of volume sits at a
    quarter of the height, the bed's at a half, so AH = 0.5."""
    _, pos, radii = random_bed(3)
    v = sphere_volumes(radii)
    order = np.argsort(pos[:, 2])
    below = np.searchsorted(np.cumsum(v[order]), v.sum() / 2)
    types = np.ones(N, int)
    types[order[:below]] = 0
    cfg = MixingConfig(grid=GRID, weight="volume")
    row = compute_indices([frame(pos, radii, types)], ["AH"], cfg).iloc[0]
    assert row["AH_z"] == pytest.approx(0.5, abs=0.01)
    assert row["AH_x"] == pytest.approx(1.0, abs=0.02)


def ball(n, a, rng):
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    return d * a * np.cbrt(rng.random(n))[:, None]


def test_sphere_spreading_index_of_concentric_balls():
    """A uniform ball of radius a has mean centre distance 3a/4; a tracer spread from a ball
    of radius b0 to one of radius b, inside a bed ball of radius a, has
    SSI = (3b/4 - 3b0/4) / (R - 3b0/4) with R the mean distance of all particles."""
    rng = np.random.default_rng(4)
    a, b0, b = 1.0, 0.4, 0.7
    bed = ball(200_000, a, rng)
    assert spreading_radius(bed) == pytest.approx(0.75 * a, rel=3e-3)
    tracer0 = ball(50_000, b0, rng)
    r0 = spreading_radius(tracer0)
    pos = np.concatenate([ball(50_000, b, rng), bed])
    types = np.r_[np.zeros(50_000, int), np.ones(len(bed), int)]
    ssi = sphere_spreading_index(pos, types, 0, r0)
    # all particles: the tracer ball and the bed ball, concentric, so their mean distance is
    # the count-weighted mean of 3b/4 and 3a/4
    r_all = (50_000 * 0.75 * b + 200_000 * 0.75 * a) / 250_000
    expected = (0.75 * b - r0) / (r_all - r0)
    assert ssi == pytest.approx(expected, abs=0.01)
    assert sphere_spreading_index(np.r_[tracer0, bed], types, 0, r0) == pytest.approx(0, abs=1e-9)


def test_sphere_spreading_index_ignores_where_a_periodic_box_is_cut():
    rng = np.random.default_rng(5)
    L = 0.04
    pos = rng.random((5000, 3)) * [L, 0.02, 0.02]
    types = (np.abs(pos[:, 0] - 0.02) > 0.012).astype(int)  # tracer: a slab in the middle
    box = (L, np.inf, np.inf)
    r0 = spreading_radius(pos[types == 0], box=box)
    shifted = pos.copy()
    shifted[:, 0] = np.mod(shifted[:, 0] + 0.019, L)  # the slab now straddles x = 0
    assert spreading_radius(shifted[types == 0], box=box) == pytest.approx(r0, rel=1e-9)
    moved = pos.copy()
    moved[types == 0, 1] += 0.001
    s1 = sphere_spreading_index(moved, types, 0, r0, box=box)
    moved_shifted = moved.copy()
    moved_shifted[:, 0] = np.mod(moved_shifted[:, 0] + 0.019, L)
    assert sphere_spreading_index(moved_shifted, types, 0, r0, box=box) == pytest.approx(s1)
