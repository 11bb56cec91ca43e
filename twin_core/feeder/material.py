"""Feeder configurations with a given feed-factor curve (seed Eq. 2), e.g. a fitted one.

The feed factor predicted from DEM material parameters is
``twin_core.calibration.feed_factor.config_from_material``."""

from __future__ import annotations

from typing import Any

from schemas.feeder import FeederConfig

__all__ = ["config_with_feed_factor"]


def config_with_feed_factor(
    base: FeederConfig | None,
    ff_max_g_rev: float,
    ff_min_g_rev: float,
    beta_per_kg: float,
    **overrides: Any,
) -> FeederConfig:
    """A copy of ``base`` (default config) with the feed factor of seed Eq. (2) replaced,
    validated again (so an unreachable set point is reported)."""
    data = (base or FeederConfig()).model_dump()
    data.update(
        ff_max_g_rev=float(ff_max_g_rev),
        ff_min_g_rev=float(ff_min_g_rev),
        beta_per_kg=float(beta_per_kg),
        **overrides,
    )
    return FeederConfig(**data)
