"""The whole build of a blender compartment model from DEM grid fields (``twin compartment
build``), as one library call: :func:`build_blender_model`.

1. The compartment model of the periodic section (``CompartmentModel``: zoning, compartments,
   conserving flows, the section's transit RTD; seed chapter 5).
2. Radial mixing of the closed section: RSD(t) of a two-type split along ``split_axis`` and the
   Eq. (10) parameters ``RSD(t) = RSD_ss + (RSD_0 - RSD_ss) exp(-k_b t)``, from the compartments
   (Eq. 2) or from the cell-level network sampled like the DEM's particles (grid RSD of seed
   Eq. B.1, ``twin_core.compartment.radial.grid_rsd_sampled``).
3. The whole blender: ``sections`` sections in series (Eq. 8-9), the rpm law of dynamic runs from
   DEM runs at other blade speeds (their net axial flows), exported as a ``BlenderModel``.
4. Validation of the section RTD against DEM particle transit times (censored to their recording
   window when it is known) or, without them, a random-walk surrogate of the cell network
   (``twin_core.compartment.surrogate``): ``twin_core.compartment.validation.compare_rtd``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["BuildOptions", "BuildResult", "build_blender_model", "load_transit_times"]


@dataclass
class BuildOptions:
    """Options of :func:`build_blender_model` (the ``twin compartment build`` options).

    ``rpm_runs``: blade speed -> grid fields of a DEM run at that speed (its net axial flow
    calibrates the rpm law; needs ``rpm``). ``transit_times`` / ``transit_window_s``: DEM
    particle transit times of the section (s) and their recording window. ``surrogate``:
    particles of the random-walk surrogate when crossings exist (0: none).

    ``flow_source``: "crossings" (face crossings, zoned by ``variables`` / ``tol`` /
    ``min_cells``: the seed's method), "transitions" (particle transitions at a lag, zoned
    kinetically: ``mobility_classes`` classes of equal cell count of the cells' escape rate
    times the sign of vx, cells of one class in a slice lumped whether or not they touch),
    "velocity", or "auto": with both crossings and transitions in the fields and transit
    times given, both models are built and the one whose (window-censored) RTD is closer to
    the transits in KS distance is kept, both reported (``flow_source_candidates``); without
    transit times, transitions when present, else crossings, else velocity.
    """

    variables: tuple[str, ...] = ("vx", "vy", "vz")
    tol: float = 0.1
    min_cells: int = 3
    flow_source: str = "auto"
    sections: int = 8
    section_form: str = "transit"
    n_upstream: int | None = None
    rpm: float | None = None
    rpm_runs: Mapping[float, Any] = field(default_factory=dict)
    mobility_classes: int = 8
    split_axis: int = 1
    rsd_source: str = "cells"
    rsd_grid: tuple[int, int, int] = (10, 6, 6)
    transit_times: np.ndarray | None = None
    transit_window_s: float | None = None
    surrogate: int = 20000
    seed: int = 0


@dataclass
class BuildResult:
    """What :func:`build_blender_model` made: the section model, the blender model, the report
    (JSON-able) and the curves its figures show (``twin_core.compartment.plots``)."""

    model: Any
    blender: Any
    report: dict[str, Any]
    fields: Any
    t_rtd: np.ndarray
    e_section: np.ndarray
    samples: np.ndarray | None
    validation: str | None
    e_censored: np.ndarray | None
    t_mix: np.ndarray
    rsd_t: np.ndarray
    rsd_grid: np.ndarray | None
    fit: dict[str, float]


def load_transit_times(path: str | Path) -> tuple[np.ndarray, float | None]:
    """Transit times (s) from a .npy array or an .npz holding ``transit_s`` (and optionally
    ``window_s``, the length of the recording window)."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"transit-times file {str(path)!r} does not exist")
    data = np.load(path, allow_pickle=False)
    if isinstance(data, np.lib.npyio.NpzFile):
        with data:
            if "transit_s" not in data.files:
                raise ValueError(f"{path}: key 'transit_s' missing (keys: {data.files})")
            window = float(data["window_s"]) if "window_s" in data.files else None
            return np.asarray(data["transit_s"], dtype=float), window
    return np.asarray(data, dtype=float), None


def mixing_grid(model: Any) -> np.ndarray:
    """Times for the radial-mixing RSD: up to 3 x the section residence time."""
    return np.linspace(0.0, 3.0 * model.mean_residence_time_s_, 121)


def cell_grid_rsd(fields: Any, cells: Any, opts: BuildOptions, t_mix: np.ndarray) -> np.ndarray:
    """Grid RSD (seed Eq. B.1) of the cell-level network sampled like the DEM's particles
    (Poisson counts per cell, binomial types; right also for sparse runs): the radial-mixing
    curve a DEM grid RSD would show."""
    from twin_core.compartment.radial import (
        flowing,
        grid_rsd_sampled,
        section_concentrations,
        split_initial,
    )
    from twin_core.compartment.surrogate import coarse_index

    c0 = split_initial(fields, cells.labels_, axis=opts.split_axis)
    c = section_concentrations(cells.periodic_, c0, t_mix)
    coarse = coarse_index(fields, cells.mask_, tuple(opts.rsd_grid))
    return grid_rsd_sampled(
        c,
        cells.labels_,
        fields.occupancy,
        coarse,
        int(np.prod(opts.rsd_grid)),
        seed=opts.seed,
        n_samples=10,
        active=flowing(cells.periodic_),
    )


def zoning_kwargs(opts: BuildOptions, flow_source: str) -> dict[str, Any]:
    """CompartmentModel zoning arguments of a flow source (:class:`BuildOptions`)."""
    if flow_source == "transitions":
        return {
            "variables": ("mobility", "vx"),
            "quantile_classes": {"mobility": opts.mobility_classes},
            "tol_fraction": opts.tol,
            "connected": False,
            "flow_source": "transitions",
        }
    return {
        "variables": opts.variables,
        "tol_fraction": opts.tol,
        "min_cells": opts.min_cells,
        "flow_source": flow_source,
    }


def flow_source_candidates(fields: Any, opts: BuildOptions) -> list[str]:
    """The flow sources :func:`build_blender_model` builds (``BuildOptions.flow_source``)."""
    if opts.flow_source != "auto":
        return [opts.flow_source]
    have = [
        s
        for s, ok in (
            ("transitions", fields.transitions is not None),
            ("crossings", fields.has_crossings),
        )
        if ok
    ]
    if not have:
        return ["velocity"]
    return have if opts.transit_times is not None else have[:1]


def _section_model(fields: Any, opts: BuildOptions, source: str, flow_source: str) -> Any:
    from twin_core.compartment import CompartmentModel

    model = CompartmentModel(
        section_form=opts.section_form,
        n_upstream=opts.n_upstream,
        **zoning_kwargs(opts, flow_source),
    ).fit(fields)
    if model.section_ is None:
        raise ValueError(
            f"{source}: no net axial flow through the periodic face "
            f"({model.throughput_kg_s_:.3g} kg/s): no RTD, no blender model"
        )
    return model


def _validation_samples(
    opts: BuildOptions, cells: Any, fields: Any
) -> tuple[np.ndarray | None, str | None]:
    """DEM transit times if given, else a random-walk surrogate of the cell network (its flows
    made conserving: raw counts of a short DEM run leave cells entered but never left)."""
    if opts.transit_times is not None:
        return opts.transit_times, "DEM transit times"
    if cells is not None and fields.has_crossings and opts.surrogate > 0:
        from twin_core.compartment.surrogate import walk_transit_times

        return walk_transit_times(cells.periodic_, opts.surrogate, seed=opts.seed), (
            "random-walk surrogate"
        )
    return None, None


def _section_curves(model: Any, opts: BuildOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, section E(t), the E(t) compared with transits): the latter censored to the recording
    window when DEM transit times and their window are given, else E(t) itself."""
    from twin_core.compartment.validation import window_censored

    t = np.linspace(0.0, 8.0 * model.mean_residence_time_s_, 2001)
    e = model.section_.impulse_response(t)
    censor = opts.transit_window_s is not None and opts.transit_times is not None
    return t, e, window_censored(t, e, opts.transit_window_s) if censor else e


def build_blender_model(fields: Any, opts: BuildOptions, source: str = "fields") -> BuildResult:
    """Fields -> section model -> radial mixing -> blender model -> RTD validation (module
    docstring). ``source`` names the fields in the model and in errors."""
    from twin_core.compartment import (
        CompartmentModel,
        compare_rtd,
        fit_rsd_decay,
        section_rsd,
        split_initial,
        to_blender_model,
    )
    from twin_core.compartment.fields import mirror_axis
    from twin_core.compartment.model import available_flow_source

    t0 = time.perf_counter()
    candidates = {
        fs: _section_model(fields, opts, source, fs) for fs in flow_source_candidates(fields, opts)
    }
    t_build = time.perf_counter() - t0
    curves = {fs: _section_curves(m, opts) for fs, m in candidates.items()}
    against = {  # each candidate against the DEM transit times (the choice and its report)
        fs: compare_rtd(t, e_cmp, samples=opts.transit_times)
        for fs, (t, _, e_cmp) in curves.items()
        if opts.transit_times is not None
    }
    scores = {fs: against[fs]["ks"] if fs in against else float("nan") for fs in candidates}
    chosen = min(scores, key=lambda fs: scores[fs])
    model = candidates[chosen]
    if model.mirrored_:  # net flow towards -x: work in the model's orientation
        fields = mirror_axis(fields, model.axial_axis)
    cells = None  # every cell its own compartment: radial mixing and the surrogate
    if opts.rsd_source == "cells" or (
        opts.transit_times is None and fields.has_crossings and opts.surrogate > 0
    ):
        cells = CompartmentModel(
            resolution="cells", flow_source=model.flow_source_, axial_direction="+"
        ).fit(fields)
    c0 = split_initial(fields, model.labels_, axis=opts.split_axis)
    t_mix = mixing_grid(model)
    rsd_t = section_rsd(model.periodic_, c0, t_mix)
    fit_comp = fit_rsd_decay(t_mix, rsd_t)
    rsd_grid = cell_grid_rsd(fields, cells, opts, t_mix) if opts.rsd_source == "cells" else None
    fit = fit_rsd_decay(t_mix, rsd_grid) if rsd_grid is not None else fit_comp
    rpm_runs = {
        float(r): CompartmentModel(
            **zoning_kwargs(opts, available_flow_source(f, model.flow_source_))
        ).fit(f)
        for r, f in opts.rpm_runs.items()
    }
    bm = to_blender_model(
        model,
        rpm_runs=rpm_runs or None,
        n_sections=opts.sections,
        rpm_basis=opts.rpm,
        rsd_fit=fit,
        source=f"{source} ({model.flow_source_})",
    )
    report = {
        **model.summary(),
        "build_s": t_build,
        "rsd_source": opts.rsd_source,
        "rsd_fit": fit,
        "rsd_fit_compartments_eq2": fit_comp,
        "blender_mean_residence_time_s": bm.mean_residence_time_s,
        "flow_source_candidates": {
            fs: {"n_compartments": m.n_compartments_, "censored_ks": scores[fs]}
            for fs, m in candidates.items()
        },
    }
    samples, validation = _validation_samples(opts, cells, fields)
    t_rtd, e_sec, e_cmp = curves[chosen]
    if samples is not None:
        if e_cmp is not e_sec:
            validation = f"DEM transit times (window {opts.transit_window_s} s)"
        report["rtd_validation"] = {
            "against": validation,
            **(
                against[chosen] if chosen in against else compare_rtd(t_rtd, e_cmp, samples=samples)
            ),
        }
    return BuildResult(
        model=model,
        blender=bm,
        report=report,
        fields=fields,
        t_rtd=t_rtd,
        e_section=e_sec,
        samples=samples,
        validation=validation,
        e_censored=e_cmp if samples is not None and e_cmp is not e_sec else None,
        t_mix=t_mix,
        rsd_t=rsd_t,
        rsd_grid=rsd_grid,
        fit=fit,
    )
