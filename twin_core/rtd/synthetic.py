"""Seeded synthetic tracer campaign modelled on the seed's chapter 6 experiments.

Four tracer amounts (10, 7.5, 6, 5 g) x three repeats pulsed into 12 kg/h of bulk powder
(seed 6.1.2). Each run's true RTD is the open-open axial dispersion model with parameters drawn
from the Table 6.2 untruncated row (tau_d 11.92 +/- 0.57 s, tau 16.37 +/- 0.51 s,
Pe 7.67 +/- 0.13). True outlet concentration (% w/w) = 100 r m E(t) / Q times a day factor, with the apparent
recovery r = 0.7 chosen so that the 10 g peak (~10 % w/w) matches Table 6.1's heights
(the 6 g runs were measured on another day with a recalibrated NIR model: intensity shift).
Measured = true + baseline offset + white + pink + proportional noise + sparse outliers.
Defaults put the baseline noise at ~0.12-0.13 % w/w with a slightly negative mean, as the
seed's PAT baseline (t > 120 s: mean -0.03 to -0.074, std 0.125-0.132).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from twin_core.rtd.models import axial_dispersion_open
from twin_core.rtd.noise import pink_noise

__all__ = ["TABLE_6_2", "SyntheticRun", "CampaignConfig", "generate_campaign", "generate_run"]

#: Table 6.2 untruncated row: mean and st. dev. over repeats
TABLE_6_2 = {"tau_d": (11.92, 0.57), "tau": (16.37, 0.51), "pe": (7.67, 0.13)}


@dataclass
class SyntheticRun:
    """One synthetic run with its ground truth."""

    amount_g: float
    repeat: int
    day: int
    t: NDArray[np.float64]
    c: NDArray[np.float64]  # measured, % w/w
    c_true: NDArray[np.float64] = field(repr=False)  # noise-free, no offset
    e_true: NDArray[np.float64] = field(repr=False)
    params: dict[str, float] = field(default_factory=dict)
    intensity_factor: float = 1.0
    baseline_offset: float = 0.0
    outlier_indices: NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    noise: dict[str, float] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.amount_g:g}g_r{self.repeat}"


@dataclass(frozen=True)
class CampaignConfig:
    amounts_g: tuple[float, ...] = (10.0, 7.5, 6.0, 5.0)
    repeats: int = 3
    flow_g_s: float = 12000.0 / 3600.0
    recovery: float = 0.7
    dt_s: float = 1.0
    duration_s: float = 250.0
    white_std: float = 0.10
    pink_std: float = 0.07
    proportional: float = 0.03
    outlier_rate: float = 0.01
    outlier_size: tuple[float, float] = (1.0, 3.0)
    offset_mean: float = -0.05
    offset_std: float = 0.02
    day_shift: dict = field(default_factory=lambda: {6.0: 0.75})
    day_jitter: float = 0.03


def generate_run(
    amount_g: float,
    repeat: int,
    rng: np.random.Generator,
    cfg: CampaignConfig = CampaignConfig(),
    day: int = 0,
    factor: float = 1.0,
) -> SyntheticRun:
    """One run (see module docstring); `factor` is the day's intensity factor."""
    if amount_g <= 0:
        raise ValueError(f"amount_g must be > 0, got {amount_g!r}")
    t = np.arange(0.0, cfg.duration_s + 0.5 * cfg.dt_s, cfg.dt_s)
    p = {k: float(rng.normal(m, s)) for k, (m, s) in TABLE_6_2.items()}
    e = axial_dispersion_open(t, p["tau_d"], p["tau"], p["pe"])
    c_true = 100.0 * cfg.recovery * amount_g / cfg.flow_g_s * e * factor
    offset = float(rng.normal(cfg.offset_mean, cfg.offset_std))
    noise = (
        rng.normal(0.0, cfg.white_std, t.size)
        + pink_noise(t.size, cfg.pink_std, rng)
        + cfg.proportional * c_true * rng.normal(size=t.size)
    )
    c = c_true + offset + noise
    n_out = rng.poisson(cfg.outlier_rate * t.size)
    idx = np.sort(rng.choice(t.size, size=min(n_out, t.size), replace=False)).astype(np.intp)
    c[idx] += rng.choice([-1.0, 1.0], idx.size) * rng.uniform(*cfg.outlier_size, idx.size)
    return SyntheticRun(
        amount_g,
        repeat,
        day,
        t,
        c,
        c_true,
        e,
        p,
        factor,
        offset,
        idx,
        {"white_std": cfg.white_std, "pink_std": cfg.pink_std, "proportional": cfg.proportional},
    )


def generate_campaign(
    seed: int | np.random.Generator = 0, cfg: CampaignConfig = CampaignConfig()
) -> list[SyntheticRun]:
    """The 12-run campaign (4 amounts x 3 repeats), seeded; amount order as in the seed."""
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    runs = []
    for day, amount in enumerate(cfg.amounts_g):
        factor = float(cfg.day_shift.get(amount, 1.0) * rng.normal(1.0, cfg.day_jitter))
        for r in range(cfg.repeats):
            runs.append(generate_run(amount, r + 1, rng, cfg, day, factor))
    return runs
