"""Discrete element method (DEM) engine: Hertz-Mindlin spheres in numba.

Public API: :class:`Simulation`, :class:`Material`, :class:`MaterialTable`,
:class:`RotationMotion`, :class:`TranslationMotion`, :class:`ParticleFactory`,
:class:`BoxRegion`, :class:`CylinderRegion` and the time-step helpers.
"""

from .insertion import BoxRegion, CylinderRegion, ParticleFactory
from .materials import (
    Material,
    MaterialTable,
    damping_coefficient,
    hertz_contact_time,
    rayleigh_time,
    restitution_from_damping,
)
from .motion import RotationMotion, TranslationMotion
from .simulation import Simulation

__all__ = [
    "BoxRegion",
    "CylinderRegion",
    "Material",
    "MaterialTable",
    "ParticleFactory",
    "RotationMotion",
    "Simulation",
    "TranslationMotion",
    "damping_coefficient",
    "hertz_contact_time",
    "rayleigh_time",
    "restitution_from_damping",
]
