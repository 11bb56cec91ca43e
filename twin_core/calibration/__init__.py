"""Bulk calibration of DEM material parameters: definitive screening designs, stepwise
response surfaces, inverse calibration, design campaigns."""

from .design import (
    SEED_LEVELS,
    DefinitiveScreeningDesign,
    coded_to_physical,
    conference_matrix,
    correlation_map,
    definitive_screening_design,
    dsd_properties,
    physical_to_coded,
)
from .inverse import CalibrationResult, InverseCalibration, Solution
from .rsm import ResponseSurface, StepwiseResult, TwoStepRSM, check_table, stepwise
from .tables import (
    SEED_BULK_RESPONSES,
    SEED_FACTORS,
    SEED_FF_RESPONSES,
    SEED_TABLE_3_4,
    load_seed_table,
)

__all__ = [
    "SEED_BULK_RESPONSES",
    "SEED_FACTORS",
    "SEED_FF_RESPONSES",
    "SEED_LEVELS",
    "SEED_TABLE_3_4",
    "CalibrationResult",
    "DefinitiveScreeningDesign",
    "InverseCalibration",
    "ResponseSurface",
    "Solution",
    "StepwiseResult",
    "TwoStepRSM",
    "check_table",
    "coded_to_physical",
    "conference_matrix",
    "correlation_map",
    "definitive_screening_design",
    "dsd_properties",
    "load_seed_table",
    "physical_to_coded",
    "stepwise",
]
