"""Inter-compartment mass flows: the seed's Eq. (1) and mass-conserving flows.

Cell-face flows use the layout of the ``crossings_*`` keys: ``flows[axis]`` (nx,ny,nz,2) in
kg/s through the + face of each cell, [...,0] in the + direction, [...,1] in the - one.

* :func:`cell_flows_from_crossings`: counts x particle mass / duration (exact when counts
  come from particle tracking).
* :func:`cell_flows_from_velocity`: first-order upwind face fluxes
  ``F = A rho_up max(v_f, 0)`` with ``v_f`` the mean normal velocity of the two cells and
  ``rho_up`` the bulk density (holdup / volume) of the upwind cell (finite-volume upwinding,
  e.g. LeVeque, *Finite Volume Methods for Hyperbolic Problems*, 2002, ch. 4).
* :func:`aggregate_flows`: sum of cell-face flows between distinct compartments.
* :func:`seed_flows`: chapter 5 Eq. (1), ``F_ij = A_ij (v_i - v_j)`` per direction, kept for
  comparison; it does not conserve mass (docs/seed.md).
* :func:`project_flows`: minimal-norm correction of a flow vector onto exact conservation
  with non-negative flows, solved by a semismooth Newton method on the dual of the QP
  ``min 1/2 sum w (f - f0)^2  s.t.  C f = b, f >= 0`` (KKT: ``f = max(0, f0 + W^-1 C^T l)``;
  Qi & Sun 1993, Math. Program. 58, 353) and polished by an exact equality solve on the
  final active set.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from twin_core.compartment.fields import GridFields

Flows = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class FlowGraph:
    """Directed compartment-to-compartment flows (kg/s), one edge per (src, dst, wrap).

    ``wrap`` marks flows through the periodic face of the axial axis.  ``dropped_kg_s`` is the
    total cell-face flow lost because one side lay outside every compartment (empty cells).
    """

    n: int
    src: np.ndarray
    dst: np.ndarray
    rate: np.ndarray
    wrap: np.ndarray
    dropped_kg_s: float = 0.0


def cell_flows_from_crossings(fields: GridFields) -> Flows:
    """Cell-face mass flows (kg/s) from crossing counts: N m_p / duration."""
    if fields.crossings is None:
        raise ValueError("fields: crossings_x/y/z are required for flow_source='crossings'")
    k = fields.particle_mass_kg / fields.duration_s
    return tuple(c * k for c in fields.crossings)  # type: ignore[return-value]


def _shift(a: np.ndarray, axis: int, periodic: bool, fill: float = 0.0) -> np.ndarray:
    """Value of the + neighbour along ``axis`` (wrapping if periodic, ``fill`` past a wall)."""
    out = np.roll(a, -1, axis=axis)
    if not periodic:
        idx = [slice(None)] * a.ndim
        idx[axis] = -1
        out[tuple(idx)] = fill
    return out


def cell_flows_from_velocity(fields: GridFields, mask: np.ndarray) -> Flows:
    """Upwind face mass flows from time-averaged velocities (module docstring).

    Faces with an empty cell on either side and the last face of a closed axis carry none.
    """
    rho = np.divide(fields.holdup_kg, fields.cell_volume, out=np.zeros(fields.shape), where=mask)
    out = []
    for axis in range(3):
        per = fields.periodic[axis]
        v = np.where(mask, fields.velocity[..., axis], 0.0)
        v_n = _shift(v, axis, per)
        ok = mask & _shift(mask, axis, per, fill=False).astype(bool)
        vf = 0.5 * (v + v_n)
        area = fields.face_area(axis)
        fwd = np.where(ok, area * rho * np.maximum(vf, 0.0), 0.0)
        bwd = np.where(ok, area * _shift(rho, axis, per) * np.maximum(-vf, 0.0), 0.0)
        out.append(np.stack([fwd, bwd], axis=-1))
    return (out[0], out[1], out[2])


def aggregate_flows(
    flows: Flows, labels: np.ndarray, periodic: tuple[bool, bool, bool], axial_axis: int = 0
) -> FlowGraph:
    """Sum cell-face flows between distinct compartments of ``labels`` (-1 = empty).

    Flows inside one compartment cancel in its balance and are dropped; flows with an empty
    cell on either side are counted in ``dropped_kg_s``.
    """
    n = int(labels.max()) + 1
    keys, rates = [], []
    dropped = 0.0
    for axis in range(3):
        per = periodic[axis]
        a = labels
        b = _shift(labels, axis, per, fill=-1)
        wrap = np.zeros(labels.shape, dtype=bool)
        if per and axis == axial_axis:
            idx = [slice(None)] * 3
            idx[axis] = -1
            wrap[tuple(idx)] = True
        for direction in (0, 1):
            f = flows[axis][..., direction]
            s, d = (a, b) if direction == 0 else (b, a)
            both = (s >= 0) & (d >= 0)
            dropped += float(f[~both].sum())
            use = both & (s != d) & (f > 0)
            keys.append(np.stack([s[use], d[use], wrap[use].astype(np.int64)], axis=1))
            rates.append(f[use])
    return _summed_graph(n, np.concatenate(keys).astype(np.int64), np.concatenate(rates), dropped)


def _summed_graph(n: int, key: np.ndarray, rate: np.ndarray, dropped: float) -> FlowGraph:
    """FlowGraph of the rates summed per distinct (src, dst, wrap) row of ``key``."""
    if key.size == 0:
        z = np.zeros(0, dtype=np.int64)
        return FlowGraph(n, z, z.copy(), np.zeros(0), np.zeros(0, bool), dropped)
    uk, inv = np.unique(key, axis=0, return_inverse=True)
    r = np.bincount(inv.ravel(), weights=rate, minlength=uk.shape[0])
    return FlowGraph(n, uk[:, 0], uk[:, 1], r, uk[:, 2].astype(bool), dropped)


def aggregate_transitions(fields: GridFields, labels: np.ndarray) -> FlowGraph:
    """Sum the cell-to-cell transition flows F_ij = m_p C_ij / (n_origins tau) of
    ``fields.transitions`` (:mod:`twin_core.compartment.transitions`) between distinct
    compartments of ``labels`` (-1 = empty); a transition with a period shift becomes a
    ``wrap`` edge (its direction follows from the slices it joins, :func:`wrap_directions`).
    Transitions inside one compartment are dropped; those touching an empty cell are counted
    in ``dropped_kg_s``."""
    tr = fields.transitions
    if tr is None:
        raise ValueError("fields: transition_* keys are required for flow_source='transitions'")
    n = int(labels.max()) + 1
    flat = labels.ravel()
    s, d = flat[tr.src], flat[tr.dst]
    rate = tr.flows_kg_s(fields.particle_mass_kg)
    both = (s >= 0) & (d >= 0)
    dropped = float(rate[~both].sum())
    use = both & ((s != d) | (tr.shift != 0))
    if np.any(use & (s == d)):
        raise ValueError(
            "a transition through the periodic face stays in one compartment: "
            "compartments must not span the whole axial period"
        )
    key = np.stack([s[use], d[use], (tr.shift[use] != 0).astype(np.int64)], axis=1)
    return _summed_graph(n, key, rate[use], dropped)


def wrap_directions(
    slice_index: np.ndarray, src: np.ndarray, dst: np.ndarray, wrap: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Forward and backward masks of the ``wrap`` edges of a periodic network: a forward
    crossing of the periodic face goes from a higher axial slice to a lower one (e.g. the
    last to the first), a backward one the other way; jumps are shorter than one period."""
    w = np.asarray(wrap).astype(bool)
    s, d = slice_index[src], slice_index[dst]
    fwd = w & (s > d)
    bwd = w & (s < d)
    if np.any(w & (s == d)):
        raise ValueError("a wrap edge must join two different axial slices")
    return fwd, bwd


def seed_flows(fields: GridFields, labels: np.ndarray, axial_axis: int = 0) -> FlowGraph:
    """Chapter 5 Eq. (1): F_ij(k) = A_ij(k) (v_i(k) - v_j(k)), for comparison only.

    ``A_ij(k)`` is the interfacial area of compartments i and j on faces normal to k,
    ``v_i(k)`` the mean k-velocity of the cells of compartment i; a positive F_ij is a flow
    from i to j.  The volumetric flow is turned into mass flow with the mean bulk density
    (holdup / volume) of the two compartments.  The seed gives no upwinding and no
    conservation: a uniform plug flow gives zero flow, and compartment balances do not close.
    """
    n = int(labels.max()) + 1
    hit = labels >= 0
    lab = labels[hit]
    vol = np.bincount(lab, weights=fields.cell_volume[hit], minlength=n)
    cnt = np.bincount(lab, minlength=n).astype(float)
    mass = np.bincount(lab, weights=fields.holdup_kg[hit], minlength=n)
    rho = np.divide(mass, vol, out=np.zeros(n), where=vol > 0)
    keys, rates = [], []
    for axis in range(3):
        per = fields.periodic[axis]
        vmean = np.bincount(lab, weights=fields.velocity[..., axis][hit], minlength=n)
        vmean = np.divide(vmean, cnt, out=np.zeros(n), where=cnt > 0)
        a = labels
        b = _shift(labels, axis, per, fill=-1)
        use = (a >= 0) & (b >= 0) & (a != b)
        if not use.any():
            continue
        pair = np.stack([a[use], b[use]], axis=1)
        area = fields.face_area(axis)[use]
        wrap = np.zeros(labels.shape, dtype=bool)
        if per and axis == axial_axis:
            idx = [slice(None)] * 3
            idx[axis] = -1
            wrap[tuple(idx)] = True
        wr = wrap[use].astype(np.int64)
        up, inv = np.unique(np.column_stack([pair, wr]), axis=0, return_inverse=True)
        A = np.bincount(inv.ravel(), weights=area, minlength=up.shape[0])
        i, j = up[:, 0], up[:, 1]
        F = A * (vmean[i] - vmean[j]) * 0.5 * (rho[i] + rho[j])
        pos = F > 0
        keys.append(np.column_stack([i[pos], j[pos], up[pos, 2]]))
        rates.append(F[pos])
        neg = F < 0
        keys.append(np.column_stack([j[neg], i[neg], up[neg, 2]]))
        rates.append(-F[neg])
    key = np.concatenate(keys).astype(np.int64)
    rate = np.concatenate(rates)
    uk, inv = np.unique(key, axis=0, return_inverse=True)
    r = np.bincount(inv.ravel(), weights=rate, minlength=uk.shape[0])
    return FlowGraph(n, uk[:, 0], uk[:, 1], r, uk[:, 2].astype(bool), 0.0)


def node_balance(
    n: int,
    src: np.ndarray,
    dst: np.ndarray,
    rate: np.ndarray,
    feed: np.ndarray | None = None,
    discharge: np.ndarray | None = None,
) -> np.ndarray:
    """Inflow minus outflow (kg/s) of every node: zero for a conserving network."""
    bal = np.bincount(dst, weights=rate, minlength=n) - np.bincount(src, weights=rate, minlength=n)
    if feed is not None:
        bal = bal + feed
    if discharge is not None:
        bal = bal - discharge
    return bal


def imbalance_report(graph: FlowGraph, scale: float | None = None) -> dict[str, float]:
    """Mass imbalance of a flow graph: max and RMS |in - out| per node, absolute (kg/s) and
    relative to ``scale`` (default: the mean total outflow of a node)."""
    bal = node_balance(graph.n, graph.src, graph.dst, graph.rate)
    out = np.bincount(graph.src, weights=graph.rate, minlength=graph.n)
    if scale is None:
        scale = float(out.mean()) if out.size and out.mean() > 0 else 1.0
    return {
        "max_abs_kg_s": float(np.abs(bal).max()) if bal.size else 0.0,
        "rms_abs_kg_s": float(np.sqrt(np.mean(bal**2))) if bal.size else 0.0,
        "max_rel": float(np.abs(bal).max() / scale) if bal.size else 0.0,
        "rms_rel": float(np.sqrt(np.mean(bal**2)) / scale) if bal.size else 0.0,
        "scale_kg_s": float(scale),
    }


def incidence(n: int, src: np.ndarray, dst: np.ndarray) -> sp.csr_matrix:
    """Node-edge incidence C (n x E): +1 at the destination, -1 at the source of each edge,
    so that ``C f`` is inflow minus outflow."""
    e = src.size
    rows = np.concatenate([dst, src])
    cols = np.concatenate([np.arange(e), np.arange(e)])
    vals = np.concatenate([np.ones(e), -np.ones(e)])
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, e))


def _polish_active_set(
    C: sp.csr_matrix, b: np.ndarray, f0: np.ndarray, winv: np.ndarray, act: np.ndarray
) -> np.ndarray | None:
    """min 1/2 sum w (f - f0)^2 s.t. C f = b on the edges ``act`` (the others 0): f_A =
    f0_A + W^-1 C_A^T l with (C_A W^-1 C_A^T) l = b - C_A f0_A, repeated without the edges that
    come out negative; None if it does not end with f >= 0 and C f = b (to 1e-12)."""
    act = act.copy()
    for _ in range(20):
        idx = np.flatnonzero(act)
        if idx.size == 0:
            return None
        CA = C[:, idx]
        H = (CA @ sp.diags(winv[idx]) @ CA.T).tocsc()
        rhs = b - CA @ f0[idx]
        lam = spla.lsqr(H, rhs, atol=1e-16, btol=1e-16, iter_lim=20 * H.shape[0])[0]
        fa = f0[idx] + winv[idx] * (CA.T @ lam)
        if fa.min(initial=0.0) >= 0.0:
            f = np.zeros(f0.size)
            f[idx] = fa
            return f if np.abs(C @ f - b).max(initial=0.0) <= 1e-12 else None
        act[idx[fa < 0]] = False
    return None


def project_flows(
    C: sp.spmatrix,
    b: np.ndarray,
    f0: np.ndarray,
    weights: np.ndarray | None = None,
    tol: float = 1e-13,
    max_iter: int = 100,
    tiny: float = 1e-11,
) -> np.ndarray:
    """Minimal-norm correction onto ``C f = b`` with ``f >= 0`` (module docstring).

    Solves ``min 1/2 sum_e w_e (f_e - f0_e)^2`` subject to ``C f = b`` and ``f >= 0`` for a
    sparse constraint matrix C (e.g. :func:`incidence` rows of the balanced nodes plus a
    throughput row).  Residual ``|C f - b|_inf <= tol * max(|f0|_inf, |b|_inf)`` on return.
    Raises ValueError when no non-negative solution exists.
    """
    C = sp.csr_matrix(C, dtype=float)
    f0 = np.asarray(f0, dtype=float)
    b = np.asarray(b, dtype=float)
    m, e = C.shape
    if f0.shape != (e,):
        raise ValueError(f"f0 must have shape ({e},), got {f0.shape}")
    if b.shape != (m,):
        raise ValueError(f"b must have shape ({m},), got {b.shape}")
    w = np.ones(e) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (e,) or np.any(w <= 0):
        raise ValueError("weights must be positive with one per edge")
    scale = max(float(np.abs(f0).max(initial=0.0)), float(np.abs(b).max(initial=0.0)), 1e-300)
    f0s, bs = f0 / scale, b / scale
    winv = 1.0 / w
    CT = C.T.tocsr()
    lam = np.zeros(m)

    def primal(lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        z = f0s + winv * (CT @ lam)
        return np.maximum(z, 0.0), z > 0

    def neg_dual(lam: np.ndarray, f: np.ndarray) -> float:
        return float(-0.5 * np.sum(w * (f - f0s) ** 2) + lam @ (C @ f - bs))

    f, act = primal(lam)
    g = C @ f - bs
    eye = sp.identity(m, format="csc")
    for _ in range(max_iter):
        if np.abs(g).max(initial=0.0) <= tol:
            break
        H = (C @ sp.diags(act * winv) @ CT).tocsc()
        mu = 1e-12 * max(float(H.diagonal().max(initial=0.0)), 1.0)
        try:
            d = spla.spsolve(H + mu * eye, -g)
        except RuntimeError:
            d = spla.lsqr(H, -g, atol=1e-15, btol=1e-15)[0]
        phi0 = neg_dual(lam, f)
        slope = float(g @ d)
        alpha = 1.0
        while True:
            lam_new = lam + alpha * d
            f_new, act_new = primal(lam_new)
            if neg_dual(lam_new, f_new) <= phi0 + 1e-4 * alpha * slope or alpha < 1e-10:
                break
            alpha *= 0.5
        lam, f, act = lam_new, f_new, act_new
        g = C @ f - bs
    resid = float(np.abs(g).max(initial=0.0))
    if resid > max(tol, 1e-10):
        # the Newton steps stalled (a degenerate active set): solve the equality-constrained
        # problem exactly on the active edges, dropping those that come out negative
        polished = _polish_active_set(C, bs, f0s, winv, f > 0)
        if polished is not None:
            f = polished
            resid = float(np.abs(C @ f - bs).max(initial=0.0))
    stalled = resid > max(tol, 1e-10)
    # flows left at round-off level (< ``tiny`` of the largest) are structurally zero: a
    # 1e-17 kg/s trickle into a compartment without outflow would make it a trap of the
    # network; drop them and project again on the remaining edges (the set shrinks, so this
    # terminates).  Newton steps that stall at a kink (a flow that must end exactly at 0,
    # residual ~ that flow) are finished the same way with flows below 1e-6 of the largest.
    cut = 1e-6 if stalled else tiny
    small = (f > 0) & (f < cut * float(f.max(initial=0.0)))
    if stalled and not small.any():
        raise ValueError(
            f"project_flows: no non-negative conserving flows found (residual {resid * scale:.3e})"
        )
    if small.any():
        keep = ~small & (f > 0)
        out = np.zeros(e)
        if keep.any():
            out[keep] = project_flows(
                C[:, np.flatnonzero(keep)],
                b,
                f0[keep],
                weights=w[keep],
                tol=tol,
                max_iter=max_iter,
                tiny=tiny,
            )
        return out
    return f * scale
