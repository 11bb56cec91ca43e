"""The loss-in-weight feeder's hopper as a material-tracking model: which raw-material lot
leaves the feeder at each tick.

The hopper holds a stack of layers (lot, mass), the oldest at the bottom. A refill puts its
lot on top. Each tick the feeder discharges m = q dt (q the measured mass flow, kg/s):

    a fraction alpha of m from the whole hopper, each layer in proportion to its mass
        (stirred heel, "mixed": the refill mixes at once with the heel, a CSTR of varying
        holdup, Levenspiel 1999 ch. 11);
    the rest, (1 - alpha) m, from the bottom layers, oldest first
        (plug flow, "fifo": mass flow in Jenike's sense, first in, first out).

With M the hopper mass and x_j the layers, the discharge of lot j in a tick is

    d_j = alpha m x_j / M + (1 - alpha) (the part of the bottom layers taken, oldest first)

and sum_j d_j = m exactly: mass is conserved lot by lot by construction. ``alpha = 0`` is
``fifo``, ``alpha = 1`` ``mixed``; between them, a calibrated mixture (``mixture``): the share
of the discharge that funnel flow draws from the whole bed (Jenike, A.W. (1964) Storage and
flow of solids, Univ. of Utah Eng. Exp. Station Bull. 123: mass flow vs funnel flow hoppers).
alpha is calibrated on a refill with a tagged lot (an NIR or a sampled assay at the feeder
outlet): alpha is the slope of -ln(share of the old lot) against the mass discharged over the
hopper mass, since the old lot's share decays as exp(-alpha * discharged / M) once the new lot
is mixed in, 0 for pure plug flow until the heel is gone. Its effect on a recall is measured in
``docs/traceability.md``: the lot's tail in the product is longest with ``mixed``.

Refill mass: ``mass_kg`` of the refill event when the plant gives it, else the mass that makes
the model's hopper equal the measured hopper mass once the refill has stopped (the model
re-synchronises to the load cell at each refill). A discharge larger than the model's hopper
(measurements out of balance) is taken from the newest lot and counted in ``overdraw_kg``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["HOPPER_MODELS", "Hopper", "mixed_fraction"]

#: hopper models and their alpha (``mixture``: the configured one)
HOPPER_MODELS = ("fifo", "mixed", "mixture")


def mixed_fraction(model: str, alpha: float) -> float:
    """alpha of a hopper model: 0 for ``fifo``, 1 for ``mixed``, ``alpha`` for ``mixture``."""
    if model not in HOPPER_MODELS:
        raise ValueError(f"hopper model must be one of {list(HOPPER_MODELS)}, got {model!r}")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"mixed_fraction must be in [0, 1], got {alpha!r}")
    return {"fifo": 0.0, "mixed": 1.0}.get(model, float(alpha))


class Hopper:
    """One feeder's hopper: layers of lots (bottom first) and the discharge law of the module
    docstring.

    Args:
        lot: index of the lot in the hopper at the start.
        mass_kg: its mass (0 or NaN: unknown; the discharge then overdraws that lot until the
            first refill re-synchronises the model).
        alpha: the stirred share of the discharge (0 fifo .. 1 mixed).
    """

    def __init__(self, lot: int, mass_kg: float, alpha: float) -> None:
        self.alpha = float(alpha)
        m = float(mass_kg) if np.isfinite(mass_kg) and mass_kg > 0 else 0.0
        #: [lot index, mass kg], bottom (oldest) first
        self.layers: list[list[float]] = [[lot, m]]
        #: the lot currently fed on top (a discharge beyond the hopper's content is taken from it)
        self.newest = lot
        self.overdraw_kg = 0.0

    @property
    def mass_kg(self) -> float:
        layers = self.layers
        return layers[0][1] if len(layers) == 1 else float(sum(x[1] for x in layers))

    def refill(self, lot: int, mass_kg: float) -> None:
        """Put ``mass_kg`` of ``lot`` on top (a refill)."""
        if mass_kg > 0:
            if self.layers and self.layers[-1][0] == lot:
                self.layers[-1][1] += mass_kg
            else:
                self.layers.append([lot, float(mass_kg)])
        self.newest = lot

    def discharge(self, m: float) -> list[tuple[int, float]]:
        """Take ``m`` kg out (one tick); returns (lot index, kg) of what left, lots in layer
        order (equation of the module docstring)."""
        out: dict[int, float] = {}
        if m <= 0:
            return []
        total = self.mass_kg
        avail = min(m, total)
        mm = self.alpha * avail
        if mm > 0 and total > 0:
            keep = 1.0 - mm / total
            for layer in self.layers:
                take = layer[1] * (mm / total)
                out[int(layer[0])] = out.get(int(layer[0]), 0.0) + take
                layer[1] *= keep
        rest = avail - mm
        last = None
        while rest > 0 and self.layers:
            layer = self.layers[0]
            last = int(layer[0])
            take = min(rest, layer[1])
            out[last] = out.get(last, 0.0) + take
            layer[1] -= take
            rest -= take
            if layer[1] <= 0:
                self.layers.pop(0)
        deficit = m - avail + max(rest, 0.0)
        if 0 < deficit <= 1e-9 * m and last is not None:
            out[last] += deficit  # rounding of the layers' sum, not an overdraw
        elif deficit > 0:
            out[self.newest] = out.get(self.newest, 0.0) + deficit
            self.overdraw_kg += deficit
        return list(out.items())

    def to_state(self) -> dict[str, Any]:
        return {
            "alpha": self.alpha,
            "layers": [[int(a), float(b)] for a, b in self.layers],
            "newest": int(self.newest),
            "overdraw_kg": self.overdraw_kg,
        }

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> Hopper:
        obj = cls(0, 0.0, float(state["alpha"]))
        obj.layers = [[int(a), float(b)] for a, b in state["layers"]]
        obj.newest = int(state["newest"])
        obj.overdraw_kg = float(state["overdraw_kg"])
        return obj
