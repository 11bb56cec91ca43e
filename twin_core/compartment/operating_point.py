"""The whole blender's E(t) at an operating point (blade speed, throughput) from a table of
compartment models of its periodic section, each built from a DEM run at one blade speed.

A section model at blade speed r_k (``BlenderModel.rpm_basis``) carries the DEM run's own time
scale: its flowing holdup V_k and net axial flow q_k (the blades' conveying rate at the DEM fill),
so its whole-blender E_k(t) (``blender_model_rtd``, n sections in series) has the mean
tau_k = int t E_k dt. The line runs at another throughput Q and its holdup M is set by the weir,
not by the DEM fill. The rule used here (documented in docs/compartment.md):

1. **Mean residence time.** The conveying frequency of the blades, kappa(r) = q(r) / V (1/s), is
   taken from the DEM runs (linear in r between the table's speeds, through (0, 0) below the
   lowest, proportional to r above the highest). The holdup the line settles to is
   M(r, Q) = M_b (kappa(r_b) / kappa(r)) (Q / Q_b)^beta around a basis point (r_b, Q_b, M_b),
   so the mean residence time is

       tau(r, Q) = M(r, Q) / Q = (M_b / Q_b) (kappa(r_b) / kappa(r)) (Q / Q_b)^(beta - 1).

   beta = 1 (holdup proportional to throughput, mean independent of Q: a conveying rate
   proportional to the holdup) is the default; beta = 0 keeps the holdup fixed (mean
   proportional to 1 / Q). Without a basis holdup the DEM runs' own time scale is kept:
   tau(r) = tau_k kappa(r_k) / kappa(r).

2. **Shape.** Each table model's E_k is rescaled in time to that mean (flows scaled together at
   fixed holdup, which keeps the dimensionless RTD: E(t) = (tau_k / tau) E_k(t tau_k / tau),
   Nauman 2008 ch. 15), and between two table speeds r_a < r < r_b the two rescaled laws are
   mixed linearly in r: E = w E_a + (1 - w) E_b, w = (r_b - r) / (r_b - r_a). At a table speed
   the model is that run's; outside the table, the nearest speed's shape.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from schemas.blender_model import BlenderModel
from twin_core.compartment.blender_model import blender_model_rtd

__all__ = [
    "BLADES26_MODELS",
    "INTERIM_MODELS",
    "SHIPPED_MODELS",
    "HoldupRule",
    "ModelTable",
    "OperatingPoint",
    "configured_point",
    "load_models",
    "rtd_equivalent",
    "table_from_config",
]

#: the section models the live twin uses by default (one JSON per blade speed), built by
#: ``benchmarks/blender_campaign.py`` from the seed-size DEM section (``blender.yaml``: 6,000
#: particles, 20 s, paddles to 3 mm from the trough; docs/compartment.md)
SHIPPED_MODELS = Path(__file__).parent / "data"
#: kept for study, not the default: the 600-particle runs of the first geometry
#: (``blender_interim.yaml``; the default before the seed-size campaign) ...
INTERIM_MODELS = SHIPPED_MODELS / "interim"
#: ... and the seed-size runs of the first geometry (``blender_blades26.yaml``: 26 mm paddles
#: whose tips leave an unswept, slow annulus above the trough)
BLADES26_MODELS = SHIPPED_MODELS / "blades26"


@dataclass(frozen=True)
class OperatingPoint:
    """Blade speed (rev/min) and throughput (kg/h) of the blender."""

    rpm: float
    throughput_kg_h: float


@dataclass(frozen=True)
class HoldupRule:
    """How the line's holdup follows the operating point (module docstring, step 1).

    ``holdup_kg``: flowing holdup of the whole blender at the basis point (None: the DEM runs'
    own time scale); ``basis``: that point; ``beta``: exponent of the throughput.
    """

    holdup_kg: float | None = None
    basis: OperatingPoint | None = None
    beta: float = 1.0

    def __post_init__(self) -> None:
        if self.holdup_kg is not None:
            if not self.holdup_kg > 0:
                raise ValueError(f"holdup_kg must be > 0, got {self.holdup_kg!r}")
            if self.basis is None or not (self.basis.rpm > 0 and self.basis.throughput_kg_h > 0):
                raise ValueError(
                    f"basis must have rpm > 0 and throughput_kg_h > 0, got {self.basis}"
                )


class ModelTable:
    """Section models at several blade speeds and the whole blender's E(t) at any operating
    point (module docstring).

    Args:
        models: section models, each with ``rpm_basis`` (one per blade speed; a later one at the
            same speed replaces an earlier).
        rule: the holdup rule.
    """

    def __init__(self, models: Sequence[BlenderModel], rule: HoldupRule | None = None) -> None:
        self.rule = rule or HoldupRule()
        self._models: dict[float, BlenderModel] = {}
        for m in models:
            self.add(m)
        if not self._models:
            raise ValueError("models must hold at least one BlenderModel, got none")

    def add(self, model: BlenderModel) -> None:
        """Add ``model`` at its blade speed (replacing the one there)."""
        if model.rpm_basis is None:
            raise ValueError("model.rpm_basis must be given, got None")
        self._models[float(model.rpm_basis)] = model

    @property
    def speeds(self) -> list[float]:
        """The table's blade speeds, ascending."""
        return sorted(self._models)

    def conveying_frequency(self, rpm: float) -> float:
        """kappa(r) = q / V (1/s) of the blades (module docstring, step 1): the table models'
        1 / tau_k (tau_k = n V_k / q_k, ``BlenderModel.mean_residence_time_s``, the mean of the
        network's E_k) interpolated linearly in r, through (0, 0) below the lowest speed,
        proportional to r above the highest."""
        if not (np.isfinite(rpm) and rpm > 0):
            raise ValueError(f"rpm must be finite and > 0, got {rpm!r}")
        r = np.array(self.speeds)
        k = np.array([1.0 / self._models[s].mean_residence_time_s for s in r])
        if rpm >= r[-1]:
            return float(k[-1] * rpm / r[-1])
        return float(np.interp(rpm, np.concatenate([[0.0], r]), np.concatenate([[0.0], k])))

    def mean_residence_time_s(self, point: OperatingPoint) -> float:
        """tau(r, Q) of the module docstring, step 1."""
        kappa = self.conveying_frequency(point.rpm)
        rule = self.rule
        if rule.holdup_kg is None:
            return 1.0 / kappa
        if not (np.isfinite(point.throughput_kg_h) and point.throughput_kg_h > 0):
            raise ValueError(f"throughput_kg_h must be > 0, got {point.throughput_kg_h!r}")
        assert rule.basis is not None
        q_b = rule.basis.throughput_kg_h
        tau_b = rule.holdup_kg / (q_b / 3600.0)
        ratio = self.conveying_frequency(rule.basis.rpm) / kappa
        return tau_b * ratio * (point.throughput_kg_h / q_b) ** (rule.beta - 1.0)

    def weights(self, rpm: float) -> list[tuple[float, float]]:
        """(table speed, weight) of the shapes mixed at ``rpm`` (module docstring, step 2)."""
        r = self.speeds
        if rpm <= r[0]:
            return [(r[0], 1.0)]
        if rpm >= r[-1]:
            return [(r[-1], 1.0)]
        hi = int(np.searchsorted(r, rpm))
        a, b = r[hi - 1], r[hi]
        w = (b - rpm) / (b - a)
        return [(a, w), (b, 1.0 - w)] if w < 1.0 else [(a, 1.0)]

    def rtd(self, point: OperatingPoint, t: np.ndarray) -> np.ndarray:
        """E(t) (1/s) of the whole blender at ``point`` on the uniform grid ``t`` from 0:
        sum_k w_k (tau_k / tau) E_k(t tau_k / tau) (module docstring)."""
        t = np.asarray(t, dtype=float)
        tau = self.mean_residence_time_s(point)
        e = np.zeros_like(t)
        for speed, w in self.weights(point.rpm):
            model = self._models[speed]
            stretch = model.mean_residence_time_s / tau
            e += w * stretch * np.asarray(blender_model_rtd(model, t * stretch), dtype=float)
        return e

    def rtd_equivalent(self, point: OperatingPoint) -> tuple[str, dict[str, float]]:
        """The axial-dispersion model (open-open with delay, seed Eq. 7 as in Table 6.2) fitted
        by least squares to E(t) at ``point`` on a grid of 0.25 s over 8 mean residence times:
        (model name, parameters)."""
        from twin_core.rtd.fitting import fit

        tau = self.mean_residence_time_s(point)
        t = np.arange(0.0, 8.0 * tau, 0.25)
        res = fit(t, self.rtd(point, t), "ad_open")
        return "axial_dispersion_open", {k: float(v) for k, v in res.params.items()}

    def describe(self, point: OperatingPoint) -> str:
        """The models and weights used at ``point``, e.g. ``'50 rpm x 0.40 + 100 rpm x 0.60'``."""
        parts = [f"{s:g} rpm x {w:.2f}" for s, w in self.weights(point.rpm)]
        return " + ".join(parts)


def load_models(path: str | Path | None = None) -> list[BlenderModel]:
    """BlenderModels from a JSON file or every ``*.json`` of a directory (None: the shipped
    ones), ordered by blade speed."""
    p = SHIPPED_MODELS if path is None else Path(path)
    if p.is_dir():
        files = sorted(p.glob("*.json"))
        if not files:
            raise ValueError(f"export_path {str(p)!r} holds no *.json BlenderModel")
    elif p.exists():
        files = [p]
    else:
        raise ValueError(f"export_path {str(p)!r} does not exist")
    models = [BlenderModel.load(f) for f in files]
    return sorted(models, key=lambda m: m.rpm_basis or 0.0)


def table_from_config(blender: Any) -> ModelTable:
    """The :class:`ModelTable` of a ``schemas.line.BlenderModelConfig`` of kind compartment
    (its models, with ``blade_speed_rpm`` as the speed of a model that names none, and its
    holdup rule)."""
    models = [
        m
        if m.rpm_basis is not None
        else m.model_copy(update={"rpm_basis": blender.blade_speed_rpm})
        for m in load_models(blender.export_path)
    ]
    h = blender.holdup
    rule = (
        HoldupRule()
        if h is None
        else HoldupRule(h.kg, OperatingPoint(h.rpm, h.throughput_kg_h), h.beta)
    )
    return ModelTable(models, rule)


def configured_point(config: Any) -> OperatingPoint:
    """The operating point a ``schemas.line.LineConfig`` declares: ``blender.blade_speed_rpm``
    and the sum of the feeders' set points."""
    q = float(sum(f.setpoint_kg_h for f in config.feeders))
    return OperatingPoint(float(config.blender.blade_speed_rpm), q)


def rtd_equivalent(blender: Any, point: OperatingPoint) -> Any:
    """The ``BlenderModelConfig`` of kind ``rtd`` the declared line model (close-loop, plant
    simulator) uses for a compartment blender: :meth:`ModelTable.rtd_equivalent` at ``point``
    (cached per configuration and point)."""
    return _rtd_equivalent(blender.model_dump_json(), point)


@functools.lru_cache(maxsize=16)
def _rtd_equivalent(blender_json: str, point: OperatingPoint) -> Any:
    from schemas.line import BlenderModelConfig

    blender = BlenderModelConfig.model_validate_json(blender_json)
    model, params = table_from_config(blender).rtd_equivalent(point)
    return blender.model_copy(update={"kind": "rtd", "model": model, "params": params})
