"""Multi-zonal compartment model of the blender built from DEM grid fields (chapter 5).

Fields (npz) -> zones -> compartments -> conserving flows -> linear network -> RTD / RSD ->
whole blender (n sections) -> serializable :class:`schemas.blender_model.BlenderModel`, whose
numerics (E(t), outlet prediction, RSD profile) are the ``blender_model_*`` functions.

The names below are imported from their submodules on first use (PEP 562), so that loading a
blender model for prediction does not import the zoning and fitting machinery.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS: dict[str, str] = {
    "blender_rsd_profile": "blender",
    "blender_rtd": "blender",
    "fit_rsd_decay": "blender",
    "predict_outlet": "blender",
    "rsd_decay": "blender",
    "blender_model_flow_scale": "blender_model",
    "blender_model_network": "blender_model",
    "blender_model_predict": "blender_model",
    "blender_model_rsd_profile": "blender_model",
    "blender_model_rtd": "blender_model",
    "blender_model_section": "blender_model",
    "blender_model_fields": "export",
    "to_blender_model": "export",
    "GridFields": "fields",
    "load_fields": "fields",
    "save_fields": "fields",
    "validate_fields": "fields",
    "aggregate_flows": "flows",
    "cell_flows_from_crossings": "flows",
    "cell_flows_from_velocity": "flows",
    "imbalance_report": "flows",
    "project_flows": "flows",
    "seed_flows": "flows",
    "CompartmentModel": "model",
    "CompartmentNetwork": "network",
    "chain_sections": "network",
    "convolve_power": "network",
    "first_passage_network": "network",
    "open_section": "network",
    "rsd": "network",
    "rtd_moments": "network",
    "section_rsd": "radial",
    "split_initial": "radial",
    "SyntheticCase": "synthetic",
    "synthetic_blender_fields": "synthetic",
    "compare_rtd": "validation",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'twin_core.compartment' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"twin_core.compartment.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
