"""Numerics of the serialised blender model (:class:`schemas.blender_model.BlenderModel`).

The schema holds the data of one periodic section (compartments, holdups, flow triplets, the
periodic face) and how many sections are in series; these functions turn it back into
networks and answer with them, like an RTD model:

* :func:`blender_model_rtd` - E(t) of the whole blender, E_section^{*n} (seed Eq. 8-9);
* :func:`blender_model_predict` - outlet concentration for a piecewise-constant inlet
  (zero-order hold through the cumulative RTD, Levenspiel ch. 11), flows optionally scaled in
  time (warped time, Nauman 2008 ch. 15);
* :func:`blender_model_rsd_profile` - RSD along the axis, seed Eq. (10) in time-of-flight form;
* :func:`blender_model_flow_scale` - flow scale s(rpm) from the stored DEM runs at other blade
  speeds.

The section network and the cumulative RTD on the last grid asked for are cached per model
object (a model is immutable), so repeated predictions skip the RTD computation.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from schemas.blender_model import BlenderModel
from twin_core.compartment.blender import (
    blender_cdf_increments,
    blender_rsd_profile,
    blender_rtd,
    predict_outlet,
)
from twin_core.compartment.network import (
    CompartmentNetwork,
    first_passage_network,
    open_section,
)

__all__ = [
    "blender_model_flow_scale",
    "blender_model_network",
    "blender_model_predict",
    "blender_model_rsd_profile",
    "blender_model_rtd",
    "blender_model_section",
]

#: models whose section network (and last cumulative RTD) is kept
_CACHE_SIZE = 4


@dataclass
class _Derived:
    """What is computed once per model: its section network and the last cumulative RTD."""

    section: CompartmentNetwork
    cdf_key: tuple[float, int] | None = None
    cdf: np.ndarray | None = field(default=None, repr=False)


_derived_cache: OrderedDict[int, tuple[BlenderModel, _Derived]] = OrderedDict()


def blender_model_network(model: BlenderModel) -> CompartmentNetwork:
    """The periodic section of ``model`` as a :class:`CompartmentNetwork` (flows through the
    periodic face flagged ``wrap``)."""
    return CompartmentNetwork(
        holdup=np.asarray(model.holdup_kg),
        src=np.asarray(model.flow_src, dtype=np.int64),
        dst=np.asarray(model.flow_dst, dtype=np.int64),
        rate=np.asarray(model.flow_kg_s),
        wrap=np.asarray(model.flow_wrap, dtype=bool),
        slice_index=np.asarray(model.compartment_slice, dtype=np.int64),
    )


def _derived(model: BlenderModel) -> _Derived:
    hit = _derived_cache.get(id(model))
    if hit is not None and hit[0] is model:
        _derived_cache.move_to_end(id(model))
        return hit[1]
    per = blender_model_network(model)
    if model.section_form == "transit":
        section = first_passage_network(per, model.n_upstream)
    else:
        section = open_section(per)
    derived = _Derived(section)
    _derived_cache[id(model)] = (model, derived)
    while len(_derived_cache) > _CACHE_SIZE:
        _derived_cache.popitem(last=False)
    return derived


def blender_model_section(model: BlenderModel) -> CompartmentNetwork:
    """The section whose impulse response is the section RTD (``model.section_form``: the
    record-passage transit form with ``n_upstream`` upstream copies, or the closed-closed cut
    of the periodic face)."""
    return _derived(model).section


def blender_model_rtd(
    model: BlenderModel, t: np.ndarray, n_sections: int | None = None
) -> np.ndarray:
    """E(t) (1/s) of the whole blender (or of ``n_sections`` sections) on a uniform grid t from
    0: the n-fold convolution of the section RTD (seed Eq. 8-9)."""
    n = model.n_sections if n_sections is None else n_sections
    return blender_rtd(blender_model_section(model), n, np.asarray(t, dtype=float))


def blender_model_predict(
    model: BlenderModel,
    t: np.ndarray,
    inlet_concentration: np.ndarray,
    flow_scale: np.ndarray | None = None,
    initial_concentration: float | None = None,
) -> np.ndarray:
    """Outlet concentration on the uniform grid t for a piecewise-constant inlet concentration
    (same units out as in): y(t_k) = c0 (1 - F(t_k)) + sum_j u_j [F(t_k - t_j) - F(t_k - t_j+1)]
    with F the blender's cumulative RTD (Levenspiel ch. 11).

    ``flow_scale`` (len(t)) scales every flow relative to the basis (rpm / rpm_basis or
    throughput / throughput_kg_h with the holdup fixed); ``initial_concentration`` is the
    blender content at t[0] (default: steady state at inlet_concentration[0]).
    """
    t = np.asarray(t, dtype=float)
    derived = _derived(model)
    cdf = None
    if flow_scale is None and t.size >= 2:
        key = (round(float(t[1] - t[0]), 12), t.size)
        if derived.cdf_key != key:
            derived.cdf = blender_cdf_increments(
                derived.section, model.n_sections, float(t[1] - t[0]), t.size
            )
            derived.cdf_key = key
        cdf = derived.cdf
    return predict_outlet(
        derived.section,
        model.n_sections,
        t,
        np.asarray(inlet_concentration, dtype=float),
        flow_scale=flow_scale,
        initial=initial_concentration,
        cdf=cdf,
    )


def blender_model_rsd_profile(model: BlenderModel, x_m: np.ndarray) -> np.ndarray:
    """RSD along the blender axis by seed Eq. (10) with t = x / v_x, v_x = section length x
    throughput / flowing holdup (needs ``rsd_ss``, ``rsd_0`` and ``k_b_per_s`` in the model)."""
    if model.rsd_ss is None or model.rsd_0 is None or model.k_b_per_s is None:
        raise ValueError("rsd_profile needs rsd_ss, rsd_0 and k_b_per_s in the model")
    v_x = model.section_length_m * (model.throughput_kg_h / 3600.0) / model.flowing_holdup_kg
    return blender_rsd_profile(x_m, model.rsd_ss, model.rsd_0, model.k_b_per_s, v_x)


def blender_model_flow_scale(model: BlenderModel, rpm: np.ndarray) -> np.ndarray:
    """Flow scale s(rpm) for :func:`blender_model_predict`: linear interpolation of the model's
    ``rpm_flow_scale`` points with (rpm_basis, 1) and (0, 0); proportional to rpm / rpm_basis
    beyond the last point (and everywhere when no points are stored)."""
    if model.rpm_basis is None:
        raise ValueError("flow_scale_for_rpm needs rpm_basis in the model")
    rpm = np.asarray(rpm, dtype=float)
    if np.any(rpm < 0) or not np.all(np.isfinite(rpm)):
        raise ValueError("rpm must be finite and >= 0")
    pts = {0.0: 0.0, float(model.rpm_basis): 1.0}
    for r, sc in model.rpm_flow_scale or []:
        pts[float(r)] = float(sc)
    x = np.array(sorted(pts))
    y = np.array([pts[v] for v in x])
    out = np.interp(rpm, x, y)
    beyond = rpm > x[-1]
    out[beyond] = y[-1] * rpm[beyond] / x[-1]
    return out
