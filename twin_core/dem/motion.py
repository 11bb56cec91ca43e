"""Prescribed kinematics of DEM walls (meshes): rotation about an axis and translation."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["RotationMotion", "TranslationMotion"]


@dataclass(frozen=True)
class RotationMotion:
    """Rigid rotation about the axis through ``axis_point`` along ``axis_dir`` at ``rpm``.

    The angle is ``theta = 2 pi rpm / 60 (min(max(t, t_start), t_end) - t_start)`` (right-hand rule
    about ``axis_dir``); the wall velocity at a point p is ``omega x (p - axis_point)``.
    """

    axis_point: tuple[float, float, float]
    axis_dir: tuple[float, float, float]
    rpm: float
    t_start: float = 0.0
    t_end: float = math.inf

    def __post_init__(self) -> None:
        d = np.asarray(self.axis_dir, float)
        if d.shape != (3,) or not np.linalg.norm(d) > 0:
            raise ValueError(f"axis_dir must be a non-zero 3-vector, got {self.axis_dir}")
        if np.asarray(self.axis_point, float).shape != (3,):
            raise ValueError(f"axis_point must be a 3-vector, got {self.axis_point}")
        if not self.t_end >= self.t_start:
            raise ValueError(f"t_end must be >= t_start, got {self.t_end}")

    @property
    def omega(self) -> float:
        """Angular speed in rad/s."""
        return 2.0 * math.pi * self.rpm / 60.0

    def params(self) -> np.ndarray:
        """Row of the kernel's mesh table (columns 0..12)."""
        u = np.asarray(self.axis_dir, float)
        u = u / np.linalg.norm(u)
        return np.array(
            [1.0, *np.asarray(self.axis_point, float), *u, self.omega, 0, 0, 0]
            + [self.t_start, self.t_end]
        )

    def to_dict(self) -> dict:
        """JSON-able form."""
        return {"kind": "rotation", **self.__dict__}


@dataclass(frozen=True)
class TranslationMotion:
    """Rigid translation at constant ``velocity`` (m/s) between ``t_start`` and ``t_end``."""

    velocity: tuple[float, float, float]
    t_start: float = 0.0
    t_end: float = math.inf

    def __post_init__(self) -> None:
        if np.asarray(self.velocity, float).shape != (3,):
            raise ValueError(f"velocity must be a 3-vector, got {self.velocity}")
        if not self.t_end >= self.t_start:
            raise ValueError(f"t_end must be >= t_start, got {self.t_end}")

    def params(self) -> np.ndarray:
        """Row of the kernel's mesh table (columns 0..12)."""
        return np.array(
            [2.0, 0, 0, 0, 0, 0, 1, 0, *np.asarray(self.velocity, float)]
            + [self.t_start, self.t_end]
        )

    def to_dict(self) -> dict:
        """JSON-able form."""
        return {"kind": "translation", **self.__dict__}


def motion_from_dict(d: dict | None) -> RotationMotion | TranslationMotion | None:
    """Inverse of ``to_dict``."""
    if d is None:
        return None
    d = dict(d)
    kind = d.pop("kind")
    if kind == "rotation":
        return RotationMotion(
            tuple(d["axis_point"]), tuple(d["axis_dir"]), d["rpm"], d["t_start"], d["t_end"]
        )
    return TranslationMotion(tuple(d["velocity"]), d["t_start"], d["t_end"])
