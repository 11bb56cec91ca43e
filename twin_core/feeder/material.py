"""Feeder configurations from fitted or DEM-derived feed-factor parameters."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from schemas.feeder import FeederConfig

__all__ = ["config_with_feed_factor", "config_from_material"]


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


def config_from_material(
    material: Mapping[str, float],
    surfaces: Mapping[str, Any],
    base: FeederConfig | None = None,
    ff_to_g_rev: float = 1000.0,
    mass_scale: float = 1.0,
    **overrides: Any,
) -> FeederConfig:
    """Feeder config whose FF(W) comes from feed-factor response surfaces (seed Eqs. 14-16,
    see :func:`twin_core.calibration.feed_factor.fit_feed_factor_surfaces`) evaluated at DEM
    material parameters.

    ``ff_to_g_rev`` converts the surfaces' feed-factor unit to g/rev (default 1000: the seed's
    DEM feed factors, 0.02-0.07, read as kg per screw revolution for a hopper of ~1 kg,
    which matches its 150,000 1-mm particles emptying in ~20 s at 100 rpm). ``mass_scale``
    stretches the hopper-mass axis from the DEM hopper to the real one (beta / mass_scale).
    """
    if ff_to_g_rev <= 0:
        raise ValueError(f"ff_to_g_rev must be > 0, got {ff_to_g_rev}")
    if mass_scale <= 0:
        raise ValueError(f"mass_scale must be > 0, got {mass_scale}")
    from twin_core.calibration.feed_factor import feed_factor_parameters

    p = feed_factor_parameters(surfaces, material)
    return config_with_feed_factor(
        base,
        p["FF_max"] * ff_to_g_rev,
        p["FF_min"] * ff_to_g_rev,
        p["beta"] / mass_scale,
        **overrides,
    )
