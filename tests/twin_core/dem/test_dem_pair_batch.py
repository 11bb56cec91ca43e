"""The batched pair contact law (twin_core.dem.pairs): the vectorised block law against an
independent NumPy transcription of the published law (Hertz normal spring, Tsuji dashpot,
Mindlin no-slip spring with the Coulomb truncation of LAMMPS ``gran/hertz/history``, constant
directional rolling torque of Ai et al. 2011 model A), the same bits in every column of a
block (SIMD lanes and the scalar remainder), and the clearing of a spring when its pair parts
between list rebuilds."""

from __future__ import annotations

import numpy as np
import pytest

from twin_core.dem.pairs import (
    _NIN,
    _ROW,
    BLOCK,
    BLOCK_WORDS,
    contact_block,
    find_contacts,
    flatten_pairs,
)

DT = 2e-6


def _inputs(m: int, seed: int = 0) -> np.ndarray:
    """Random contacts (rows of the block layout, one column per contact) covering sticking and
    sliding springs, zero springs, springs with a normal part, rolling capped and not, no
    rolling friction and no relative rotation."""
    rng = np.random.default_rng(seed)
    x = np.zeros((_NIN, m))
    ri = rng.uniform(0.5e-3, 1.5e-3, m)
    rj = rng.uniform(0.5e-3, 1.5e-3, m)
    delta = (ri + rj) * rng.uniform(1e-5, 5e-3, m)
    n = rng.normal(size=(3, m))
    n /= np.linalg.norm(n, axis=0)
    x[0:3] = n * (ri + rj - delta)
    x[3], x[4] = ri, rj
    x[5], x[6] = 2500 * 4 / 3 * np.pi * ri**3, 2500 * 4 / 3 * np.pi * rj**3
    x[7:10] = rng.normal(scale=0.05, size=(3, m))
    x[10:16] = rng.normal(scale=20.0, size=(6, m))
    x[13:16, ::7] = x[10:13, ::7]  # no relative rotation
    x[16] = 1 / (0.4 * x[5] * ri**2) + 1 / (0.4 * x[6] * rj**2)
    x[17:20] = rng.normal(scale=1e-6, size=(3, m)) * rng.choice([0.0, 1e-3, 1.0, 30.0], m)
    e = rng.uniform(1e7, 1e9, m)
    g = e / rng.uniform(2.2, 3.0, m)
    x[20], x[21] = e, g
    x[22] = rng.choice([0.05, 0.3, 0.6], m)
    x[23] = rng.choice([0.0, 0.01, 0.2, 5.0], m)  # 5.0: the cap holds
    x[24] = rng.uniform(0.1, 1.5, m)
    x[25] = np.sqrt(4 * g / e)
    return x


def _reference(x: np.ndarray) -> np.ndarray:
    """The law written out independently in NumPy (module docstring), one contact per column:
    force on i (3), torque on i (3), torque on j (3), delta/2, new spring (3)."""
    d = x[0:3]
    ri, rj, mi, mj = x[3], x[4], x[5], x[6]
    e, g, mu, mur, dmp = x[20], x[21], x[22], x[23], x[24]
    dist = np.linalg.norm(d, axis=0)
    n = d / dist
    delta = ri + rj - dist
    r_star = ri * rj / (ri + rj)
    m_star = mi * mj / (mi + mj)
    ci, cj = ri - delta / 2, rj - delta / 2
    rv = x[7:10] + np.cross((ci * x[10:13] + cj * x[13:16]).T, n.T).T
    vn = np.sum(rv * n, axis=0)
    vt = rv - vn * n
    sn = 2 * e * np.sqrt(r_star * delta)
    st = 8 * g * np.sqrt(r_star * delta)
    fn = np.maximum(2 / 3 * sn * delta + dmp * np.sqrt(sn * m_star) * vn, 0.0)
    h = x[17:20].copy()
    hmag = np.linalg.norm(h, axis=0)
    hp = h - np.sum(h * n, axis=0) * n
    hpm = np.linalg.norm(hp, axis=0)
    rot = hpm > 0
    h[:, rot] = hp[:, rot] * hmag[rot] / hpm[rot]
    h = h + vt * DT
    ct = dmp * np.sqrt(st * m_star)
    ft = -st * h - ct * vt
    ftm = np.linalg.norm(ft, axis=0)
    slide = ftm > mu * fn
    ft[:, slide] *= (mu * fn / ftm)[slide]
    h[:, slide] = -(ft[:, slide] + ct[slide] * vt[:, slide]) / st[slide]
    wr = x[10:13] - x[13:16]
    wm = np.linalg.norm(wr, axis=0)
    mr = np.zeros_like(wr)
    on = (mur > 0) & (wm > 0)
    tr = mur * fn * r_star
    cap = tr * DT * x[16] > wm
    s = np.where(cap, 1 / (DT * x[16]), tr / np.where(wm > 0, wm, 1.0))
    mr[:, on] = -(s * wr)[:, on]
    nxf = np.cross(n.T, ft.T).T
    return np.vstack([-fn * n + ft, ci * nxf + mr, cj * nxf - mr, delta / 2, h])


def _run_block(x: np.ndarray, col0: int = 0) -> np.ndarray:
    """Results of contact_block for the contacts ``x`` placed from column ``col0``."""
    m = x.shape[1]
    w = np.full(BLOCK_WORDS, np.nan)
    for r in range(_NIN):
        w[r * _ROW + col0 : r * _ROW + col0 + m] = x[r]
    if col0:
        for r in range(_NIN):  # valid contacts in front of them
            w[r * _ROW : r * _ROW + col0] = x[r, :1]
    contact_block(col0 + m, w, DT)
    out = w[_NIN * _ROW :].reshape(-1, _ROW)[:13]
    return out[:, col0 : col0 + m]


def test_block_law_matches_an_independent_transcription_of_the_published_law():
    """Reference: the law as published (Hertz 1882; Tsuji et al. 1992; Mindlin & Deresiewicz
    1953 with LAMMPS gran/hertz/history's Coulomb truncation; Ai et al. 2011 model A), written
    out in NumPy without the engine's algebra (no shared dashpot ratio, no shared division):
    1,000 contacts agree to 1e-10 of each quantity's scale; sliding and sticking springs both
    occur."""
    x = np.hstack([_inputs(BLOCK, seed) for seed in range(8)])
    got = np.hstack([_run_block(x[:, c : c + BLOCK]) for c in range(0, x.shape[1], BLOCK)])
    ref = _reference(x)
    for rows in (slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 10), slice(10, 13)):
        scale = np.abs(ref[rows]).max(axis=0) + 1e-300
        assert np.all(np.abs(got[rows] - ref[rows]) <= 1e-10 * scale)
    force = np.linalg.norm(ref[0:3], axis=0)
    assert np.sum(force > 0) > 900  # a few fast-separating contacts clamp at F_n = 0
    h0 = np.linalg.norm(x[17:20], axis=0)
    h1 = np.linalg.norm(ref[10:13], axis=0)
    assert np.sum(h1 < h0 * 0.99) > 50  # truncated (sliding) springs
    assert np.sum(h1 > h0) > 50  # growing (sticking) springs


@pytest.mark.parametrize("col0, m", [(0, 1), (0, 3), (5, 37), (91, 37), (0, BLOCK)])
def test_block_law_gives_the_same_bits_in_any_column(col0, m):
    """Whether a contact lands in a SIMD lane or in the scalar remainder of the loop, its
    results are the same bits: the sums do not depend on where a chunk's blocks start (and so
    stay independent of the thread count)."""
    x = _inputs(BLOCK, seed=3)
    ref = _run_block(x)
    got = _run_block(x[:, :m], col0)
    assert np.array_equal(got, ref[:, :m])


def test_a_spring_is_cleared_when_its_pair_parts_between_rebuilds():
    """find_contacts keeps the spring of a pair in contact, clears it when the pair is found
    apart (LAMMPS clears the shear history when a listed pair stops touching) and records
    which springs may be live (derived from the springs when the lists are packed)."""
    P = np.zeros((2, 13))
    P[:, 9] = 1e-3
    P[1, 0] = 1.9e-3  # overlapping
    nb = np.array([[1], [0]], np.int64)
    nown = np.array([1, 0], np.int64)
    hist = np.zeros((2, 1, 3))
    hist[0, 0] = (1e-7, 0.0, 2e-7)
    pstart = np.zeros(3, np.int64)
    nbf = np.zeros((2, 2), np.int32)
    live = np.zeros(2, np.uint8)
    flatten_pairs(2, nb, nown, hist, pstart, nbf, live)
    assert pstart.tolist() == [0, 1, 1] and nbf[:, 0].tolist() == [0, 1] and live[0] == 1
    clist = np.zeros((3, 2), np.int32)
    dom = np.array([0, 0, 0, 1, 1, 1, 1, 1, 1.0])
    per = np.zeros(3, np.int64)
    assert find_contacts(0, 2, P, nbf, pstart, hist, live, dom, per, clist) == 1
    assert clist[:, 0].tolist() == [0, 0, 1] and live[0] == 1
    assert hist[0, 0].tolist() == [1e-7, 0.0, 2e-7]
    P[1, 0] = 2.1e-3  # apart, still listed
    assert find_contacts(0, 2, P, nbf, pstart, hist, live, dom, per, clist) == 0
    assert hist[0, 0].tolist() == [0.0, 0.0, 0.0] and live[0] == 0


def test_each_contact_takes_its_material_pair_from_the_current_tables():
    """Static contacts (no velocity, no spring) of alternating materials get the Hertz force
    ``(4/3) E* sqrt(R*) delta^(3/2)`` (Hertz 1882) of their own material pair, and a changed
    table is used at the next evaluation (the block buffer keeps no stale coefficients)."""
    from twin_core.dem.pairs import pair_scatter

    n = 5
    r = 1e-3
    P = np.zeros((n, 13))
    P[:, 0] = 0.1 + np.arange(n) * 1.99e-3  # chain along x, overlap 10 um
    P[:, 9] = r
    P[:, 10] = 1e-5
    P[:, 11] = 1e5
    P[:, 12] = 1.0
    IA = np.zeros((n, 3), np.int64)
    IA[:, 1] = [0, 1, 0, 1, 1]
    nb = np.zeros((n, 1), np.int64)
    nb[:, 0] = np.minimum(np.arange(n) + 1, n - 1)
    nown = np.array([1, 1, 1, 1, 0], np.int64)
    hist = np.zeros((n, 1, 3))
    pstart = np.zeros(n + 1, np.int64)
    nbf = np.zeros((2, n), np.int32)
    live = np.zeros(n, np.uint8)
    flatten_pairs(n, nb, nown, hist, pstart, nbf, live)
    clist = np.zeros((3, n), np.int32)
    work = np.zeros((1, BLOCK_WORDS))
    F = np.zeros((n, 6))  # the one chunk sums into F
    acc = np.zeros((0, n, 6))
    bounds = np.zeros(2, np.int64)
    dom = np.array([0, 0, 0, 1, 1, 1, 1, 1, 1.0])
    per = np.zeros(3, np.int64)
    pt = np.zeros((6, 2, 2))
    pt[2] = 0.5
    delta = 2 * r - 1.99e-3
    for e01 in (2e8, 7e8):
        pt[0] = [[1e8, e01], [e01, 4e8]]
        pair_scatter(
            n,
            P,
            IA,
            nbf,
            pstart,
            nown,
            hist,
            live,
            clist,
            work,
            F,
            acc,
            bounds,
            pt,
            dom,
            per,
            1e-7,
        )
        e_pairs = np.array([e01, e01, e01, 4e8])  # contacts 0-1, 1-2, 2-3, 3-4
        f = 4 / 3 * e_pairs * np.sqrt(r / 2) * delta**1.5
        want = np.r_[-f[0], f[:-1] - f[1:], f[-1]]
        np.testing.assert_allclose(F[:n, 0], want, rtol=0, atol=1e-9 * f.max())
