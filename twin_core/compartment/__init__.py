"""Multi-zonal compartment model of the blender built from DEM grid fields (chapter 5).

Fields (npz) -> zones -> compartments -> conserving flows -> linear network -> RTD / RSD ->
whole blender (n sections) -> serializable :class:`schemas.blender_model.BlenderModel`.
"""

from twin_core.compartment.blender import (
    blender_rsd_profile,
    blender_rtd,
    fit_rsd_decay,
    predict_outlet,
    rsd_decay,
)
from twin_core.compartment.export import blender_model_fields, to_blender_model
from twin_core.compartment.fields import GridFields, load_fields, save_fields, validate_fields
from twin_core.compartment.flows import (
    aggregate_flows,
    cell_flows_from_crossings,
    cell_flows_from_velocity,
    imbalance_report,
    project_flows,
    seed_flows,
)
from twin_core.compartment.model import CompartmentModel
from twin_core.compartment.network import (
    CompartmentNetwork,
    chain_sections,
    convolve_power,
    first_passage_network,
    open_section,
    rsd,
    rtd_moments,
)
from twin_core.compartment.radial import section_rsd, split_initial
from twin_core.compartment.synthetic import SyntheticCase, synthetic_blender_fields
from twin_core.compartment.validation import compare_rtd

__all__ = [
    "CompartmentModel",
    "CompartmentNetwork",
    "GridFields",
    "SyntheticCase",
    "aggregate_flows",
    "blender_model_fields",
    "blender_rsd_profile",
    "blender_rtd",
    "cell_flows_from_crossings",
    "cell_flows_from_velocity",
    "chain_sections",
    "compare_rtd",
    "convolve_power",
    "first_passage_network",
    "fit_rsd_decay",
    "imbalance_report",
    "load_fields",
    "open_section",
    "predict_outlet",
    "project_flows",
    "rsd",
    "rsd_decay",
    "rtd_moments",
    "save_fields",
    "section_rsd",
    "seed_flows",
    "split_initial",
    "synthetic_blender_fields",
    "to_blender_model",
    "validate_fields",
]
