"""Configuration of the seed's DEM scenes (one YAML file per run; ``twin dem run SCENE.yaml``).

A scene file holds one of :class:`BlenderScene`, :class:`DrawdownScene`, :class:`FeederScene`,
:class:`SiloScene`, chosen by its ``scene`` field. All quantities are SI (m, s, kg, Pa) unless the
field name says otherwise (``_mm``, ``_rpm``, ``_deg``). Load with :func:`load_scene`.

Seed references: drawdown test 3.2.2, feeder 3.2.3 and 3.3.2, periodic blender section 4.2 and
5.2.1; material parameter ranges Table 3.1.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import Field, TypeAdapter, model_validator

from schemas.base import Fraction, NonNegative, Positive, StrictModel

__all__ = [
    "BlenderGeometry",
    "BlenderScene",
    "DemScene",
    "DrawdownGeometry",
    "DrawdownScene",
    "FeederGeometry",
    "FeederScene",
    "MaterialConfig",
    "OutputConfig",
    "SiloScene",
    "load_scene",
]


class MaterialConfig(StrictModel):
    """Particle and wall material (seed Table 3.1 names in brackets)."""

    density: Positive = Field(1500.0, description="particle density, kg/m^3")
    shear_modulus: Positive = Field(5e6, description="particle shear modulus G, Pa (SM)")
    poisson: float = Field(0.25, ge=0.0, lt=0.5, description="particle Poisson ratio (PR)")
    pp_friction: NonNegative = Field(0.5, description="particle-particle static friction (PP_SF)")
    pp_rolling_friction: NonNegative = Field(0.01, description="PP rolling friction (PP_RF)")
    pp_restitution: Fraction = Field(0.1, description="PP restitution (PP_COR)")
    pw_friction: NonNegative = Field(0.5, description="particle-wall static friction (PW_SF)")
    pw_rolling_friction: NonNegative = Field(0.01, description="PW rolling friction (PW_RF)")
    pw_restitution: Fraction = Field(0.1, description="PW restitution (PW_COR)")
    wall_density: Positive = Field(7800.0, description="wall (steel) density, kg/m^3")
    wall_shear_modulus: Positive = Field(7e10, description="wall (steel) shear modulus, Pa")
    wall_poisson: float = Field(0.3, ge=0.0, lt=0.5, description="wall Poisson ratio")
    walls_of_particle_material: bool = Field(
        False,
        description="walls take the particle's density, shear modulus and Poisson ratio "
        "instead of the wall_* (steel) values (the pw_* coefficients still apply)",
    )
    damping: Literal["tsuji", "corrected"] = Field(
        "tsuji",
        description="restitution -> dashpot mapping: 'tsuji' (beta = ln e / sqrt(ln^2 e + pi^2), "
        "the EDEM/LIGGGHTS form) or the engine's exact Hertz correction",
    )


class OutputConfig(StrictModel):
    """What a run writes besides its results JSON."""

    frame_interval_s: Positive | None = Field(
        None, description="store particle frames at this interval (None: scene default)"
    )
    frame_precision: Literal["float32", "float64"] = "float32"
    checkpoint_interval_s: Positive = Field(1.0, description="simulated time between checkpoints")
    vtk: bool = Field(False, description="write particle .vtp files at each frame (+ .pvd)")
    stl: bool = Field(True, description="write the scene geometry as binary STL")
    figures: bool = Field(True, description="write PNG figures")


class SceneBase(StrictModel):
    name: str = Field("run", min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.\-]+$")
    material: MaterialConfig = Field(default_factory=MaterialConfig)
    radius: Positive = Field(1e-3, description="particle radius, m")
    dt_fraction: float = Field(0.2, gt=0.0, le=0.5, description="time step / Rayleigh time")
    seed: int = Field(0, ge=0, description="random seed (particle placement)")
    output: OutputConfig = Field(default_factory=OutputConfig)


class BlenderGeometry(StrictModel):
    """Periodic section (seed Fig. 5.2)."""

    length: Positive = 0.040
    width: Positive = 0.080
    height: Positive = 0.080
    shaft_radius: Positive = 0.006
    blade_length: Positive | None = Field(
        None,
        description="paddle length from the shaft, m (None: to tip_clearance from the trough)",
    )
    blade_width: Positive = 0.012
    blade_thickness: Positive = 0.003
    tip_clearance: Positive = 0.003
    pitch_deg: float = Field(20.0, ge=-89.0, le=89.0)
    blades_per_station: int = Field(2, ge=1, le=8)
    n_stations: int = Field(2, ge=1, le=8)


class BlenderScene(SceneBase):
    """Periodic blender section (seed 4.2, 5.2.1): two types placed left (y < 0, type 1) and
    right (type 2) of a separating plate, plate removed, blades rotated."""

    scene: Literal["blender"] = "blender"
    geometry: BlenderGeometry = Field(default_factory=BlenderGeometry)
    n_per_type: int = Field(3000, ge=1, description="particles of each type")
    rpms: list[float] = Field([50.0, 75.0, 100.0], min_length=1, description="blade speeds")
    settle_s: NonNegative = Field(0.5, description="settling time with the plate, s")
    mix_s: Positive = Field(20.0, description="mixing time after plate removal, s")
    frame_interval_s: Positive = Field(0.1, description="frames for mixing indices, s")
    sensor_interval_s: Positive = Field(0.005, description="interval of the field sensors, s")
    grid: tuple[int, int, int] = Field((10, 20, 20), description="field grid cells (x, y, z)")
    steady_after_s: NonNegative = Field(
        5.0, description="fields are averaged from this time after plate removal, s"
    )


class DrawdownGeometry(StrictModel):
    size_x: Positive = 0.2244
    size_y: Positive = 0.051
    size_z: Positive = 0.306
    opening_width: Positive = 0.030


class DrawdownScene(SceneBase):
    """Drawdown calibration test (seed 3.2.2): fill the upper compartment, settle, remove the
    plate, run to steady state; responses of Table 3.3."""

    scene: Literal["drawdown"] = "drawdown"
    geometry: DrawdownGeometry = Field(default_factory=DrawdownGeometry)
    n_particles: int = Field(50000, ge=1)
    settle_s: Positive = Field(1.0, description="settling before the plate is removed, s")
    run_s: Positive = Field(10.0, description="time after plate removal, s")
    flow_bin_s: Positive = Field(0.05, description="bin of the opening flow rate, s")
    sensor_interval_s: Positive = Field(0.005, description="interval of the sensors, s")
    frame_interval_s: Positive = Field(0.5, description="frames for snapshots, s")


class FeederGeometry(StrictModel):
    hopper_x: Positive = 0.204
    hopper_y: Positive = 0.204
    height: Positive = 0.263
    screw_radius: Positive = 0.0125
    shaft_radius: Positive = 0.005
    screw_pitch: Positive = 0.025
    clearance: Positive = 0.002
    outlet_length: Positive = 0.060
    wedge_bottom_z: Positive = 0.040
    wedge_top_z: Positive = 0.140
    impeller_z: Positive = 0.070


class FeederScene(SceneBase):
    """Loss-in-weight twin-screw feeder (seed 3.2.3, 3.3.2): fill, run out; optional refills
    of type-2 particles when the fill level falls to the given fractions."""

    scene: Literal["feeder"] = "feeder"
    geometry: FeederGeometry = Field(default_factory=FeederGeometry)
    n_particles: int = Field(150000, ge=1)
    screw_rpm: float = 100.0
    impeller_rpm: float = 25.0
    settle_s: Positive = Field(1.0, description="settling with the screws at rest, s")
    run_s: Positive = Field(20.0, description="run-out time, s")
    refill_levels: list[Fraction] = Field(
        default_factory=list,
        description="refill (type 2) when the hopper mass falls to these fractions of the "
        "initial fill (one run per level; seed 3.3.2.2 used 0.2, 0.4, 0.6, 0.8)",
    )
    refill_particles: int = Field(0, ge=0, description="particles per refill (0: as the fill)")
    flow_bin_s: Positive = Field(0.25, description="bin of the outlet flow rate, s")
    sensor_interval_s: Positive = Field(0.01, description="interval of the sensors, s")
    frame_interval_s: Positive = Field(1.0, description="frames for snapshots, s")


class SiloScene(SceneBase):
    """Flat-bottomed silo discharge for Beverloo's law W = C rho_b sqrt(g) (D0 - k d)^2.5."""

    scene: Literal["silo"] = "silo"
    silo_radius: Positive = 0.03
    silo_height: Positive = 0.15
    orifice_diameter: Positive = 0.018
    n_particles: int = Field(5000, ge=1)
    settle_s: Positive = Field(0.4, description="settling with the plug in place, s")
    discharge_s: Positive = Field(1.0, description="time after the plug is removed, s")
    recycle: bool = Field(
        True, description="re-insert discharged particles at the top (constant head)"
    )
    beverloo_c: Positive = 0.58
    beverloo_k: Positive = 1.5
    flow_bin_s: Positive = Field(0.05, description="bin of the discharge rate, s")
    sensor_interval_s: Positive = Field(0.002, description="interval of the sensors, s")
    frame_interval_s: Positive = Field(0.1, description="frames for snapshots, s")
    fill: Literal["lattice", "poured"] = Field(
        "lattice",
        description="'lattice': particles placed on a lattice in the silo at t = 0; 'poured': "
        "inserted at random in the top quarter of the silo at a constant rate over pour_s",
    )
    pour_s: Positive | None = Field(
        None, description="duration of a poured fill, s (default: half of settle_s)"
    )
    wall: Literal["mesh", "cylinder"] = Field(
        "mesh",
        description="side wall: a triangulated cylinder ('mesh') or the engine's primitive "
        "cylinder wall ('cylinder', exact circle)",
    )
    fit_window_s: tuple[NonNegative, Positive] | None = Field(
        None,
        description="(start, end) of the discharge-rate fit, s after the plug is removed "
        "(default: the last 70 % of discharge_s)",
    )

    @model_validator(mode="after")
    def _windows_fit(self) -> SiloScene:
        if self.fit_window_s is not None:
            a, b = self.fit_window_s
            if not a < b <= self.discharge_s:
                raise ValueError(
                    f"fit_window_s must satisfy start < end <= discharge_s = {self.discharge_s}, "
                    f"got {self.fit_window_s}"
                )
        if self.pour_s is not None and self.pour_s > self.settle_s:
            raise ValueError(f"pour_s must be <= settle_s = {self.settle_s}, got {self.pour_s}")
        return self


DemScene = Annotated[
    BlenderScene | DrawdownScene | FeederScene | SiloScene, Field(discriminator="scene")
]
_ADAPTER: TypeAdapter = TypeAdapter(DemScene)


def load_scene(source: str | Path | dict) -> BlenderScene | DrawdownScene | FeederScene | SiloScene:
    """Validate a scene from a YAML file path or a dict (``scene`` selects the kind)."""
    if isinstance(source, dict):
        data = source
    else:
        path = Path(source)
        if not path.exists():
            raise ValueError(f"scene file does not exist: {path}")
        data = yaml.safe_load(path.read_text())
        if not isinstance(data, dict):
            raise ValueError(f"scene file must hold a mapping, got {type(data).__name__}")
    return _ADAPTER.validate_python(data)
