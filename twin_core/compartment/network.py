"""Linear compartment network: holdups, flows, tracer dynamics, RTD and RSD.

Tracer balance of compartment i (holdup M_i kg, concentration c_i, tracer mass m_i = M_i c_i):

    dm_i/dt = sum_j F_ji m_j / M_j - (sum_j F_ij + D_i) m_i / M_i + S_i c_in(t)

with F_ij the flow i -> j (kg/s), D_i the discharge to the outlet and S_i the feed.  This is
``dm/dt = A m + s c_in``, the standard network-of-ideal-mixers model (Levenspiel, *Chemical
Reaction Engineering*, 3rd ed., ch. 12).  For a conserving network (inflow = outflow per
compartment) with throughput Q = sum S = sum D:

* the impulse response E(t) = d . m(t) / Q with m(0) = S / Q integrates to 1 and its mean
  is tau = sum M / Q (closed-vessel theorem: Danckwerts 1953, Chem. Eng. Sci. 2, 1);
* F(t) = 1 - sum m(t), so E and F are exact at the grid points.

Seen per particle, A is the generator of a continuous-time Markov chain (rate F_ij / M_i),
which is what the particle-walk surrogate samples.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.linalg import expm
from scipy.sparse.linalg import expm_multiply

from twin_core.compartment.flows import (
    incidence,
    node_balance,
    project_flows,
    wrap_directions,
)


@dataclass
class CompartmentNetwork:
    """A network of ideally mixed compartments with internal flows, feed and discharge.

    ``holdup`` (n,) kg; edges ``src -> dst`` with ``rate`` kg/s; ``feed`` and ``discharge``
    (n,) kg/s to and from outside; ``wrap`` marks edges through the periodic face (periodic
    networks); ``slice_index`` (n,) the axial slice of each compartment; ``centroid`` (n,3) m.
    """

    holdup: np.ndarray
    src: np.ndarray
    dst: np.ndarray
    rate: np.ndarray
    feed: np.ndarray | None = None
    discharge: np.ndarray | None = None
    wrap: np.ndarray | None = None
    slice_index: np.ndarray | None = None
    centroid: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.holdup = np.asarray(self.holdup, dtype=float)
        n = self.holdup.size
        self.src = np.asarray(self.src, dtype=np.int64)
        self.dst = np.asarray(self.dst, dtype=np.int64)
        self.rate = np.asarray(self.rate, dtype=float)
        if not (self.src.shape == self.dst.shape == self.rate.shape):
            raise ValueError(
                f"src, dst, rate must have equal shapes, got {self.src.shape}, "
                f"{self.dst.shape}, {self.rate.shape}"
            )
        if np.any(self.holdup <= 0):
            raise ValueError(f"holdup must be > 0, got min {self.holdup.min()}")
        if self.src.size and (self.src.min() < 0 or max(self.src.max(), self.dst.max()) >= n):
            raise ValueError(f"edge indices must lie in [0, {n})")
        if self.src.size and self.dst.min() < 0:
            raise ValueError(f"edge indices must lie in [0, {n})")
        if np.any(self.rate < 0):
            raise ValueError(f"rate must be >= 0, got min {self.rate.min()}")
        self.feed = np.zeros(n) if self.feed is None else np.asarray(self.feed, dtype=float)
        self.discharge = (
            np.zeros(n) if self.discharge is None else np.asarray(self.discharge, dtype=float)
        )
        for name in ("feed", "discharge"):
            v = getattr(self, name)
            if v.shape != (n,):
                raise ValueError(f"{name} must have shape ({n},), got {v.shape}")
            if np.any(v < 0):
                raise ValueError(f"{name} must be >= 0, got min {v.min()}")

    @property
    def n(self) -> int:
        return int(self.holdup.size)

    @property
    def throughput(self) -> float:
        """Q = total feed (kg/s)."""
        return float(self.feed.sum())

    @property
    def total_holdup(self) -> float:
        return float(self.holdup.sum())

    @property
    def mean_residence_time(self) -> float:
        """tau = V / Q (s) of a conserving network (closed-vessel theorem)."""
        q = self.throughput
        if q <= 0:
            raise ValueError("mean_residence_time needs a throughput > 0")
        return self.total_holdup / q

    def balance(self) -> np.ndarray:
        """Inflow minus outflow (kg/s) per compartment, feed and discharge included."""
        return node_balance(self.n, self.src, self.dst, self.rate, self.feed, self.discharge)

    def rate_matrix(self, scale: float = 1.0) -> sp.csr_matrix:
        """Sparse A with dm/dt = A m (tracer mass; flows multiplied by ``scale``)."""
        n = self.n
        k = self.rate / self.holdup[self.src]
        out = np.bincount(self.src, weights=k, minlength=n) + self.discharge / self.holdup
        rows = np.concatenate([self.dst, np.arange(n)])
        cols = np.concatenate([self.src, np.arange(n)])
        vals = np.concatenate([k, -out]) * scale
        return sp.csr_matrix((vals, (rows, cols)), shape=(n, n))

    def impulse_state(self) -> np.ndarray:
        """Tracer mass distribution of a unit impulse at the inlet: S / Q."""
        q = self.throughput
        if q <= 0:
            raise ValueError("impulse response needs a throughput > 0 (no feed)")
        return self.feed / q

    def impulse_response(self, t: np.ndarray) -> np.ndarray:
        """E(t) (1/s) on a uniform grid t >= 0, exact at the grid points (module docstring)."""
        e, _ = _propagate(self, np.asarray(t, dtype=float), self.impulse_state())
        return e

    def cumulative(self, t: np.ndarray) -> np.ndarray:
        """F(t) = 1 - tracer left in the network, exact at the grid points."""
        _, left = _propagate(self, np.asarray(t, dtype=float), self.impulse_state())
        return 1.0 - left

    def states(self, t: np.ndarray, m0: np.ndarray, scale: float = 1.0) -> np.ndarray:
        """Tracer masses m(t) (len(t), n) of the unforced network from m(0) = m0 (t >= 0)."""
        t = np.asarray(t, dtype=float)
        if t.size == 1:
            return np.asarray(m0, dtype=float)[None, :]
        dt = np.diff(t)
        if np.any(dt <= 0) or not np.allclose(dt, dt[0], rtol=1e-9, atol=0):
            raise ValueError("t must be uniform and increasing")
        A = self.rate_matrix(scale).tocsc()
        m = np.asarray(m0, dtype=float)
        if t[0] > 0:
            m = expm_multiply(A * t[0], m)
        return expm_multiply(A, m, start=0.0, stop=t[-1] - t[0], num=t.size, endpoint=True)


def _uniform_dt(t: np.ndarray) -> float:
    if t.ndim != 1 or t.size < 2:
        raise ValueError(f"t must be a 1-D grid with >= 2 points, got shape {t.shape}")
    dt = np.diff(t)
    if np.any(dt <= 0) or not np.allclose(dt, dt[0], rtol=1e-6, atol=0):
        raise ValueError("t must be uniform and increasing")
    if t[0] < 0:
        raise ValueError(f"t must start at >= 0, got {t[0]}")
    return float(dt[0])


def _propagate(
    net: CompartmentNetwork, t: np.ndarray, m0: np.ndarray, block: int = 16
) -> tuple[np.ndarray, np.ndarray]:
    """Discharge rate d.m(t_k)/Q-normalised and tracer left 1.m(t_k) on a uniform grid.

    Exact discrete propagator Phi = expm(A dt) (dense, Pade) applied block-wise: the output
    rows r_b = d Phi^b, s_b = 1 Phi^b are precomputed for b < block, so a block of outputs
    costs one small matrix-vector product.  Stops once the tracer left is < 1e-15.
    """
    dt = _uniform_dt(t)
    n = net.n
    dvec = net.discharge / net.holdup
    m = np.asarray(m0, dtype=float)
    if n > 1200:  # large networks: sparse action of the exponential (Al-Mohy & Higham 2011)
        Asp = net.rate_matrix().tocsc()
        if t[0] > 0:
            m = expm_multiply(Asp * t[0], m)
        ms = expm_multiply(Asp, m, start=0.0, stop=t[-1] - t[0], num=t.size, endpoint=True)
        return ms @ dvec, ms.sum(axis=1)
    A = net.rate_matrix().toarray()
    if t[0] > 0:
        m = expm(A * t[0]) @ m
    Phi = expm(A * dt)
    B = min(block, t.size)
    R = np.empty((B, n))
    S = np.empty((B, n))
    r, s = dvec.copy(), np.ones(n)
    for b in range(B):
        R[b], S[b] = r, s
        r = r @ Phi
        s = s @ Phi
    PhiB = np.linalg.matrix_power(Phi, B)
    e = np.zeros(t.size)
    left = np.zeros(t.size)
    total0 = float(np.abs(m0).sum()) or 1.0
    for k0 in range(0, t.size, B):
        k1 = min(k0 + B, t.size)
        e[k0:k1] = R[: k1 - k0] @ m
        left[k0:k1] = S[: k1 - k0] @ m
        if abs(left[k1 - 1]) < 1e-15 * total0 and np.abs(m).sum() < 1e-15 * total0:
            break
        m = PhiB @ m
    return e, left


# ----------------------------------------------------------------------------- sections


def periodic_throughput(net: CompartmentNetwork) -> float:
    """Net flow (kg/s) through the periodic face: forward wrap minus backward wrap flow."""
    if net.wrap is None or net.slice_index is None:
        raise ValueError("network has no wrap/slice information")
    fwd, bwd = _wrap_directions(net)
    return float(net.rate[fwd].sum() - net.rate[bwd].sum())


def _wrap_directions(net: CompartmentNetwork) -> tuple[np.ndarray, np.ndarray]:
    return wrap_directions(net.slice_index, net.src, net.dst, net.wrap)


def open_section(net: CompartmentNetwork, weights: str = "uniform") -> CompartmentNetwork:
    """Cut a conserving periodic section at its periodic face into an open vessel.

    Forward flows through the face become the feed of the first-slice compartments and the
    discharge of the last-slice ones; backward flows through the face are removed (closed-
    closed boundaries, Danckwerts 1953); the feed, discharge and internal flows are then
    projected (:func:`project_flows`) onto exact conservation with total feed = the net
    periodic throughput Q.  Holdups are kept, so the mean residence time is V / Q.
    """
    Q = periodic_throughput(net)
    if Q <= 0:
        raise ValueError(f"net throughput through the periodic face must be > 0, got {Q}")
    fwd, bwd = _wrap_directions(net)
    n = net.n
    internal = ~(fwd | bwd)
    feed0 = np.bincount(net.dst[fwd], weights=net.rate[fwd], minlength=n)
    dis0 = np.bincount(net.src[fwd], weights=net.rate[fwd], minlength=n)
    fi = np.flatnonzero(feed0 > 0)
    di = np.flatnonzero(dis0 > 0)
    outside = n
    src = np.concatenate([net.src[internal], np.full(fi.size, outside), di])
    dst = np.concatenate([net.dst[internal], fi, np.full(di.size, outside)])
    f0 = np.concatenate([net.rate[internal], feed0[fi], dis0[di]])
    C = incidence(n + 1, src, dst)[:n]
    row = np.zeros(src.size)
    row[src == outside] = 1.0
    C = sp.vstack([C, sp.csr_matrix(row)]).tocsr()
    b = np.concatenate([np.zeros(n), [Q]])
    w = _weights(f0, weights)
    f = project_flows(C, b, f0, weights=w)
    ni = int(internal.sum())
    feed = np.zeros(n)
    feed[fi] = f[ni : ni + fi.size]
    dis = np.zeros(n)
    dis[di] = f[ni + fi.size :]
    keep = f[:ni] > 0
    meta = dict(net.meta)
    meta["open_correction_rel"] = float(np.linalg.norm(f - f0) / max(np.linalg.norm(f0), 1e-300))
    return CompartmentNetwork(
        holdup=net.holdup.copy(),
        src=net.src[internal][keep],
        dst=net.dst[internal][keep],
        rate=f[:ni][keep],
        feed=feed,
        discharge=dis,
        wrap=np.zeros(int(keep.sum()), dtype=bool),
        slice_index=None if net.slice_index is None else net.slice_index.copy(),
        centroid=None if net.centroid is None else net.centroid.copy(),
        meta=meta,
    )


def _weights(f0: np.ndarray, kind: str) -> np.ndarray:
    """Projection weights: 'uniform' (minimal Euclidean correction) or 'relative'
    (minimal correction relative to each flow, w = 1 / f0)."""
    if kind == "uniform":
        return np.ones_like(f0)
    if kind == "relative":
        ref = max(float(f0.max(initial=0.0)), 1e-300)
        return 1.0 / np.maximum(f0, 1e-6 * ref)
    raise ValueError(f"weights must be 'uniform' or 'relative', got {kind!r}")


def chain_sections(section: CompartmentNetwork, n_sections: int) -> CompartmentNetwork:
    """Whole blender: ``n_sections`` open sections in series (mixing-cup coupling).

    The discharge of section s is collected and fed to section s+1 with the feed split of
    the section (flow d_i f_j / Q from outlet compartment i to inlet compartment j), so the
    chain's impulse response is exactly the n-fold convolution of the section's (Eq. 8-9).
    """
    if n_sections < 1:
        raise ValueError(f"n_sections must be >= 1, got {n_sections}")
    n = section.n
    Q = section.throughput
    if Q <= 0:
        raise ValueError("section has no feed")
    fi = np.flatnonzero(section.feed > 0)
    di = np.flatnonzero(section.discharge > 0)
    cs = np.repeat(di, fi.size)
    cd = np.tile(fi, di.size)
    cr = section.discharge[cs] * section.feed[cd] / Q
    src, dst, rate = [], [], []
    for s in range(n_sections):
        src.append(section.src + s * n)
        dst.append(section.dst + s * n)
        rate.append(section.rate)
        if s + 1 < n_sections:
            src.append(cs + s * n)
            dst.append(cd + (s + 1) * n)
            rate.append(cr)
    feed = np.zeros(n * n_sections)
    feed[:n] = section.feed
    dis = np.zeros(n * n_sections)
    dis[(n_sections - 1) * n :] = section.discharge
    return CompartmentNetwork(
        holdup=np.tile(section.holdup, n_sections),
        src=np.concatenate(src),
        dst=np.concatenate(dst),
        rate=np.concatenate(rate),
        feed=feed,
        discharge=dis,
        slice_index=None
        if section.slice_index is None
        else np.concatenate(
            [
                section.slice_index + s * (int(section.slice_index.max()) + 1)
                for s in range(n_sections)
            ]
        ),
        meta={"n_sections": n_sections},
    )


def chain_periodic(
    net: CompartmentNetwork, n_sections: int, weights: str = "uniform"
) -> CompartmentNetwork:
    """Whole blender with face-to-face coupling: ``n_sections`` copies of the periodic
    network joined through their periodic faces in both directions (backflow between
    sections kept), cut closed-closed only at the blender inlet and outlet and re-projected
    there (as :func:`open_section`).  Conserving, so its mean residence time is n V / Q;
    unlike :func:`chain_sections` its E is not exactly the n-fold convolution of a section.
    """
    if n_sections < 1:
        raise ValueError(f"n_sections must be >= 1, got {n_sections}")
    Q = periodic_throughput(net)
    if Q <= 0:
        raise ValueError(f"net throughput through the periodic face must be > 0, got {Q}")
    fwd, bwd = _wrap_directions(net)
    n = net.n
    internal = ~(fwd | bwd)
    src, dst, f0 = [], [], []
    for c in range(n_sections):
        off = c * n
        src.append(net.src[internal] + off)
        dst.append(net.dst[internal] + off)
        f0.append(net.rate[internal])
        if c + 1 < n_sections:
            src += [net.src[fwd] + off, net.src[bwd] + off + n]
            dst += [net.dst[fwd] + off + n, net.dst[bwd] + off]
            f0 += [net.rate[fwd], net.rate[bwd]]
    N = n * n_sections
    outside = N
    feed0 = np.bincount(net.dst[fwd], weights=net.rate[fwd], minlength=n)
    dis0 = np.bincount(net.src[fwd], weights=net.rate[fwd], minlength=n)
    fi = np.flatnonzero(feed0 > 0)
    di = np.flatnonzero(dis0 > 0)
    ni = int(sum(a.size for a in src))
    src = np.concatenate(src + [np.full(fi.size, outside), di + (n_sections - 1) * n])
    dst = np.concatenate(dst + [fi, np.full(di.size, outside)])
    f0 = np.concatenate(f0 + [feed0[fi], dis0[di]])
    C = incidence(N + 1, src, dst)[:N]
    row = np.zeros(src.size)
    row[src == outside] = 1.0
    C = sp.vstack([C, sp.csr_matrix(row)]).tocsr()
    f = project_flows(C, np.concatenate([np.zeros(N), [Q]]), f0, weights=_weights(f0, weights))
    feed = np.zeros(N)
    feed[fi] = f[ni : ni + fi.size]
    dis = np.zeros(N)
    dis[di + (n_sections - 1) * n] = f[ni + fi.size :]
    keep = f[:ni] > 0
    return CompartmentNetwork(
        holdup=np.tile(net.holdup, n_sections),
        src=src[:ni][keep],
        dst=dst[:ni][keep],
        rate=f[:ni][keep],
        feed=feed,
        discharge=dis,
        meta={"n_sections": n_sections, "coupling": "faces"},
    )


def first_passage_network(
    net: CompartmentNetwork, n_upstream: int = 2, entry: str = "record"
) -> CompartmentNetwork:
    """Unwrapped periodic network for the first-passage time across one section length.

    Copies -n_upstream..0 of the periodic section are joined through their periodic faces in
    both directions; forward flow out of copy 0 is absorbed (discharge), backward flow out of
    the most upstream copy re-enters that copy's last slice (periodic truncation: every copy
    keeps its flow balance, so no state is a trap; the error is set by the expected number of
    such crossings per transit, ``meta["truncated_crossings"]``).
    The feed marks the entry distribution: ``entry="flux"`` the forward flow into copy 0
    through its inlet face; ``entry="record"`` (default) the stationary law of the entry
    state at record passages (:func:`record_entry`).  With "record" this is the exact RTD of
    a particle walking the network as a Markov chain, timed between successive first
    passages of new multiples of the section length (the DEM transit-time definition).
    """
    if entry not in ("flux", "record"):
        raise ValueError(f"entry must be 'flux' or 'record', got {entry!r}")
    fwd, bwd = _wrap_directions(net)
    n = net.n
    k = n_upstream + 1
    internal = ~(fwd | bwd)
    src, dst, rate = [], [], []
    for c in range(k):
        off = c * n
        src.append(net.src[internal] + off)
        dst.append(net.dst[internal] + off)
        rate.append(net.rate[internal])
        if c + 1 < k:
            src.append(net.src[fwd] + off)
            dst.append(net.dst[fwd] + off + n)
            rate.append(net.rate[fwd])
            src.append(net.src[bwd] + off + n)
            dst.append(net.dst[bwd] + off)
            rate.append(net.rate[bwd])
    src.append(net.src[bwd])
    dst.append(net.dst[bwd])
    rate.append(net.rate[bwd])
    dis = np.zeros(k * n)
    dis[(k - 1) * n :] = np.bincount(net.src[fwd], weights=net.rate[fwd], minlength=n)
    feed = np.zeros(k * n)
    feed[(k - 1) * n :] = np.bincount(net.dst[fwd], weights=net.rate[fwd], minlength=n)
    fp = CompartmentNetwork(
        holdup=np.tile(net.holdup, k),
        src=np.concatenate(src),
        dst=np.concatenate(dst),
        rate=np.concatenate(rate),
        feed=feed,
        discharge=dis,
        meta={"n_upstream": n_upstream, "entry": entry},
    )
    if entry == "record":
        p, occ = record_entry(fp, net.dst[fwd], net.src[fwd], net.rate[fwd], n)
        fp.feed = p * feed.sum()
        # expected number of backward crossings out of the most upstream copy per transit:
        # the events the periodic truncation folds back (0 for an infinite chain of copies)
        fp.meta["truncated_crossings"] = float(
            np.sum(net.rate[bwd] / net.holdup[net.src[bwd]] * occ[net.src[bwd]])
        )
    q_net = float(net.rate[fwd].sum() - net.rate[bwd].sum())
    if q_net > 0:
        fp.meta["tau"] = net.total_holdup / q_net
    return fp


def transit_network(
    net: CompartmentNetwork, n_upstream: int | None = None, tol: float = 1e-4, max_upstream: int = 8
) -> CompartmentNetwork:
    """Record-passage first-passage network with ``n_upstream`` copies, or (None) the fewest
    copies, from 1, whose dropped backward crossings per transit are below ``tol``."""
    if n_upstream is not None:
        return first_passage_network(net, n_upstream)
    for k in range(1, max_upstream + 1):
        fp = first_passage_network(net, k)
        if fp.meta["truncated_crossings"] < tol:
            break
    return fp


def section_tau(section: CompartmentNetwork) -> float:
    """Time scale V/Q of one section: ``meta["tau"]`` of a first-passage network (its feed
    counts gross crossings), else the network's own holdup / throughput."""
    tau = section.meta.get("tau")
    return float(tau) if tau is not None else section.mean_residence_time


def record_entry(
    fp: CompartmentNetwork,
    land: np.ndarray,
    leave: np.ndarray,
    rate: np.ndarray,
    n: int,
    max_iter: int = 200,
    tol: float = 1e-13,
) -> np.ndarray:
    """Stationary entry law at record passages of a first-passage network ``fp`` and the
    time-integrated tracer (-A)^-1 p it leaves in every state.

    Starting from an entry law p on the last copy, the time-integrated tracer is
    (-A)^-1 p and the absorption flux through each forward periodic edge (leave -> land) is
    rate / M_leave times it; the landing law is the next entry law.  Iterating this Markov
    operator converges to its fixed point (power iteration).
    """
    from scipy.sparse.csgraph import breadth_first_order
    from scipy.sparse.linalg import splu

    A = fp.rate_matrix().tocsr()
    off = fp.n - n
    # solve only on the states the tracer can reach from an entry state: unreachable ones
    # (isolated compartments or closed cycles cut off from the main flow) would make -A
    # singular and never hold tracer
    adj = sp.csr_matrix(
        (
            np.ones(fp.src.size + land.size),
            (
                np.concatenate([fp.src, np.full(land.size, fp.n)]),
                np.concatenate([fp.dst, off + land]),
            ),
        ),
        shape=(fp.n + 1, fp.n + 1),
    )
    reach = breadth_first_order(adj, fp.n, directed=True, return_predecessors=False)
    live = np.zeros(fp.n + 1, dtype=bool)
    live[reach] = True
    live = live[: fp.n] & (A.diagonal() < 0)
    idx = np.flatnonzero(live)
    lu = splu((-A[idx][:, idx]).tocsc())
    p = fp.feed / fp.feed.sum()
    for _ in range(max_iter):
        occ = np.zeros(fp.n)
        occ[idx] = lu.solve(p[idx])
        flux = rate / fp.holdup[off + leave] * occ[off + leave]
        p_new = np.zeros(fp.n)
        np.add.at(p_new, off + land, flux)
        p_new /= p_new.sum()
        if np.abs(p_new - p).sum() < tol:
            p = p_new
            break
        p = p_new
    occ = np.zeros(fp.n)
    occ[idx] = lu.solve(p[idx])
    return p, occ


def closed_network(net: CompartmentNetwork) -> CompartmentNetwork:
    """The periodic section as a closed vessel (no feed/discharge; wrap flows kept)."""
    return CompartmentNetwork(
        holdup=net.holdup,
        src=net.src,
        dst=net.dst,
        rate=net.rate,
        wrap=net.wrap,
        slice_index=net.slice_index,
        centroid=net.centroid,
    )


# ----------------------------------------------------------------------------- RTD tools


def fftconvolve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Full linear convolution of two real 1-D arrays by real FFTs (scipy.fft, zero-padded to a
    fast length); the same as ``scipy.signal.fftconvolve`` without importing scipy.signal."""
    from scipy import fft as sfft

    n = a.size + b.size - 1
    m = sfft.next_fast_len(n, real=True)
    return sfft.irfft(sfft.rfft(a, m) * sfft.rfft(b, m), m)[:n]


def trapezoid_convolve(e1: np.ndarray, e2: np.ndarray, dt: float) -> np.ndarray:
    """(E1 * E2)(t_k) = int_0^t E1(t - s) E2(s) ds by the trapezoid rule (Eq. 9), via FFT."""
    n = min(e1.size, e2.size)
    full = fftconvolve(e1[:n], e2[:n])[:n]
    full = full - 0.5 * (e1[0] * e2[:n] + e2[0] * e1[:n])
    return np.maximum(full, 0.0) * dt


def convolve_power(e: np.ndarray, n: int, dt: float) -> np.ndarray:
    """n-fold self-convolution of E on a uniform grid (binary powering, trapezoid rule)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    result = None
    base = e
    k = n
    while k:
        if k & 1:
            result = base if result is None else trapezoid_convolve(result, base, dt)
        k >>= 1
        if k:
            base = trapezoid_convolve(base, base, dt)
    return result


def rtd_moments(t: np.ndarray, e: np.ndarray) -> tuple[float, float, float]:
    """Area, mean and variance of E(t) on a grid (trapezoid rule)."""
    area = float(np.trapezoid(e, t))
    mean = float(np.trapezoid(t * e, t) / area)
    var = float(np.trapezoid((t - mean) ** 2 * e, t) / area)
    return area, mean, var


def rsd(c: np.ndarray, weights: np.ndarray | None = None, axis: int = -1) -> np.ndarray:
    """Relative standard deviation across compartments, chapter 5 Eq. (2):

    RSD = sqrt(sum (C_i - C_av)^2 / (N - 1)) / C_av.  With ``weights`` (e.g. holdups) the
    holdup-weighted mean and variance are used instead (unbiased for frequency weights scaled
    to N).  Works along ``axis`` (one RSD per time point of a (nt, n) array).
    """
    c = np.asarray(c, dtype=float)
    n = c.shape[axis]
    if n < 2:
        raise ValueError(f"rsd needs >= 2 compartments, got {n}")
    if weights is None:
        mean = c.mean(axis=axis, keepdims=True)
        var = ((c - mean) ** 2).sum(axis=axis) / (n - 1)
    else:
        w = np.asarray(weights, dtype=float)
        w = w / w.sum() * n
        shape = [1] * c.ndim
        shape[axis] = n
        w = w.reshape(shape)
        mean = (w * c).sum(axis=axis, keepdims=True) / n
        var = (w * (c - mean) ** 2).sum(axis=axis) / (n - 1)
    return np.sqrt(var) / np.squeeze(mean, axis=axis)
