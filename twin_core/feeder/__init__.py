"""Feed-factor model (seed Eq. 2) and a loss-in-weight feeder simulator.

The simulator is configured by ``schemas.feeder.FeederConfig`` (hopper, refill, PID, noise); a
feeder's place in a line (id, component, set point, its ``FeederConfig`` overrides) is
``schemas.line.FeederLine`` -- the one feeder configuration model, with no second copy here.
"""

from .feed_factor import FeedFactorFit, feed_factor, fit_feed_factor
from .liw import FeederTrace, LossInWeightFeeder

__all__ = [
    "FeedFactorFit",
    "FeederTrace",
    "LossInWeightFeeder",
    "feed_factor",
    "fit_feed_factor",
]
