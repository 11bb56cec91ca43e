"""Feed-factor model (seed Eq. 2) and a loss-in-weight feeder simulator."""

from .feed_factor import FeedFactorFit, feed_factor, fit_feed_factor
from .liw import FeederTrace, LossInWeightFeeder

__all__ = [
    "FeedFactorFit",
    "FeederTrace",
    "LossInWeightFeeder",
    "feed_factor",
    "fit_feed_factor",
]
