"""An independent particle-parcel simulation of lots through a feeder's hopper and the blender:
the reference the material-tracking model (``twin_core.tracking.tracker``) is checked against.

It shares no code with the tracking model: the material is a population of parcels of mass
``parcel_kg``, each with its lot; the hopper and the blender act on parcels by drawing from
their laws, not by convolution:

- hopper, each tick of dt with discharge m = q dt from a hopper of mass M: the stirred share
  alpha m takes from each lot's N_j parcels a random sample of c = alpha m N_j / M of them,
  whole parcels, the fraction owed carried to the next tick (error diffusion: the count never
  strays a parcel from its expectation, so that 0.1 g parcels do not add a random walk of the
  composition that real powder, 1e9 particles, does not have), then the oldest parcels leave
  until (1 - alpha) m more has gone (plug flow); a refill adds its parcels on top; a parcel
  leaving in tick i leaves at t_i + U dt, U ~ U(0, 1);
- blender: each parcel stays a residence time drawn from the RTD law, tanks in series with
  delay: r = tau_d + Gamma(n, tau / n) (Levenspiel 1999 Eq. 14.3: the gamma distribution is the
  exit-age distribution of n equal tanks), so it leaves at t_h + r.

The outlet times of a lot's parcels are then a sample of where its mass leaves: the share of
them inside a recall's intervals estimates the recall's coverage with binomial error
sqrt(p (1 - p) / N) for N parcels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["ParcelRun", "simulate_parcels"]


@dataclass
class ParcelRun:
    """The parcels of one feeder: lot (index into ``lots``), hopper exit and outlet times."""

    lots: list[str]
    lot: np.ndarray
    t_hopper_s: np.ndarray
    t_out_s: np.ndarray
    parcel_kg: float


def simulate_parcels(
    t_s: np.ndarray,
    q_kg_h: float,
    initial: tuple[str, float],
    refills: Sequence[tuple[float, str, float]],
    alpha: float,
    tis: tuple[float, float, float],
    parcel_kg: float,
    seed: int | np.random.Generator = 0,
) -> ParcelRun:
    """One feeder discharging ``q_kg_h`` (constant) on the tick grid ``t_s``.

    Args:
        initial: (lot, kg) in the hopper at the start.
        refills: (plant time, lot, kg), each added on top at the first tick >= its time.
        alpha: the hopper's stirred share (0 plug flow .. 1 stirred).
        tis: (tau_d, tau, n) of the blender's tanks-in-series RTD.
        parcel_kg: mass of a parcel.
    """
    rng = np.random.default_rng(seed)
    t = np.asarray(t_s, float)
    dt = float(t[1] - t[0])
    lots = [initial[0]] + [r[1] for r in refills]
    # the hopper: parcel lots, oldest first, as a growing array with a start pointer
    bed = [np.zeros(int(round(initial[1] / parcel_kg)), dtype=np.int64)]
    hop = np.concatenate(bed)
    out_lot: list[np.ndarray] = []
    out_t: list[np.ndarray] = []
    m = q_kg_h / 3600.0 * dt
    owed = 0.0  # plug-flow mass owed (parcels are discrete)
    carry: dict[int, float] = {}  # stirred-share parcels owed per lot (error diffusion)
    order = sorted(range(len(refills)), key=lambda k: refills[k][0])
    nxt = 0
    for i in range(t.size):
        while nxt < len(order) and refills[order[nxt]][0] <= t[i] + 1e-9:
            k = order[nxt]
            add = np.full(int(round(refills[k][2] / parcel_kg)), k + 1, dtype=np.int64)
            hop = np.concatenate([hop, add])
            nxt += 1
        if hop.size == 0:
            continue
        mass = hop.size * parcel_kg
        leave = np.zeros(hop.size, dtype=bool)
        if alpha > 0:
            p = min(1.0, alpha * m / mass)
            for k in np.unique(hop):
                members = np.nonzero(hop == k)[0]
                c = p * members.size + carry.get(int(k), 0.0)
                take = min(int(c), members.size)
                carry[int(k)] = c - take
                if take:
                    leave[rng.choice(members, size=take, replace=False)] = True
        owed += (1.0 - alpha) * m
        n_fifo = int(owed / parcel_kg)
        if n_fifo > 0:
            stay = np.nonzero(~leave)[0][:n_fifo]
            leave[stay] = True
            owed -= stay.size * parcel_kg
        if leave.any():
            out_lot.append(hop[leave])
            out_t.append(t[i] + rng.random(int(leave.sum())) * dt)
            hop = hop[~leave]
    lot = np.concatenate(out_lot) if out_lot else np.zeros(0, np.int64)
    th = np.concatenate(out_t) if out_t else np.zeros(0)
    tau_d, tau, n = tis
    r = tau_d + rng.gamma(n, tau / n, size=th.size)
    return ParcelRun(lots, lot, th, th + r, parcel_kg)
