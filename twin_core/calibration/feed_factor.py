"""Response surfaces of the feed-factor parameters over the DEM material design.

The seed fitted Eq. (2) to the feed factor vs hopper mass curve of each of the 21 DEM feeder
runs of the Table 3.2 design (Table 8.1), then regressed FF_max, FF_min and beta on the
material parameters by the same stepwise procedure as the bulk responses (Eqs. 14-16,
section 3.3.2.4). :func:`fit_feed_factor_surfaces` repeats that;
:func:`feed_factor_parameters` evaluates the surfaces at a material parameter set and
:func:`config_from_material` turns them into a loss-in-weight feeder configuration.

Notes on the seed's equations: Eq. (14) (FF_max) is centred on the 21-run means (0.35,
0.05287); Eqs. (15)-(16) are centred on 0.3456 / 0.0526 / 0.3978, the means over 23 runs, so
they were refitted after adding the two verification runs of Table 3.5, whose feed-factor
values the seed does not list. They cannot be reproduced from the published tables.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from schemas.feeder import FeederConfig
from twin_core.feeder.material import config_with_feed_factor

from .rsm import Criterion, ResponseSurface, TwoStepRSM
from .tables import SEED_FACTORS, SEED_FF_RESPONSES

__all__ = [
    "config_from_material",
    "fit_feed_factor_surfaces",
    "feed_factor_parameters",
    "parity_table",
    "SEED_EQ14_TERMS",
]

#: terms of the seed's Eq. (14) for FF_max
SEED_EQ14_TERMS = ["PP_SF", "PP_RF", "PW_SF", "PP_SF*PP_SF", "PP_SF*PP_RF", "PW_SF*PW_SF"]


def fit_feed_factor_surfaces(
    table: pd.DataFrame,
    factors: Sequence[str] = SEED_FACTORS,
    responses: Sequence[str] = SEED_FF_RESPONSES,
    criterion: Criterion = "p",
) -> dict[str, TwoStepRSM]:
    """Two-step stepwise surfaces for each feed-factor parameter column of ``table``.

    Default criterion: p values (enter/leave at 0.1), which selects exactly the terms of the
    seed's Eq. (14) for FF_max.
    """
    return {r: TwoStepRSM(factors, criterion=criterion).fit(table, r) for r in responses}


def feed_factor_parameters(
    surfaces: Mapping[str, TwoStepRSM | ResponseSurface],
    material: Mapping[str, float],
) -> dict[str, float]:
    """(FF_max, FF_min, beta) predicted at one material parameter set, in the units of the
    fitted table. FF_min and beta are clipped at 0 (a response surface can extrapolate below
    the physical limit; seed Eq. 15 has a negative intercept)."""
    out = {}
    for name, s in surfaces.items():
        model = s.model_ if isinstance(s, TwoStepRSM) else s
        missing = [f for f in model.factors_ if f not in material]
        if missing:
            raise ValueError(f"material lacks parameter(s) {missing} needed by the {name} surface")
        val = float(model.predict({k: [float(material[k])] for k in model.factors_})[0])
        if name in ("FF_min", "beta"):
            val = max(val, 0.0)
        out[name] = val
    if "FF_max" in out and "FF_min" in out and out["FF_min"] > out["FF_max"]:
        raise ValueError(
            f"predicted FF_min {out['FF_min']:.4g} exceeds FF_max {out['FF_max']:.4g} at "
            f"{dict(material)}: outside the region the surfaces describe"
        )
    return out


def parity_table(model: TwoStepRSM | ResponseSurface) -> pd.DataFrame:
    """Actual vs predicted values of the fitted runs (for a parity plot)."""
    m = model.model_ if isinstance(model, TwoStepRSM) else model
    return pd.DataFrame(
        {"actual": m.actual_, "predicted": m.fitted_, "residual": m.actual_ - m.fitted_}
    ).assign(within_2rmse=lambda d: np.abs(d.residual) <= 2 * m.rmse_)


def config_from_material(
    material: Mapping[str, float],
    surfaces: Mapping[str, TwoStepRSM | ResponseSurface],
    base: FeederConfig | None = None,
    ff_to_g_rev: float = 1000.0,
    mass_scale: float = 1.0,
    **overrides: Any,
) -> FeederConfig:
    """Feeder config whose FF(W) comes from feed-factor response surfaces (seed Eqs. 14-16,
    see :func:`fit_feed_factor_surfaces`) evaluated at DEM
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
    p = feed_factor_parameters(surfaces, material)
    return config_with_feed_factor(
        base,
        p["FF_max"] * ff_to_g_rev,
        p["FF_min"] * ff_to_g_rev,
        p["beta"] / mass_scale,
        **overrides,
    )
