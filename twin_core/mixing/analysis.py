"""Mixing analysis of a DEM run: indices -> mixing progress -> T95 fits (seed 4.4.2-4.4.3),
and the T95 table across blade speeds (seed Table 4.2 / Figure 4.7); its figures are in
``twin_core.mixing.plots``."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from twin_core.mixing.series import (
    INDEX_NAMES,
    MixingConfig,
    common_subset,
    compute_indices,
    mixed_reference,
    mixing_progress,
    parse_indices,
)
from twin_core.mixing.t95 import OnsetFit, T95Fit, fit_delayed_onset, fit_t95

#: indices fitted with the oscillating Eq. (30) (the seed does so for average height)
OSCILLATING = frozenset({"AH"})


@dataclass
class MixingAnalysis:
    """Indices, normalised progress and T95 fits of one run.

    ``progress`` is the curve the fits are made on (see ``normalize`` of :func:`analyze`);
    ``progress_random`` is the progress toward a random mixture of the same bed (``None`` when
    no such mixture can be made, see :func:`~twin_core.mixing.series.mixed_reference`), and
    ``final_vs_random`` its mean over the last part of the run (1 = as mixed as random).
    ``onset_fits`` are the delayed-onset fits (mixing starts after filling), beside ``fits``.
    """

    indices: pd.DataFrame
    progress: pd.DataFrame
    fits: dict[str, T95Fit]
    progress_random: pd.DataFrame | None = None
    final_vs_random: dict[str, float] | None = None
    normalize: str = "plateau"
    onset_fits: dict[str, OnsetFit] | None = None

    def t95_table(self) -> pd.DataFrame:
        """Per index: Eq. (29)/(30) fit (A, gamma, w, T95, R^2), the delayed-onset fit (onset
        ``t0_s``, ``T95_onset_s``, ``R2_onset``) and ``final_vs_random``."""
        onset = self.onset_fits or {}
        rows = []
        for k, f in self.fits.items():
            o = onset.get(k)
            rows.append(
                {"index": k, "model": f.model, "A": f.A, "gamma": f.gamma, "w": f.w,
                 "T95_s": f.t95, "R2": f.r2,
                 "t0_s": o.t0 if o else np.nan, "T95_onset_s": o.t95 if o else np.nan,
                 "R2_onset": o.r2 if o else np.nan,
                 "final_vs_random": (self.final_vs_random or {}).get(k, np.nan)}
            )  # fmt: skip
        return pd.DataFrame(rows).set_index("index")


def analyze(
    frames: Sequence,
    config: MixingConfig,
    indices: str | Sequence[str] = "all",
    smooth_window: int = 11,
    n_shuffles: int = 3,
    allow_lost: bool = False,
    normalize: str = "plateau",
    tail_fraction: float = 0.2,
    fit_onset: bool = True,
) -> MixingAnalysis:
    """Compute indices on ``frames`` (first frame = segregated start), normalise them to
    0..1 with the random-mixture reference of the first frame, and fit Eq. (29) (Eq. (30) for
    AH) to the Savitzky-Golay smoothed progress of each index. ``allow_lost``: see
    :func:`~twin_core.mixing.series.compute_indices`.

    ``normalize="plateau"`` (default, the seed's 0-1 normalisation of each curve, 4.4.2) maps
    the initial value to 0 and the mean of the last ``tail_fraction`` of the run to 1, so T95
    is the time to 95 % of the approach to the steady state; ``normalize="random"`` maps the
    random mixture of the same bed to 1 (a bed that stays less mixed than random then never
    reaches 0.95). Both progress curves are kept in the result. ``fit_onset``: also fit the
    delayed-onset curve (:func:`~twin_core.mixing.t95.fit_delayed_onset`) of each index."""
    if normalize not in ("plateau", "random"):
        raise ValueError(f"normalize must be 'plateau' or 'random', got {normalize!r}")
    if not 0.0 < tail_fraction < 1.0:
        raise ValueError(f"tail_fraction must be in (0, 1), got {tail_fraction}")
    frames = list(frames)
    names = parse_indices(indices)
    dropped = 0
    if allow_lost:
        frames, dropped = common_subset(frames)
    df = compute_indices(frames, names, config)
    df.attrs["dropped_particles"] = dropped
    n_tail = max(1, int(round(tail_fraction * len(df))))
    prog_random, final = _random_progress(df, frames[0], names, config, n_shuffles, n_tail)
    if normalize == "random":
        if prog_random is None:
            raise ValueError(
                "normalize='random' needs a random mixture of the bed, and every size class "
                "holds one species: use normalize='plateau'"
            )
        prog = prog_random
    else:
        prog = mixing_progress(df, df.iloc[-n_tail:].mean())
    fits, onset = _fit_curves(prog, names, smooth_window, onset=fit_onset)
    return MixingAnalysis(df, prog, fits, prog_random, final, normalize, onset)


def _random_progress(df, frame0, names, config, n_shuffles, n_tail):
    """Progress toward a random mixture of the first frame's bed and its mean over the tail;
    ``(None, {})`` when the species differ in size (no random mixture by equal swaps)."""
    try:
        ref = mixed_reference(frame0, names, config, n_shuffles=n_shuffles, seed=config.seed)
    except ValueError as err:
        if "size class" not in str(err):
            raise
        return None, {}
    prog = mixing_progress(df, ref)
    return prog, {n: float(prog[n].iloc[-n_tail:].mean()) for n in names if n in prog}


def _fit_curves(
    prog: pd.DataFrame, names, smooth_window: int, onset: bool
) -> tuple[dict[str, T95Fit], dict[str, OnsetFit]]:
    """Eq. (29) (Eq. (30) for AH) and, with ``onset``, the delayed-onset fit of each index;
    an index whose fit fails is left out (reported missing rather than guessed)."""
    fits: dict[str, T95Fit] = {}
    onsets: dict[str, OnsetFit] = {}
    t = prog["t"].to_numpy()
    for name in names:
        y = prog[name].to_numpy()
        if not np.all(np.isfinite(y)) or len(y) < 5:
            continue
        model = "osc" if name in OSCILLATING else "exp"
        try:
            fits[name] = fit_t95(t, y, model, smooth_window)
        except (RuntimeError, ValueError):
            continue
        if onset and len(y) >= 8:
            try:
                onsets[name] = fit_delayed_onset(t, y, model, smooth_window)
            except (RuntimeError, ValueError):
                pass
    return fits, onsets


def t95_by_speed(analyses: Mapping[float, MixingAnalysis]) -> pd.DataFrame:
    """Table 4.2 layout: rows = indices, columns = blade speed (rpm), values = T95 (s)."""
    cols = {}
    for rpm, an in sorted(analyses.items(), reverse=True):
        cols[f"{rpm:g} rpm"] = {k: f.t95 for k, f in an.fits.items()}
    order = [n for n in INDEX_NAMES if any(n in c for c in cols.values())]
    return pd.DataFrame(cols).reindex(order)
