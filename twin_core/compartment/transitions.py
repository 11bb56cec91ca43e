"""Cell-to-cell particle transitions at a lag: the flows of a Markov-state compartment model.

Face-crossing counts (``crossings_*``) count every passage of a cell face, so a particle that
rattles on a face while the bed around it does not move is counted as exchange; on the seed-
size blender (r = 1 mm, 4 mm cells) the model built from them mixes a near-stagnant bottom
layer with the conveyed powder above it (docs/compartment.md).  The Markov-state-model
estimator instead counts where each particle is a lag tau later (Prinz et al., *J. Chem.
Phys.* 134, 174105, 2011: transition counts C_ij(tau) over all time origins, the
maximum-likelihood transition matrix P_ij = C_ij / sum_j C_ij).  As a compartment network
(a continuous-time Markov chain with rates k_ij = P_ij / tau, i != j) the mass flow from cell
i to cell j is

    F_ij = M_i k_ij = m_p C_ij / (n_origins tau),        M_i = m_p sum_j C_ij / n_origins,

the particle mass times the transitions counted per unit of observed time.  Rattling inside
the lag cancels; jumps across several cells (fast particles thrown by a blade) are kept as
direct edges.  The axial axis is periodic: ``shift`` is the number of periods crossed
(+1 forward through the periodic face, -1 backward), from the particle's unwrapped axial
coordinate.

Frames are ``FrameWriter`` snapshots (every 0.1 s in the blender scene).  A particle may move
more than half a period between two frames; the unwrapped displacement is the periodic image
closest to the trapezoidal estimate (v_0 + v_1) dt / 2 from the frames' velocities (on the
seed-size run at 100 rpm the frames give 38,223 transits against 38,224 recorded every step).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from twin_core.compartment.grid_index import cell_index

TRANSITION_KEYS: tuple[str, ...] = (
    "transition_src",
    "transition_dst",
    "transition_shift",
    "transition_count",
    "transition_lag_s",
    "transition_origins",
)


@dataclass(frozen=True)
class CellTransitions:
    """Particle transition counts between grid cells at one lag.

    ``src``, ``dst``: flat cell indices (C order over (nx, ny, nz)); ``shift``: periods of the
    axial axis crossed (-1, 0, +1); ``count``: transitions observed; ``lag_s``: the lag;
    ``origins``: time origins counted (frame pairs); ``dropped``: transitions not kept
    (a position outside the grid, or a jump of a whole period or more).
    """

    src: np.ndarray
    dst: np.ndarray
    shift: np.ndarray
    count: np.ndarray
    lag_s: float
    origins: int
    dropped: int = 0

    def flows_kg_s(self, particle_mass_kg: float) -> np.ndarray:
        """F = m_p C / (n_origins tau) per listed transition (kg/s; module docstring)."""
        return particle_mass_kg * self.count / (self.origins * self.lag_s)

    def to_dict(self) -> dict[str, Any]:
        """Arrays keyed as in the grid-field file format (``transition_*``)."""
        return {
            "transition_src": self.src,
            "transition_dst": self.dst,
            "transition_shift": self.shift,
            "transition_count": self.count,
            "transition_lag_s": np.float64(self.lag_s),
            "transition_origins": np.int64(self.origins),
        }


def unwrap_periodic(x: np.ndarray, v: np.ndarray, dt: np.ndarray, length: float) -> np.ndarray:
    """Unwrapped periodic coordinate of every particle over a frame series.

    ``x`` (n_frames, n) wrapped coordinates, ``v`` (n_frames, n) the velocity component,
    ``dt`` (n_frames - 1,) frame intervals; each displacement is the periodic image of the
    raw difference closest to (v_k + v_{k+1}) dt_k / 2 (module docstring).
    """
    x = np.asarray(x, dtype=float)
    raw = np.diff(x, axis=0)
    hint = 0.5 * (v[1:] + v[:-1]) * np.asarray(dt, dtype=float)[:, None]
    d = raw + length * np.round((hint - raw) / length)
    return np.concatenate([x[:1], x[:1] + np.cumsum(d, axis=0)])


def count_transitions(
    times: np.ndarray,
    positions: np.ndarray,
    velocities: np.ndarray,
    edges: tuple[np.ndarray, np.ndarray, np.ndarray],
    *,
    axial_axis: int = 0,
    lag_frames: int = 1,
) -> CellTransitions:
    """Transition counts C_ij(tau) of particles tracked over frames (module docstring).

    ``times`` (n_frames,), ``positions`` / ``velocities`` (n_frames, n, 3) with the same
    particle in the same column of every frame; tau = ``lag_frames`` frame intervals (the
    frames must be evenly spaced to 5 %).
    """
    times = np.asarray(times, dtype=float)
    positions = np.asarray(positions, dtype=float)
    velocities = np.asarray(velocities, dtype=float)
    nf = times.size
    if positions.shape[0] != nf or positions.ndim != 3 or positions.shape[2] != 3:
        raise ValueError(f"positions must have shape (n_frames={nf}, n, 3), got {positions.shape}")
    if velocities.shape != positions.shape:
        raise ValueError(
            f"velocities must have the shape of positions {positions.shape}, got {velocities.shape}"
        )
    if lag_frames < 1 or lag_frames >= nf:
        raise ValueError(f"lag_frames must be in [1, {nf - 1}], got {lag_frames}")
    dt = np.diff(times)
    if np.any(dt <= 0) or dt.max() > 1.05 * dt.min():
        raise ValueError(
            f"times must be evenly spaced and increasing, got intervals {dt.min():.4g}-"
            f"{dt.max():.4g} s"
        )
    e_ax = edges[axial_axis]
    length = float(e_ax[-1] - e_ax[0])
    shape = tuple(e.size - 1 for e in edges)
    u = unwrap_periodic(positions[:, :, axial_axis], velocities[:, :, axial_axis], dt, length)
    period = np.floor((u - e_ax[0]) / length).astype(np.int64)
    periodic = tuple(a == axial_axis for a in range(3))
    flat = np.empty(u.shape, dtype=np.int64)
    inside = np.empty(u.shape, dtype=bool)
    for k in range(nf):
        # the axial cell from the unwrapped coordinate, so that cell and period agree exactly
        pk = positions[k].copy()
        pk[:, axial_axis] = e_ax[0] + (u[k] - e_ax[0]) - period[k] * length
        flat[k], inside[k] = cell_index(pk, edges, periodic)
    ax_idx = np.unravel_index(flat, shape)[axial_axis]
    s0, s1 = flat[:-lag_frames].ravel(), flat[lag_frames:].ravel()
    sh = (period[lag_frames:] - period[:-lag_frames]).ravel()
    ok = (inside[:-lag_frames] & inside[lag_frames:]).ravel()
    # a kept shift must be a jump of less than one period: +1 lands in a lower slice
    a0, a1 = ax_idx[:-lag_frames].ravel(), ax_idx[lag_frames:].ravel()
    ok &= (sh == 0) | ((sh == 1) & (a1 < a0)) | ((sh == -1) & (a1 > a0))
    dropped = int((~ok).sum())
    keep = ok & ~((s0 == s1) & (sh == 0))
    ncell = int(np.prod(shape))
    key = (s0[keep] * ncell + s1[keep]) * 3 + (sh[keep] + 1)
    uk, cnt = np.unique(key, return_counts=True)
    return CellTransitions(
        src=(uk // 3) // int(np.prod(shape)),
        dst=(uk // 3) % int(np.prod(shape)),
        shift=(uk % 3 - 1).astype(np.int64),
        count=cnt.astype(np.int64),
        lag_s=float(lag_frames * dt.mean()),
        origins=int(nf - lag_frames),
        dropped=dropped,
    )


def frames_arrays(frames: Iterable[Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(times, positions, velocities) of frames (objects with ``t``, ``ids``, ``positions``,
    ``velocities``), each frame's particles ordered by id; only particles present in every
    frame are kept."""
    ts, ids, ps, vs = [], [], [], []
    for f in frames:
        o = np.argsort(f.ids, kind="stable")
        ts.append(float(f.t))
        ids.append(np.asarray(f.ids)[o])
        ps.append(np.asarray(f.positions, dtype=float)[o])
        vs.append(np.asarray(f.velocities, dtype=float)[o])
    if len(ts) < 2:
        raise ValueError(f"frames: need >= 2 frames, got {len(ts)}")
    common = ids[0]
    for i in ids[1:]:
        common = np.intersect1d(common, i, assume_unique=True)
    if common.size == 0:
        raise ValueError("frames: no particle is present in every frame")
    sel = [np.searchsorted(i, common) for i in ids]
    return (
        np.asarray(ts),
        np.stack([p[s] for p, s in zip(ps, sel)]),
        np.stack([v[s] for v, s in zip(vs, sel)]),
    )


def mirror_transitions(
    tr: CellTransitions, shape: tuple[int, int, int], axis: int, periodic: bool
) -> CellTransitions:
    """The transitions seen with ``axis`` reversed (cell index i -> n - 1 - i along it; the
    period shift changes sign when ``axis`` is the periodic axial one)."""

    def flip(flat: np.ndarray) -> np.ndarray:
        idx = list(np.unravel_index(flat, shape))
        idx[axis] = shape[axis] - 1 - idx[axis]
        return np.ravel_multi_index(tuple(idx), shape)

    return CellTransitions(
        src=flip(tr.src),
        dst=flip(tr.dst),
        shift=-tr.shift if periodic else tr.shift,
        count=tr.count,
        lag_s=tr.lag_s,
        origins=tr.origins,
        dropped=tr.dropped,
    )


def validate_transitions(data: Any, shape: tuple[int, int, int]) -> CellTransitions | None:
    """``CellTransitions`` from the ``transition_*`` keys of a grid-field mapping (all or none),
    or None; raises ``ValueError`` naming the key."""
    present = [k for k in TRANSITION_KEYS if k in data]
    if not present:
        return None
    if len(present) != len(TRANSITION_KEYS):
        missing = sorted(set(TRANSITION_KEYS) - set(present))
        raise ValueError(f"fields: transition keys come as a set; missing {missing}")
    arrs = {k: np.asarray(data[k]) for k in TRANSITION_KEYS}
    n = arrs["transition_src"].shape
    ncell = int(np.prod(shape))
    for k in ("transition_src", "transition_dst", "transition_shift", "transition_count"):
        a = arrs[k]
        if a.ndim != 1 or a.shape != n or not np.issubdtype(a.dtype, np.integer):
            raise ValueError(
                f"fields: key {k!r} must be a 1-D integer array of shape {n}, "
                f"got {a.shape} {a.dtype}"
            )
    for k in ("transition_src", "transition_dst"):
        a = arrs[k]
        if a.size and (a.min() < 0 or a.max() >= ncell):
            raise ValueError(
                f"fields: key {k!r} must index the {ncell} cells, got {a.min()}..{a.max()}"
            )
    sh = arrs["transition_shift"]
    if sh.size and np.abs(sh).max() > 1:
        raise ValueError(f"fields: key 'transition_shift' must be -1, 0 or +1, got {sh.max()}")
    if arrs["transition_count"].size and arrs["transition_count"].min() < 1:
        raise ValueError("fields: key 'transition_count' must be >= 1")
    lag = float(arrs["transition_lag_s"].reshape(()))
    if not np.isfinite(lag) or lag <= 0:
        raise ValueError(f"fields: key 'transition_lag_s' must be > 0, got {lag}")
    origins = int(arrs["transition_origins"].reshape(()))
    if origins < 1:
        raise ValueError(f"fields: key 'transition_origins' must be >= 1, got {origins}")
    return CellTransitions(
        src=arrs["transition_src"].astype(np.int64),
        dst=arrs["transition_dst"].astype(np.int64),
        shift=sh.astype(np.int64),
        count=arrs["transition_count"].astype(np.int64),
        lag_s=lag,
        origins=origins,
    )
