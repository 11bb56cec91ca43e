"""Export a fitted compartment model as the serializable :class:`schemas.blender_model.BlenderModel`."""

from __future__ import annotations

from typing import Any

import numpy as np

from twin_core.compartment.flows import wrap_directions
from twin_core.compartment.model import CompartmentModel


def blender_model_fields(
    model: CompartmentModel,
    n_sections: int = 8,
    rpm_basis: float | None = None,
    rsd_fit: dict[str, float] | None = None,
    source: str = "",
    rpm_runs: dict[float, CompartmentModel] | None = None,
) -> dict[str, Any]:
    """Plain-data fields of a BlenderModel for the periodic section of ``model``.

    ``rpm_runs`` maps other blade speeds to models fitted on DEM runs there; the ratios of their
    net axial flows to this one become ``rpm_flow_scale`` (the rpm law of dynamic runs).
    """
    if n_sections < 1:
        raise ValueError(f"n_sections must be >= 1, got {n_sections}")
    if model.section_ is None:
        raise ValueError(
            f"no net axial flow through the periodic face (throughput "
            f"{model.throughput_kg_s_} kg/s): no RTD, no blender model"
        )
    per = model.periodic_
    fwd, _ = wrap_directions(per.slice_index, per.src, per.dst, per.wrap)
    feed = np.bincount(per.dst[fwd], weights=per.rate[fwd], minlength=per.n)
    dis = np.bincount(per.src[fwd], weights=per.rate[fwd], minlength=per.n)
    inlet = np.flatnonzero(feed > 0)
    outlet = np.flatnonzero(dis > 0)
    d: dict[str, Any] = {
        "n_compartments": per.n,
        "holdup_kg": per.holdup.tolist(),
        "flow_src": per.src.tolist(),
        "flow_dst": per.dst.tolist(),
        "flow_kg_s": per.rate.tolist(),
        "flow_wrap": per.wrap.astype(bool).tolist(),
        "compartment_slice": per.slice_index.tolist(),
        "inlet_compartments": inlet.tolist(),
        "inlet_kg_s": feed[inlet].tolist(),
        "outlet_compartments": outlet.tolist(),
        "outlet_kg_s": dis[outlet].tolist(),
        "n_sections": n_sections,
        "section_form": model.section_form,
        "n_upstream": model.n_upstream_,
        "throughput_kg_h": float(model.throughput_kg_s_ * 3600.0),
        "rpm_basis": rpm_basis,
        "section_length_m": model.section_length_m_,
        "compartment_centroid_m": model.centroid_.tolist(),
        "source": source,
        "notes": {k: v for k, v in model.summary().items() if isinstance(v, (int, float, str))},
    }
    if rpm_runs:
        if rpm_basis is None:
            raise ValueError("rpm_runs needs rpm_basis")
        d["rpm_flow_scale"] = [
            (float(r), float(m.throughput_kg_s_ / model.throughput_kg_s_))
            for r, m in sorted(rpm_runs.items())
        ]
    if rsd_fit is not None:
        d["rsd_ss"] = rsd_fit["rsd_ss"]
        d["rsd_0"] = rsd_fit["rsd_0"]
        d["k_b_per_s"] = rsd_fit["k_b"]
    return d


def to_blender_model(model: CompartmentModel, **kwargs: Any) -> Any:
    """The fitted model as a validated ``schemas.blender_model.BlenderModel``
    (keyword arguments as in :func:`blender_model_fields`)."""
    from schemas.blender_model import BlenderModel

    return BlenderModel.model_validate(blender_model_fields(model, **kwargs))
