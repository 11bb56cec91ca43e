"""Mixing indices (seed 4.3.1) against their analytic bounds.

References: a fully segregated bed must give each index's unmixed bound; a random type
assignment must give the binomial-sampling (random mixture) bound of each definition
(Lacey 1954: Sr^2 = p(1-p)/n; contact statistics of a random binary mixture: AA:AB:BB =
p^2 : 2p(1-p) : (1-p)^2); a growing swapped fraction moves every index toward mixed.
"""

import numpy as np
import pandas as pd
import pytest

from twin_core.dem.frames import Frame
from twin_core.mixing import (
    INDEX_NAMES,
    GridSpec,
    MixingConfig,
    compute_indices,
    mixed_reference,
    mixing_progress,
    shuffled_frame,
)
from twin_core.mixing.distance_indices import random_pairs, siiria_index, siiria_index_sampled
from twin_core.mixing.neighbours import contacts_from_positions

R = 1e-3


def fcc_bed(box=(0.02, 0.04, 0.03)):
    """Spheres of radius R on an FCC lattice (12 touching neighbours each)."""
    a = 2 * np.sqrt(2) * R
    basis = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) * a
    n = [int(b // a) for b in box]
    cells = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, 3)
    pos = (cells[:, None, :] * a + basis[None]).reshape(-1, 3) + R / 2
    return pos, n[0] * a


@pytest.fixture(scope="module")
def bed():
    pos, lx = fcc_bed()
    n = len(pos)
    types = (pos[:, 1] >= np.median(pos[:, 1])).astype(int)  # tracer (0) on the left half
    grid = GridSpec((0, 0, 0), (lx, 0.04, 0.03), (1, 8, 8))
    cfg = MixingConfig(grid=grid, box=(lx, np.inf, np.inf), ah_axis=1, sm_pairs=20_000)
    return Frame(0.0, np.arange(n), types, np.full(n, R), pos, np.zeros_like(pos)), cfg


def test_segregated_bed_gives_unmixed_bounds(bed):
    f0, cfg = bed
    row = compute_indices([f0], "all", cfg).iloc[0]
    assert abs(row["LI"]) < 0.05
    assert row["RSD"] == pytest.approx(1.0, abs=0.05)  # sqrt((1-p)/p) at p = 0.5
    assert row["ESI"] == pytest.approx(1.0, abs=0.02)
    assert row["MSI"] == pytest.approx(row["RSD"])
    assert row["ME"] == pytest.approx(0.0, abs=1e-12)
    assert row["DM"] == pytest.approx(0.0, abs=0.02)
    assert row["VRR"] == 1.0 and row["VBBC"] == 1.0
    assert row["CN"] < 0.05 and row["PS"] < 0.1 and row["NNM"] < 0.1
    assert row["SI"] > 1.9
    assert row["SM"] == 0.0 and abs(row["NDM"]) < 1e-12
    assert row["AH_y"] < 0.6  # tracer sits on the near half along y


def test_random_assignment_gives_mixed_bounds(bed):
    f0, cfg = bed
    frames = [f0] + [shuffled_frame(f0, s) for s in range(1, 6)]
    df = compute_indices(frames, "all", cfg).iloc[1:]
    counts = np.bincount(cfg.grid.cell_index(f0.positions), minlength=cfg.grid.n_cells)
    n_bar = counts[counts >= 0.5 * counts.mean()].mean()
    # every random assignment must sit at the random-mixture bound within ~4 sigma
    assert np.all(np.abs(df["LI"] - 1) < 0.1)
    assert np.all(np.abs(df["RSD"] / np.sqrt(1 / n_bar) - 1) < 0.35)
    assert np.all(np.abs(df["ESI"] * np.sqrt(n_bar) - 1) < 0.35)
    # DM: var of the cell variance ~ 2/N_cells relative -> sd(DM) ~ 0.011 here; 4 sd = 0.045
    assert np.all(np.abs(df["DM"] - (1 - 1 / np.sqrt(n_bar))) < 0.05)
    assert np.all(df["ME"] > 0.98)
    assert np.all(np.abs(df["CN"] - 1) < 0.05)
    assert np.all(np.abs(df["SI"] - 1) < 0.03)
    assert np.all(np.abs(df["NNM"] - 1) < 0.03)
    assert np.all(np.abs(df["PS"] - 1) < 0.06)
    assert np.all(np.abs(df["AH_y"] - 1) < 0.02)
    assert np.all(np.abs(df["NDM"] - 1) < 0.05)
    assert np.all(df["VBBC"] < 0.02) and np.all(df["VRR"] > 50)


def test_unequal_fraction_contact_statistics(bed):
    """Random mixture with p = 0.3: CN -> 2p(1-p)/(p^2+(1-p)^2), NNM -> 4p(1-p), SI -> 1."""
    f0, cfg = bed
    rng = np.random.default_rng(3)
    p = 0.3
    types = (rng.random(len(f0.ids)) >= p).astype(int)
    fr = Frame(0.0, f0.ids, types, f0.radii, f0.positions, f0.velocities)
    row = compute_indices([fr], ["CN", "SI", "NNM"], cfg).iloc[0]
    assert row["CN"] == pytest.approx(2 * p * (1 - p) / (p**2 + (1 - p) ** 2), rel=0.05)
    assert row["NNM"] == pytest.approx(4 * p * (1 - p), rel=0.05)
    assert row["SI"] == pytest.approx(1.0, abs=0.03)


def test_growing_swapped_fraction_moves_every_index_toward_mixed(bed):
    f0, cfg = bed
    rng = np.random.default_rng(7)
    n = len(f0.ids)
    order = rng.permutation(n)
    frames = []
    for k, frac in enumerate(np.linspace(0, 1, 6)):
        sel = order[: int(frac * n)]
        pos = f0.positions.copy()
        pos[sel] = f0.positions[rng.permutation(sel)]
        frames.append(Frame(float(k), f0.ids, f0.types, f0.radii, pos, f0.velocities))
    df = compute_indices(frames, "all", cfg)
    prog = mixing_progress(df, mixed_reference(f0, "all", cfg, n_shuffles=3))
    for name in INDEX_NAMES:
        col = "AH" if name == "AH" else name
        steps = np.diff(prog[col].to_numpy())
        assert np.all(steps > 0), f"{name} not monotonic toward mixed: {prog[col].to_numpy()}"
    # fully swapped = a random mixture: every progress ends near 1, except VRR = s0^2/s^2, which
    # diverges at the random floor of s^2 and so scatters by tens of percent between mixtures
    last = prog.iloc[-1][[n for n in INDEX_NAMES if n != "VRR"]]
    assert np.all(np.abs(last - 1) < 0.15)
    assert prog.iloc[-1]["VRR"] > 0.3


def test_siiria_sampled_estimator_agrees_with_exact_kernel():
    """The sampled Siiria estimator is unbiased: exact value within 4 standard errors."""
    rng = np.random.default_rng(0)
    p0 = rng.random((1500, 3)) * 0.03
    p1 = p0 + rng.normal(0, 0.004, p0.shape)
    exact = siiria_index(p0, p1, 0.87, 100.0)
    est, se = siiria_index_sampled(p0, p1, random_pairs(1500, 50_000, 1), 0.87, 100.0)
    assert abs(est - exact) < 4 * se
    assert se / exact < 0.02


def test_contacts_across_periodic_boundary():
    pos = np.array([[0.0001, 0.01, 0.01], [0.0399, 0.01, 0.01], [0.02, 0.01, 0.01]])
    pairs = contacts_from_positions(pos, np.full(3, R), box=(0.04, np.inf, np.inf))
    assert pairs.tolist() == [[0, 1]]
    assert len(contacts_from_positions(pos, np.full(3, R))) == 0


def test_error_paths(bed):
    f0, cfg = bed
    with pytest.raises(ValueError, match="unknown index 'XYZ'"):
        compute_indices([f0], ["XYZ"], cfg)
    with pytest.raises(ValueError, match="grid must look like"):
        GridSpec.parse("8by8", (0, 0, 0), (1, 1, 1))
    with pytest.raises(ValueError, match="hi must exceed lo"):
        GridSpec((0, 0, 0), (1, 0, 1))
    other = Frame(1.0, f0.ids + 1, f0.types, f0.radii, f0.positions, f0.velocities)
    with pytest.raises(ValueError, match="same particle ids"):
        compute_indices([f0, other], ["LI"], cfg)
    with pytest.raises(ValueError, match="tracer type 5"):
        compute_indices([f0], ["LI"], MixingConfig(grid=cfg.grid, tracer=5))
    with pytest.raises(ValueError, match="frames is empty"):
        compute_indices([], ["LI"], cfg)


def test_dataframe_columns(bed):
    f0, cfg = bed
    df = compute_indices([f0, shuffled_frame(f0, 1)], "LI,VBBC", cfg)
    assert isinstance(df, pd.DataFrame)
    assert list(df.columns) == ["t", "LI", "VBBC", "VBBC_raw"]


def test_lost_particles_are_refused_or_dropped_and_reported(bed):
    f0, cfg = bed
    keep = np.arange(len(f0.ids)) != 5
    f1 = Frame(
        1.0, f0.ids[keep], f0.types[keep], f0.radii[keep], f0.positions[keep], f0.velocities[keep]
    )
    with pytest.raises(ValueError, match="same particle ids"):
        compute_indices([f0, f1], ["LI"], cfg)
    df = compute_indices([f0, f1], ["LI", "SI"], cfg, allow_lost=True)
    assert df.attrs["dropped_particles"] == 1
    assert len(df) == 2


@pytest.mark.parametrize("periodic", [False, True], ids=["closed", "periodic-x"])
def test_cell_list_search_equals_kd_tree(periodic):
    """Contacts and the 12 nearest neighbours from the cell-list search are exactly those of a
    KD-tree (scipy's cKDTree, periodic box included), with free-surface and flying particles
    (whose 12th neighbour lies beyond the first shell of cells)."""
    from scipy.spatial import cKDTree

    from twin_core.mixing.neighbours import neighbour_search

    rng = np.random.default_rng(4)
    n = 2500
    pos = rng.random((n, 3)) * [0.04, 0.05, 0.03]
    pos[:8] += [0.0, 0.0, 0.5]  # far above the bed
    radii = rng.uniform(0.4e-3, 1.2e-3, n)
    L = 0.04
    box = np.array([L, np.inf, np.inf]) if periodic else None
    pairs, nb = neighbour_search(pos, radii, box, 0.02, 12)
    ref_pos = pos.copy()
    size = None
    if periodic:
        ref_pos[:, 0] = np.mod(ref_pos[:, 0], L)
        ref_pos[:, 1:] -= ref_pos[:, 1:].min(axis=0)
        size = np.array([L, 4 * (np.ptp(ref_pos[:, 1]) + 1), 4 * (np.ptp(ref_pos[:, 2]) + 1)])
    tree = cKDTree(ref_pos, boxsize=size)
    _, idx = tree.query(ref_pos, k=13)
    assert all(set(a) == set(b) for a, b in zip(nb, idx[:, 1:]))
    cand = tree.query_pairs(2 * radii.max() * 1.02, output_type="ndarray")
    d = tree.data[cand[:, 1]] - tree.data[cand[:, 0]]
    if periodic:
        d[:, 0] -= L * np.round(d[:, 0] / L)
    near = np.linalg.norm(d, axis=1) < (radii[cand[:, 0]] + radii[cand[:, 1]]) * 1.02
    ref = np.sort(cand[near], axis=1)
    ref = ref[np.lexsort((ref[:, 1], ref[:, 0]))]
    assert np.array_equal(pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))], ref)


@pytest.mark.parametrize("periodic", [False, True], ids=["closed", "periodic-xy"])
def test_neighbour_search_equals_brute_force_on_a_sparse_layer(periodic):
    """A thin, sparse layer (cells holding fewer than k + 1 particles around many particles,
    so the k nearest lie beyond the first shell of cells): contacts and the 12 nearest
    neighbours, nearest first, equal a brute-force all-pairs reference with the minimum image
    on periodic axes."""
    from twin_core.mixing.neighbours import neighbour_search

    rng = np.random.default_rng(7)
    n, k = 120, 12
    size = np.array([0.03, 0.03, 0.002])
    pos = rng.random((n, 3)) * size
    radii = rng.uniform(0.3e-3, 0.9e-3, n)
    box = np.array([size[0], size[1], np.inf]) if periodic else None
    pairs, nb = neighbour_search(pos, radii, box, 0.02, k)
    d = pos[None, :, :] - pos[:, None, :]
    if periodic:
        d[..., :2] -= size[:2] * np.round(d[..., :2] / size[:2])
    dist = np.sqrt((d**2).sum(axis=-1))
    np.fill_diagonal(dist, np.inf)
    ref_nb = np.argsort(dist, axis=1, kind="stable")[:, :k]
    assert np.array_equal(np.sort(nb, axis=1), np.sort(ref_nb, axis=1))
    assert np.all(np.diff(np.take_along_axis(dist, nb, axis=1), axis=1) >= 0)  # nearest first
    i, j = np.nonzero(np.triu(dist < (radii[:, None] + radii[None, :]) * 1.02, 1))
    ref = np.stack([i, j], axis=1)
    got = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    assert np.array_equal(got, ref[np.lexsort((ref[:, 1], ref[:, 0]))])
