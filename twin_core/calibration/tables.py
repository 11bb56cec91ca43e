"""The seed's calibration tables, shipped as small CSV files in ``data/``.

* ``seed_table_3_2_dsd.csv``: Table 3.2, the 21-run definitive screening design of the DEM
  material parameters (physical units);
* ``seed_table_3_3_bulk.csv``: Table 3.3, the drawdown-test bulk responses of those runs;
* ``seed_table_8_1_feed_factor.csv``: Table 8.1, the feed-factor parameters (Eq. 2) fitted
  to the 21 feeder runs of the same design, with the R^2 of each fit;
* ``seed_table_3_5_verification.csv``: Table 3.5, the two verification runs, with the rows
  the seed labels "PR (Pa)" and "SM" swapped back (PR 0.3 / 0.4, SM 3e6 / 8e6 Pa).

Table 3.4 (the inverse-calibration example) is :data:`SEED_TABLE_3_4`.
"""

from __future__ import annotations

from importlib import resources

import pandas as pd

__all__ = [
    "SEED_FACTORS",
    "SEED_BULK_RESPONSES",
    "SEED_FF_RESPONSES",
    "SEED_TABLE_3_4",
    "load_seed_table",
]

SEED_FACTORS = ["PP_SF", "PP_RF", "PP_COR", "PW_SF", "PW_RF", "PW_COR", "SM", "PR"]
SEED_BULK_RESPONSES = ["AOR_deg", "shear_angle_deg", "mass_lower_kg", "max_flowrate_kg_s"]
SEED_FF_RESPONSES = ["FF_max", "FF_min", "beta"]

#: Table 3.4: measured bulk responses and the seed's GAMS/BARON answer for the four unknowns.
SEED_TABLE_3_4 = {
    "targets": {
        "AOR_deg": 30.0,
        "mass_lower_kg": 0.22,
        "shear_angle_deg": 25.0,
        "max_flowrate_kg_s": 0.17,
    },
    "solution": {"PP_SF": 0.4931, "PP_RF": 0.0383, "PP_COR": 0.1851, "PW_SF": 0.195},
}

_FILES = {
    "dsd": "seed_table_3_2_dsd.csv",
    "bulk": "seed_table_3_3_bulk.csv",
    "feed_factor": "seed_table_8_1_feed_factor.csv",
    "verification": "seed_table_3_5_verification.csv",
}


def _read(name: str) -> pd.DataFrame:
    with resources.files(__package__).joinpath("data", _FILES[name]).open("r") as fh:
        return pd.read_csv(fh)


def load_seed_table(which: str = "bulk") -> pd.DataFrame:
    """A seed table by name: 'dsd' (Table 3.2), 'bulk' (3.2 joined with 3.3),
    'feed_factor' (3.2 joined with 8.1), 'verification' (3.5, corrected)."""
    if which not in ("dsd", "bulk", "feed_factor", "verification"):
        raise ValueError(
            f"which must be 'dsd', 'bulk', 'feed_factor' or 'verification', got {which!r}"
        )
    if which in ("dsd", "verification"):
        return _read(which)
    return _read("dsd").merge(_read(which), on="run", validate="one_to_one")
