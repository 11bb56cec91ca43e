"""Material tracking: raw-material lots from the feeders' hoppers to the blender outlet
(ICH Q13 section 3.3), recall intervals and batches.

- :mod:`~twin_core.tracking.hopper`: the loss-in-weight hopper's law (fifo, mixed, mixture);
- :mod:`~twin_core.tracking.tracker`: lot mass flows at the outlet, streaming
  (:class:`MaterialTracker`) and over arrays (:func:`track_lots`);
- :mod:`~twin_core.tracking.recall`: product intervals holding a lot, composition at a time;
- :mod:`~twin_core.tracking.batches`: batch boundaries and the batch record's numbers.
"""

from twin_core.tracking.hopper import HOPPER_MODELS, Hopper, mixed_fraction
from twin_core.tracking.tracker import (
    LotTrace,
    MaterialTracker,
    Refill,
    initial_lot_id,
    normalised_kernel,
    refill_lot_id,
    track_lots,
)

__all__ = [
    "HOPPER_MODELS",
    "Hopper",
    "LotTrace",
    "MaterialTracker",
    "Refill",
    "initial_lot_id",
    "mixed_fraction",
    "normalised_kernel",
    "refill_lot_id",
    "track_lots",
]
