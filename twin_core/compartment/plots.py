"""Figures of a compartment-model build (matplotlib ``Figure`` objects; the caller saves them):
zone maps, compartment maps, the network graph, the section RTD against its validation sample,
radial mixing and the RSD along the blender. No pyplot state is used."""

from __future__ import annotations

import matplotlib
import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.colors import BoundaryNorm, ListedColormap
from matplotlib.figure import Figure

from twin_core.compartment.blender_model import blender_model_rsd_profile, blender_model_rtd
from twin_core.compartment.build import BuildResult

__all__ = ["build_figures", "plot_simulation"]


def plot_zone_maps(r: BuildResult) -> Figure:
    """The zones of each zoning variable in the first x slice (-2: empty cells)."""
    model, fields = r.model, r.fields
    ext = [fields.y_edges[0], fields.y_edges[-1], fields.z_edges[0], fields.z_edges[-1]]
    nv = len(model.zones_)
    zmin = min(int(z.min()) for z in model.zones_.values())
    zmax = max(int(z.max()) for z in model.zones_.values())
    levels = np.arange(zmin, zmax + 1)
    if zmin == -2 and zmax <= 1:  # sign zones: empty, -1, 0, +1
        cmap = ListedColormap(["white", "#3b4cc0", "#a1d99b", "#b40426"][: levels.size])
    else:
        viridis = matplotlib.colormaps["viridis"]
        cmap = ListedColormap(["white"] + list(viridis(np.linspace(0, 1, max(levels.size - 1, 1)))))
    norm = BoundaryNorm(np.arange(zmin - 0.5, zmax + 1.5), cmap.N)
    fig = Figure(figsize=(3.8 * nv + 1, 3.6), layout="constrained")
    axes = fig.subplots(1, nv, squeeze=False)
    im = None
    for ax, (name, zmap) in zip(axes[0], model.zones_.items()):
        im = ax.imshow(zmap[0].T, origin="lower", extent=ext, cmap=cmap, norm=norm)
        ax.set_title(f"zones of {name}, slice x=0")
        ax.set_xlabel("y (m)")
    axes[0][0].set_ylabel("z (m)")
    fig.colorbar(im, ax=axes[0].tolist(), ticks=levels, label="zone (-2 empty)")
    return fig


def plot_compartment_maps(r: BuildResult) -> Figure:
    """The compartments of each zoning variable and of their overlay, first x slice."""
    model, fields = r.model, r.fields
    ext = [fields.y_edges[0], fields.y_edges[-1], fields.z_edges[0], fields.z_edges[-1]]
    maps = dict(model.maps_)
    maps["overlay (compartments)"] = model.labels_
    fig = Figure(figsize=(3.8 * len(maps), 3.6), layout="constrained")
    axes = fig.subplots(1, len(maps), squeeze=False)
    for ax, (name, lab) in zip(axes[0], maps.items()):
        sl = lab[0].astype(float)
        sl[sl < 0] = np.nan
        ax.imshow(sl.T, origin="lower", extent=ext, cmap="tab20", interpolation="nearest")
        ax.set_title(f"{name}: {len(np.unique(lab[0][lab[0] >= 0]))} in slice 0")
        ax.set_xlabel("y (m)")
    return fig


def plot_network(r: BuildResult) -> Figure:
    """The periodic network: compartments at their centroids (size: holdup), links (width:
    flow), slice 0 in the y-z plane and all compartments in x-z."""
    net = r.model.periodic_
    fig = Figure(figsize=(11, 4.5), layout="tight")
    axes = fig.subplots(1, 2)
    cen = net.centroid
    rmax = float(net.rate.max())
    sc = None
    for ax, (i, j, lab_i, lab_j) in zip(axes, ((1, 2, "y", "z"), (0, 2, "x", "z"))):
        sel = (
            (net.slice_index[net.src] == 0) & (net.slice_index[net.dst] == 0)
            if i == 1
            else (~net.wrap)
        )
        seg = np.stack([cen[net.src[sel]][:, [i, j]], cen[net.dst[sel]][:, [i, j]]], axis=1)
        widths = 0.3 + 2.5 * net.rate[sel] / rmax
        ax.add_collection(LineCollection(seg, colors="0.5", linewidths=widths, alpha=0.6))
        pts = net.slice_index == 0 if i == 1 else np.ones(net.n, bool)
        sc = ax.scatter(
            cen[pts, i],
            cen[pts, j],
            s=8 + 200 * net.holdup[pts] / net.holdup.max(),
            c=net.slice_index[pts],
            cmap="viridis",
            zorder=3,
        )
        ax.set_xlabel(f"{lab_i} (m)")
        ax.set_ylabel(f"{lab_j} (m)")
    axes[0].set_title("network, slice 0 (size: holdup, width: flow)")
    axes[1].set_title(f"network, all {net.n} compartments")
    fig.colorbar(sc, ax=axes[1], label="slice")
    return fig


def plot_rtd(r: BuildResult) -> Figure:
    """Section RTD of the model against the validation sample (histogram), the censored model
    if any, V/Q; the whole blender's RTD for 1, 2, 4 and n sections (Eq. 8-9)."""
    fig = Figure(figsize=(11, 4), layout="tight")
    axes = fig.subplots(1, 2)
    ax = axes[0]
    if r.samples is not None:
        fin = np.asarray(r.samples)[np.isfinite(r.samples)]
        ax.hist(
            fin,
            bins=80,
            range=(0, r.t_rtd[-1]),
            density=True,
            alpha=0.4,
            label=f"{r.validation} (n={fin.size})",
        )
    ax.plot(r.t_rtd, r.e_section, "k-", label=f"compartment model ({r.model.section_form} form)")
    if r.e_censored is not None:
        ax.plot(r.t_rtd, r.e_censored, "r--", label="model censored to the recording window")
    ax.axvline(r.model.mean_residence_time_s_, color="k", ls=":", label="V/Q")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("E(t) (1/s)")
    ax.set_title("section RTD")
    ax.legend(fontsize=8)
    bm = r.blender
    tb = np.linspace(0.0, 3.0 * bm.mean_residence_time_s, 1501)
    for k in sorted({1, 2, 4, bm.n_sections}):
        axes[1].plot(tb, blender_model_rtd(bm, tb, n_sections=k), label=f"{k} sections")
    axes[1].set_xlabel("t (s)")
    axes[1].set_title("sections in series (Eq. 8-9)")
    axes[1].legend(fontsize=8)
    return fig


def plot_rsd(r: BuildResult) -> Figure:
    """Radial mixing of the closed section (RSD(t) and its Eq. 10 fit) and the RSD along the
    blender."""
    from twin_core.compartment import rsd_decay

    fig = Figure(figsize=(11, 4), layout="tight")
    axes = fig.subplots(1, 2)
    fit = r.fit
    axes[0].plot(r.t_mix, r.rsd_t, "k.", ms=3, label="compartments (Eq. 2)")
    if r.rsd_grid is not None:
        axes[0].plot(r.t_mix, r.rsd_grid, "b.", ms=3, label="cell network: grid RSD, sampled")
    axes[0].plot(
        r.t_mix,
        rsd_decay(r.t_mix, fit["rsd_ss"], fit["rsd_0"], fit["k_b"]),
        "r-",
        label=f"Eq. 10 fit, k_b={fit['k_b']:.3g}/s",
    )
    axes[0].set_xlabel("t (s)")
    axes[0].set_ylabel("RSD")
    axes[0].set_title("radial mixing, closed section")
    axes[0].legend(fontsize=8)
    bm = r.blender
    x = np.linspace(0.0, bm.n_sections * bm.section_length_m, 200)
    axes[1].plot(x, blender_model_rsd_profile(bm, x), "r-")
    axes[1].set_xlabel("x along the blender (m)")
    axes[1].set_ylabel("RSD")
    axes[1].set_title("RSD along the blender (Eq. 10)")
    return fig


def build_figures(r: BuildResult) -> dict[str, Figure]:
    """The figures of a build by file name."""
    return {
        "zone_maps.png": plot_zone_maps(r),
        "compartment_maps.png": plot_compartment_maps(r),
        "network_graph.png": plot_network(r),
        "rtd_comparison.png": plot_rtd(r),
        "rsd.png": plot_rsd(r),
    }


def plot_simulation(t: np.ndarray, inlet: np.ndarray, outlet: np.ndarray) -> Figure:
    """Inlet and outlet (compartment model) of a what-if run."""
    fig = Figure(figsize=(9, 4))
    ax = fig.subplots()
    ax.plot(t, inlet, color="0.6", label="inlet")
    ax.plot(t, outlet, "k-", label="outlet (compartment model)")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("concentration")
    ax.legend()
    return fig
