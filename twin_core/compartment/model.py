"""Build a multi-zonal compartment model of a periodic blender section from grid fields.

Steps (dissertation chapter 5.2.3, with the seed's flows replaced by conserving ones):

1. occupied cells (occupancy above ``empty_fraction`` of the maximum; others zone -2);
2. zones per variable: sign zones with a tolerance band ``tol_fraction`` x max |v|, or
   user thresholds; compartment map per variable by slice-wise connected components;
3. overlay of the variable maps into the product compartments (per axial slice);
4. cell-face flows from crossing counts (preferred) or upwinded velocities, summed between
   compartments, projected onto exact conservation with non-negative flows
   (:func:`~twin_core.compartment.flows.project_flows`, throughput kept);
5. the seed's Eq. (1) flows on the same compartments with their imbalance, for comparison;
6. the section RTD model: by default the transit (record-passage) form -- the periodic
   network unwrapped with upstream copies, timed between successive first passages of new
   multiples of the section length, the DEM transit-time definition; whole blender = its
   n-fold convolution (seed Eq. 8-9).  The conserving closed-closed cut of the section
   (feed/discharge at the periodic face, re-projected) is kept as ``closed_section_``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import scipy.sparse as sp

from twin_core.compartment.fields import GridFields, mirror_axis
from twin_core.compartment.flows import (
    FlowGraph,
    aggregate_flows,
    aggregate_transitions,
    cell_flows_from_crossings,
    cell_flows_from_velocity,
    imbalance_report,
    incidence,
    project_flows,
    seed_flows,
    wrap_directions,
)
from twin_core.compartment.network import (
    CompartmentNetwork,
    _weights,
    open_section,
    periodic_throughput,
    transit_network,
)
from twin_core.compartment.zoning import (
    VARIABLES,
    combine_zones,
    compartment_slices,
    field_variable,
    merge_small,
    occupied_mask,
    overlay_maps,
    quantile_thresholds,
    sign_zones,
    slice_components,
    threshold_zones,
)


class CompartmentModel:
    """Estimator: grid fields -> conserving compartment network of a periodic section.

    Parameters
    ----------
    variables : zoning variables (``vx``, ``vy``, ``vz``, ``speed``, ``solid_fraction``,
        ``occupancy``); the seed's radial model is ("vy", "vz"), its axial one ("vx",).
    tol_fraction : tolerance band of the sign zones, as a fraction of max |v| over occupied
        cells (seed: "+1 / 0 / -1").
    thresholds : optional mapping variable -> increasing thresholds (overrides sign zones).
    quantile_classes : optional mapping variable -> number of classes of equal cell count
        (thresholds at the quantiles of the occupied cells; e.g. ``{"mobility": 5}``).
    connected : True (the seed): a compartment is a connected piece of one zone in a slice;
        False: all cells of one zone in a slice form one compartment (kinetic lumping).
    empty_fraction : cells with occupancy <= this fraction of the maximum are empty (-2).
    min_cells : compartments smaller than this many cells are merged into their neighbour
        of the same slice sharing most faces (1 = no merging, the seed's maps).
    flow_source : "transitions" (particle transitions at a lag, the Markov-state estimator of
        :mod:`~twin_core.compartment.transitions`), "crossings", "velocity" or "auto" (the
        first of these the fields hold).
    projection_weights : "uniform" (minimal Euclidean correction) or "relative".
    section_form : "transit" (record-passage first-passage network, default) or "closed"
        (closed-closed cut of the periodic face) for ``section_``.
    n_upstream : upstream copies of the transit form; None (default) picks the fewest whose
        dropped backward crossings per transit are < 1e-4 (``n_upstream_`` after fit).
    resolution : "zones" (compartments from the zone maps) or "cells" (every occupied cell
        its own compartment: the finest network, used for radial mixing, where lumping
        mixes too fast).
    axial_axis : index of the periodic axial axis (0 = x).
    axial_direction : "auto" (orient the axis along the net flow: fields whose net flow runs
        towards -x are mirrored, ``mirrored_`` is then True and all maps refer to the mirrored
        fields), "+" (keep) or "-" (always mirror).

    Attributes after :meth:`fit`: ``mask_``, ``zones_`` (variable -> zone map), ``maps_``
    (variable -> compartment map), ``labels_`` (product compartment map, -1 empty),
    ``n_compartments_``, ``holdup_kg_``, ``raw_flows_`` (FlowGraph before projection),
    ``raw_imbalance_``, ``correction_rel_`` (|f - f0| / |f0|), ``periodic_`` (conserving
    periodic network), ``closed_section_`` (conserving closed-closed section),
    ``transit_section_`` (record-passage network), ``section_`` (the one chosen by
    ``section_form``), ``seed_flows_``, ``seed_imbalance_``,
    ``throughput_kg_s_``, ``mean_residence_time_s_`` (V / Q of the flowing holdup),
    ``axial_velocity_m_s_`` (L Q / V),
    ``section_length_m_``, ``flow_source_``, ``isolated_`` (compartments without any flow
    after projection: stagnant holdup that no tracer reaches) and ``isolated_holdup_kg_``.
    """

    def __init__(
        self,
        variables: Sequence[str] = ("vx", "vy", "vz"),
        tol_fraction: float = 0.1,
        thresholds: Mapping[str, Sequence[float]] | None = None,
        quantile_classes: Mapping[str, int] | None = None,
        connected: bool = True,
        empty_fraction: float = 0.01,
        min_cells: int = 3,
        flow_source: str = "auto",
        projection_weights: str = "uniform",
        section_form: str = "transit",
        n_upstream: int | None = None,
        resolution: str = "zones",
        axial_axis: int = 0,
        axial_direction: str = "auto",
    ) -> None:
        self.variables = tuple(variables)
        self.tol_fraction = tol_fraction
        self.thresholds = thresholds
        self.quantile_classes = quantile_classes
        self.connected = connected
        self.empty_fraction = empty_fraction
        self.min_cells = min_cells
        self.flow_source = flow_source
        self.projection_weights = projection_weights
        self.section_form = section_form
        self.n_upstream = n_upstream
        self.resolution = resolution
        self.axial_direction = axial_direction
        self.axial_axis = axial_axis

    def _check(self, fields: GridFields) -> None:
        if not self.variables:
            raise ValueError("variables must name at least one zoning variable")
        for v in self.variables:
            if v not in VARIABLES:
                raise ValueError(f"variables must be among {VARIABLES}, got {v!r}")
        if not 0 <= self.tol_fraction < 1:
            raise ValueError(f"tol_fraction must be in [0, 1), got {self.tol_fraction}")
        if self.flow_source not in ("auto", "transitions", "crossings", "velocity"):
            raise ValueError(
                "flow_source must be 'auto', 'transitions', 'crossings' or 'velocity', got "
                f"{self.flow_source!r}"
            )
        if self.flow_source == "transitions" and fields.transitions is None:
            raise ValueError("fields: flow_source 'transitions' needs the transition_* keys")
        if self.section_form not in ("transit", "closed"):
            raise ValueError(
                f"section_form must be 'transit' or 'closed', got {self.section_form!r}"
            )
        if self.axial_direction not in ("auto", "+", "-"):
            raise ValueError(
                f"axial_direction must be 'auto', '+' or '-', got {self.axial_direction!r}"
            )
        if self.resolution not in ("zones", "cells"):
            raise ValueError(f"resolution must be 'zones' or 'cells', got {self.resolution!r}")
        if self.n_upstream is not None and self.n_upstream < 0:
            raise ValueError(f"n_upstream must be >= 0, got {self.n_upstream}")
        if self.min_cells < 1:
            raise ValueError(f"min_cells must be >= 1, got {self.min_cells}")
        if self.axial_axis not in (0, 1, 2):
            raise ValueError(f"axial_axis must be 0, 1 or 2, got {self.axial_axis}")
        if not fields.periodic[self.axial_axis]:
            raise ValueError(f"fields: axial axis {self.axial_axis} must be periodic")
        if fields.shape[self.axial_axis] < 3:
            raise ValueError(
                f"fields: need >= 3 slices along the axial axis, got "
                f"{fields.shape[self.axial_axis]}"
            )

    def zone(self, fields: GridFields) -> dict[str, np.ndarray]:
        """Zone map of each variable (+1/0/-1 sign zones or threshold zones, -2 empty)."""
        mask = occupied_mask(fields, self.empty_fraction)
        zones = {}
        for v in self.variables:
            values = field_variable(fields, v)
            if self.thresholds and v in self.thresholds:
                zones[v] = threshold_zones(values, self.thresholds[v], mask)
            elif self.quantile_classes and v in self.quantile_classes:
                th = quantile_thresholds(values, mask, int(self.quantile_classes[v]))
                zones[v] = threshold_zones(values, th, mask)
            else:
                vmax = float(np.abs(values[mask]).max(initial=0.0))
                zones[v] = sign_zones(values, self.tol_fraction * vmax, mask)
        return zones

    def fit(self, fields: GridFields) -> CompartmentModel:
        """Zone, compartmentalise, project the flows and build the sections; returns self."""
        self._check(fields)
        ax = self.axial_axis
        source = self.flow_source
        if source == "auto":
            source = available_flow_source(fields, "transitions")
        self.flow_source_ = source
        mirror = self.axial_direction == "-"
        if self.axial_direction == "auto":
            mask0 = occupied_mask(fields, self.empty_fraction)
            if source == "transitions":
                tr = fields.transitions
                net = float(np.sum(tr.count * tr.shift))  # type: ignore[union-attr]
                mirror = net < 0
            else:
                cell0 = (
                    cell_flows_from_crossings(fields)
                    if source == "crossings"
                    else cell_flows_from_velocity(fields, mask0)
                )
                last = np.take(cell0[ax], fields.shape[ax] - 1, axis=ax)
                mirror = float(last[..., 0].sum() - last[..., 1].sum()) < 0
        if mirror:
            fields = mirror_axis(fields, ax)
        self.mirrored_ = bool(mirror)
        self.mask_ = occupied_mask(fields, self.empty_fraction)
        if not self.mask_.any():
            raise ValueError("fields: no occupied cell (occupancy is zero everywhere)")
        self.zones_ = self.zone(fields)
        self.maps_ = {v: slice_components(z, axis=ax) for v, z in self.zones_.items()}
        if self.resolution == "cells":
            order = np.moveaxis(self.mask_, ax, 0)
            lab = np.full(order.shape, -1, dtype=np.int32)
            lab[order] = np.arange(int(order.sum()), dtype=np.int32)
            labels = np.moveaxis(lab, 0, ax)
        elif not self.connected:
            labels = slice_components(
                combine_zones(list(self.zones_.values())), axis=ax, connected=False
            )
        else:
            labels = overlay_maps(list(self.maps_.values()), axis=ax)
            if self.min_cells > 1:
                labels = merge_small(labels, self.min_cells, axis=ax)
        self.labels_ = labels
        n = int(labels.max()) + 1
        self.n_compartments_ = n
        hit = labels >= 0
        lab = labels[hit]
        self.holdup_kg_ = np.bincount(lab, weights=fields.holdup_kg[hit], minlength=n)
        grids = np.meshgrid(*fields.centers, indexing="ij")
        w = fields.holdup_kg[hit]
        wsum = np.maximum(self.holdup_kg_, 1e-300)
        self.centroid_ = np.stack(
            [np.bincount(lab, weights=g[hit] * w, minlength=n) / wsum for g in grids], axis=1
        )
        self.slice_index_ = compartment_slices(labels, axis=ax)
        if np.any(self.holdup_kg_ <= 0):
            raise ValueError(
                f"fields: {int(np.sum(self.holdup_kg_ <= 0))} compartments have no holdup "
                "(occupancy zero in occupied cells?)"
            )

        if source == "transitions":
            raw = aggregate_transitions(fields, labels)
        else:
            cell = (
                cell_flows_from_crossings(fields)
                if source == "crossings"
                else cell_flows_from_velocity(fields, self.mask_)
            )
            raw = aggregate_flows(cell, labels, fields.periodic, axial_axis=ax)
        self.raw_flows_ = raw
        self.raw_imbalance_ = imbalance_report(raw)
        self.periodic_ = self._project(raw)
        self.throughput_kg_s_ = periodic_throughput(self.periodic_)
        self.seed_flows_ = seed_flows(fields, labels, axial_axis=ax)
        self.seed_imbalance_ = imbalance_report(self.seed_flows_)
        self.section_length_m_ = float(fields.edges[ax][-1] - fields.edges[ax][0])
        if self.throughput_kg_s_ <= 1e-9 * float(self.periodic_.rate.max(initial=0.0)):
            # no net axial flow (e.g. blades without pitch): the closed periodic network still
            # describes radial mixing, but there is no RTD and no blender model
            self.closed_section_ = self.transit_section_ = self.section_ = None
            self.n_upstream_ = 0
            self.mean_residence_time_s_ = float("inf")
            self.axial_velocity_m_s_ = 0.0
            return self
        self.closed_section_ = open_section(self.periodic_, weights=self.projection_weights)
        self.transit_section_ = transit_network(self.periodic_, self.n_upstream)
        self.n_upstream_ = int(self.transit_section_.meta["n_upstream"])
        self.section_ = (
            self.transit_section_ if self.section_form == "transit" else self.closed_section_
        )
        # tau = V / Q of the flowing holdup (stagnant, isolated compartments excluded)
        self.mean_residence_time_s_ = (
            self.closed_section_.total_holdup - self.isolated_holdup_kg_
        ) / self.closed_section_.throughput
        self.axial_velocity_m_s_ = self.section_length_m_ / self.mean_residence_time_s_
        return self

    def _project(self, raw: FlowGraph) -> CompartmentNetwork:
        """Conserving periodic network: project the raw flows, keeping the raw net throughput
        through the periodic face (one extra equality row)."""
        n = raw.n
        C = incidence(n, raw.src, raw.dst)
        fwd, bwd = wrap_directions(self.slice_index_, raw.src, raw.dst, raw.wrap)
        q_raw = float(raw.rate[fwd].sum() - raw.rate[bwd].sum())
        row = np.zeros(raw.src.size)
        row[fwd] = 1.0
        row[bwd] = -1.0
        C = sp.vstack([C, sp.csr_matrix(row)]).tocsr()
        b = np.concatenate([np.zeros(n), [q_raw]])
        f0 = raw.rate
        f = project_flows(C, b, f0, weights=_weights(f0, self.projection_weights))
        self.correction_rel_ = float(np.linalg.norm(f - f0) / max(np.linalg.norm(f0), 1e-300))
        keep = f > 0
        keep &= _main_component(n, raw.src, raw.dst, keep, fwd, f)
        touched = np.zeros(n, dtype=bool)
        touched[raw.src[keep]] = True
        touched[raw.dst[keep]] = True
        self.isolated_ = np.flatnonzero(~touched)
        self.isolated_holdup_kg_ = float(self.holdup_kg_[~touched].sum())
        return CompartmentNetwork(
            holdup=self.holdup_kg_,
            src=raw.src[keep],
            dst=raw.dst[keep],
            rate=f[keep],
            wrap=raw.wrap[keep],
            slice_index=self.slice_index_,
            centroid=self.centroid_,
            meta={"flow_source": self.flow_source_},
        )

    def summary(self) -> dict[str, float | int | str]:
        """Key numbers of the fitted model."""
        return {
            "n_compartments": self.n_compartments_,
            "n_flows": int(self.periodic_.rate.size),
            "flow_source": self.flow_source_,
            "throughput_kg_s": self.throughput_kg_s_,
            "holdup_kg": float(self.holdup_kg_.sum()),
            "mean_residence_time_s": self.mean_residence_time_s_,
            "axial_velocity_m_s": self.axial_velocity_m_s_,
            "raw_imbalance_max_rel": self.raw_imbalance_["max_rel"],
            "projection_correction_rel": self.correction_rel_,
            "mirrored": self.mirrored_,
            "section_form": self.section_form,
            "n_upstream": self.n_upstream_,
            "truncated_crossings": (
                self.transit_section_.meta["truncated_crossings"]
                if self.transit_section_ is not None
                else float("nan")
            ),
            "open_correction_rel": (
                self.closed_section_.meta.get("open_correction_rel", 0.0)
                if self.closed_section_ is not None
                else float("nan")
            ),
            "seed_imbalance_max_rel": self.seed_imbalance_["max_rel"],
            "dropped_flow_kg_s": self.raw_flows_.dropped_kg_s,
            "isolated_compartments": int(self.isolated_.size),
            "isolated_holdup_kg": self.isolated_holdup_kg_,
        }


def available_flow_source(fields: GridFields, flow_source: str) -> str:
    """``flow_source`` if ``fields`` hold its data, else the next they hold in the order
    transitions -> crossings -> velocity."""
    if flow_source == "transitions" and fields.transitions is None:
        flow_source = "crossings"
    if flow_source == "crossings" and not fields.has_crossings:
        flow_source = "velocity"
    return flow_source


def _main_component(
    n: int, src: np.ndarray, dst: np.ndarray, keep: np.ndarray, fwd: np.ndarray, f: np.ndarray
) -> np.ndarray:
    """Edges of the connected part of the network that carries the forward flow through the
    periodic face.  A conserving network can hold other closed parts (e.g. a few bed cells
    whose particles rattle across the periodic face and back): no tracer from the flow
    reaches them, so they are stagnant holdup (``isolated_``), not a trap of the RTD."""
    from scipy.sparse.csgraph import connected_components

    adj = sp.csr_matrix((np.ones(int(keep.sum())), (src[keep], dst[keep])), shape=(n, n))
    _, comp = connected_components(adj, directed=False)
    w = np.bincount(comp[src[keep & fwd]], weights=f[keep & fwd], minlength=comp.max() + 1)
    if not w.any():
        return np.ones(src.size, dtype=bool)
    return comp[src] == int(np.argmax(w))
