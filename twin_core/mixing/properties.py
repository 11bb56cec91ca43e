"""Feature table of the mixing indices (seed Figure 4.4) and an index-selection helper.

The selection logic follows section 4.4.4 and Figure 4.8 of the seed (the figure itself is not
in the text): the user describes the powder system and the scope of the evaluation; each
answer excludes the indices whose features conflict with it.
"""

from __future__ import annotations

import pandas as pd

from twin_core.mixing.series import INDEX_NAMES, SEED_INDICES

#: Figure 4.4, row by row ("Y" -> True), followed by the sphere spreading index (not in the
#: seed: cheap, one species, no grid, all directions at once, centroid distances only, no
#: parameter)
_FIG_4_4 = {
    "computational_complexity": "N N N N N N N N Y N Y Y Y N N  N",
    "color_dependency": "Y Y Y N Y N Y Y N Y N Y N N N  Y",
    "grid_dependency": "Y Y Y Y Y Y Y Y N N N N N N N  N",
    "direction": "N N N N N N N N Y Y Y N N N N  N",
    "size": "N N N N N N N N Y N Y Y Y Y Y  N",
    "parameter_dependency": "N N N N N N N N Y N N Y N N N  N",
}

#: classification of Figure 4.3 (variance / contact / distance based)
CATEGORY = {
    **dict.fromkeys(["VRR", "VBBC", "RSD", "LI", "MSI", "ESI", "DM", "ME"], "variance"),
    **dict.fromkeys(["SI", "PS", "NNM", "CN"], "contact"),
    **dict.fromkeys(["AH", "SM", "NDM", "SSI"], "distance"),
}


def index_properties() -> pd.DataFrame:
    """Figure 4.4 as a boolean table (rows: indices, columns: features) plus the category and
    whether the row is the seed's (``seed``; False for the sphere spreading index)."""
    data = {feat: [v == "Y" for v in row.split()] for feat, row in _FIG_4_4.items()}
    df = pd.DataFrame(data, index=list(INDEX_NAMES))
    df["category"] = [CATEGORY[name] for name in df.index]
    df["seed"] = [name in SEED_INDICES for name in df.index]
    return df


def select_indices(
    n_components: int = 2,
    polydisperse: bool = False,
    need_direction: bool = False,
    avoid_grid: bool = False,
    cheap_only: bool = False,
    bulk_stays_intact: bool = True,
    avoid_parameters: bool = False,
) -> list[str]:
    """Indices suited to a powder system and evaluation scope (seed 4.4.4 / Fig. 4.8).

    - ``n_components > 2``: only colour-dependent indices evaluate each ingredient; VBBC is
      bimodal only.
    - ``polydisperse``: size-dependent indices (contacts, distances) are biased.
    - ``need_direction``: keep only direction-resolved indices (AH, SM, NDM).
    - ``avoid_grid``: no grid-dependent (variance) index.
    - ``cheap_only``: exclude O(N^2) / neighbour-search indices.
    - ``bulk_stays_intact=False`` (fluidised, aerated, agglomerating): no contact-based index.
    - ``avoid_parameters``: no index with hyper-parameters (SM, NNM).
    """
    if n_components < 2:
        raise ValueError(f"n_components must be >= 2, got {n_components}")
    p = index_properties()
    keep = pd.Series(True, index=p.index)
    if n_components > 2:
        keep &= p["color_dependency"]
    if polydisperse:
        keep &= ~p["size"]
    if need_direction:
        keep &= p["direction"]
    if avoid_grid:
        keep &= ~p["grid_dependency"]
    if cheap_only:
        keep &= ~p["computational_complexity"]
    if not bulk_stays_intact:
        keep &= p["category"] != "contact"
    if avoid_parameters:
        keep &= ~p["parameter_dependency"]
    return [name for name in p.index if keep[name]]
