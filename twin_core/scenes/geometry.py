"""Parametric triangle-mesh geometry of the seed's DEM scenes (no CAD files needed).

Every generator returns :class:`TriMesh` objects (vertices in metres, triangles as vertex
indices) that the DEM engine takes through ``Simulation.add_mesh`` and that
:func:`twin_core.dem.stl.write_stl` exports for viewing. Closed primitives (boxes,
capped cylinders, blades) are oriented with outward normals so that :meth:`TriMesh.volume`
(divergence theorem, V = sum_f v0 . (v1 x v2) / 6) gives their enclosed volume.

Scenes (seed, dissertation sections in brackets):

* :func:`blender_section` - periodic section of a convective continuous blender
  (4.2, 5.2.1, Figs. 4.2/5.2): 40 x 80 x 80 mm box, x periodic, U-shaped trough, central
  shaft, paddle blades in an alternating configuration with a pitch angle.
* :func:`drawdown_box` - drawdown calibration test (3.2.2): 224.4 x 51 x 306 mm frame, upper
  and lower compartment, central opening closed by a removable plate.
* :func:`feeder` - loss-in-weight twin-screw feeder (3.2.3): 20.4 x 20.4 x 26.3 cm wedge
  hopper, twin screws with pitch and flight, bridge-breaking impeller, outlet.
* :func:`flat_silo` - flat-bottomed cylindrical silo with a circular orifice (Beverloo).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "TriMesh",
    "blade_mesh",
    "blender_section",
    "box_mesh",
    "cylinder_mesh",
    "drawdown_box",
    "extrude_profile",
    "feeder",
    "flat_silo",
    "helical_flight",
    "merge",
    "rectangle",
    "rotation_matrix",
]


@dataclass
class TriMesh:
    """Indexed triangle mesh (SI units)."""

    vertices: np.ndarray
    triangles: np.ndarray
    name: str = "mesh"

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=float).reshape(-1, 3)
        self.triangles = np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3)

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    def corners(self) -> np.ndarray:
        """(m, 3, 3) corner coordinates of each triangle."""
        return self.vertices[self.triangles]

    def area(self) -> float:
        """Total surface area, sum of |(v1 - v0) x (v2 - v0)| / 2 over triangles."""
        c = self.corners()
        return float(
            0.5 * np.linalg.norm(np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), axis=1).sum()
        )

    def volume(self) -> float:
        """Signed enclosed volume by the divergence theorem, sum v0 . (v1 x v2) / 6.

        Exact for a closed, consistently outward-oriented mesh (positive).
        """
        c = self.corners()
        return float(np.einsum("ij,ij->i", c[:, 0], np.cross(c[:, 1], c[:, 2])).sum() / 6.0)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def translated(self, offset: np.ndarray) -> TriMesh:
        return TriMesh(self.vertices + np.asarray(offset, float), self.triangles.copy(), self.name)

    def rotated(self, matrix: np.ndarray, origin: np.ndarray | None = None) -> TriMesh:
        o = np.zeros(3) if origin is None else np.asarray(origin, float)
        v = (self.vertices - o) @ np.asarray(matrix, float).T + o
        return TriMesh(v, self.triangles.copy(), self.name)

    def flipped(self) -> TriMesh:
        """Same surface with reversed orientation (normals point the other way)."""
        return TriMesh(self.vertices.copy(), self.triangles[:, ::-1].copy(), self.name)


def merge(meshes: list[TriMesh], name: str = "mesh") -> TriMesh:
    """Concatenate meshes into one (no vertex welding)."""
    verts, tris, off = [], [], 0
    for m in meshes:
        verts.append(m.vertices)
        tris.append(m.triangles + off)
        off += len(m.vertices)
    if not verts:
        return TriMesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), name)
    return TriMesh(np.vstack(verts), np.vstack(tris), name)


def rotation_matrix(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues rotation matrix R = I + sin(a) K + (1 - cos(a)) K^2 about unit ``axis``."""
    a = np.asarray(axis, float)
    n = np.linalg.norm(a)
    if n == 0:
        raise ValueError("axis must be non-zero")
    x, y, z = a / n
    k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * (k @ k)


def rectangle(corner: np.ndarray, u: np.ndarray, v: np.ndarray, name: str = "rect") -> TriMesh:
    """Planar quad corner, corner+u, corner+u+v, corner+v (normal along u x v)."""
    c = np.asarray(corner, float)
    u = np.asarray(u, float)
    v = np.asarray(v, float)
    return TriMesh(np.array([c, c + u, c + u + v, c + v]), [[0, 1, 2], [0, 2, 3]], name)


_BOX_FACES = {
    "-x": ([0, 4, 7, 3]),
    "+x": ([1, 2, 6, 5]),
    "-y": ([0, 1, 5, 4]),
    "+y": ([3, 7, 6, 2]),
    "-z": ([0, 3, 2, 1]),
    "+z": ([4, 5, 6, 7]),
}


def box_mesh(
    lo: np.ndarray, hi: np.ndarray, *, omit: tuple[str, ...] = (), name: str = "box"
) -> TriMesh:
    """Axis-aligned box [lo, hi] with outward normals; faces in ``omit`` ("-x", "+z", ...) left open."""
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    if np.any(hi <= lo):
        raise ValueError(f"box hi must exceed lo, got lo={lo.tolist()}, hi={hi.tolist()}")
    for f in omit:
        if f not in _BOX_FACES:
            raise ValueError(f"omit entries must be one of {sorted(_BOX_FACES)}, got {f!r}")
    v = np.array(
        [
            [lo[0], lo[1], lo[2]],
            [hi[0], lo[1], lo[2]],
            [hi[0], hi[1], lo[2]],
            [lo[0], hi[1], lo[2]],
            [lo[0], lo[1], hi[2]],
            [hi[0], lo[1], hi[2]],
            [hi[0], hi[1], hi[2]],
            [lo[0], hi[1], hi[2]],
        ]
    )
    tris = []
    for face, (a, b, c, d) in _BOX_FACES.items():
        if face in omit:
            continue
        tris += [[a, b, c], [a, c, d]]
    return TriMesh(v, np.array(tris, dtype=np.int64).reshape(-1, 3), name)


def cylinder_mesh(
    p0: np.ndarray,
    axis: np.ndarray,
    radius: float,
    length: float,
    *,
    n_seg: int = 32,
    caps: bool = True,
    name: str = "cylinder",
) -> TriMesh:
    """Cylinder of ``radius`` from ``p0`` along unit ``axis`` for ``length``; outward normals.

    The lateral surface is an inscribed ``n_seg``-gon prism (area 2 n r sin(pi/n) L, volume
    n r^2 sin(2 pi/n) L / 2).
    """
    if radius <= 0 or length <= 0:
        raise ValueError(f"radius and length must be > 0, got {radius}, {length}")
    if n_seg < 3:
        raise ValueError(f"n_seg must be >= 3, got {n_seg}")
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    e1 = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    th = 2 * np.pi * np.arange(n_seg) / n_seg
    ring = radius * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)
    p0 = np.asarray(p0, float)
    v = np.vstack([p0 + ring, p0 + a * length + ring, [p0, p0 + a * length]])
    tris = []
    for i in range(n_seg):
        j = (i + 1) % n_seg
        tris += [[i, j, n_seg + j], [i, n_seg + j, n_seg + i]]
        if caps:
            tris += [[2 * n_seg, j, i], [2 * n_seg + 1, n_seg + i, n_seg + j]]
    return TriMesh(v, tris, name)


def extrude_profile(
    profile_yz: np.ndarray, x0: float, x1: float, *, name: str = "extrusion"
) -> TriMesh:
    """Sweep an open polyline in the (y, z) plane along x from ``x0`` to ``x1`` (a ruled wall)."""
    p = np.asarray(profile_yz, float)
    n = len(p)
    if n < 2:
        raise ValueError(f"profile needs >= 2 points, got {n}")
    v = np.vstack([np.c_[np.full(n, x0), p], np.c_[np.full(n, x1), p]])
    tris = []
    for i in range(n - 1):
        tris += [[i, i + 1, n + i + 1], [i, n + i + 1, n + i]]
    return TriMesh(v, tris, name)


def _arc(cy: float, cz: float, r: float, a0: float, a1: float, n: int) -> np.ndarray:
    a = np.linspace(a0, a1, n + 1)
    return np.c_[cy + r * np.cos(a), cz + r * np.sin(a)]


def blade_mesh(
    center: np.ndarray,
    radial: np.ndarray,
    axial: np.ndarray,
    length: float,
    width: float,
    thickness: float,
    pitch_deg: float,
    *,
    name: str = "blade",
) -> TriMesh:
    """Paddle blade: a thin box ``length`` (radial) x ``width`` x ``thickness`` centred at
    ``center``, whose face plane contains the radial direction and is turned by ``pitch_deg``
    about it away from the axial-radial plane (pitch 0 = flat paddle containing the axis,
    pitch 90 = disc-like, perpendicular to the axis)."""
    r = np.asarray(radial, float)
    r /= np.linalg.norm(r)
    ax = np.asarray(axial, float)
    ax = ax - ax.dot(r) * r
    ax /= np.linalg.norm(ax)
    tang = np.cross(ax, r)
    phi = np.deg2rad(pitch_deg)
    w_dir = np.cos(phi) * ax + np.sin(phi) * tang  # along the blade width
    n_dir = np.cross(r, w_dir)  # blade face normal
    base = box_mesh([-0.5, -0.5, -0.5], [0.5, 0.5, 0.5], name=name)
    m = np.c_[r * length, w_dir * width, n_dir * thickness]  # columns: local x, y, z
    v = base.vertices @ m.T + np.asarray(center, float)
    tris = base.triangles if np.linalg.det(m) > 0 else base.triangles[:, ::-1]
    return TriMesh(v, tris, name)


def blade_axial_push(axis: np.ndarray, radial: np.ndarray, pitch_deg: float, rpm: float) -> float:
    """Sign (+1, -1, 0) of the axial component of the leading-face normal of a blade built by
    :func:`blade_mesh` rotating at ``rpm`` (right-hand rule about ``axis``): the direction in
    which the blade pushes particles along the axis (frictionless contact force is normal)."""
    ax = np.asarray(axis, float) / np.linalg.norm(axis)
    r = np.asarray(radial, float) / np.linalg.norm(radial)
    tang = np.cross(ax, r)
    phi = np.deg2rad(pitch_deg)
    w_dir = np.cos(phi) * ax + np.sin(phi) * tang
    n_dir = np.cross(r, w_dir)
    lead = n_dir if n_dir.dot(tang) * rpm > 0 else -n_dir
    return float(np.sign(np.round(lead.dot(ax), 12)))


@dataclass
class SceneGeometry:
    """Meshes of a scene with their roles; ``info`` holds derived dimensions (m)."""

    static: list[TriMesh] = field(default_factory=list)
    rotating: list[tuple[TriMesh, np.ndarray, np.ndarray, float]] = field(default_factory=list)
    removable: list[tuple[TriMesh, float]] = field(default_factory=list)
    info: dict = field(default_factory=dict)

    def all_meshes(self) -> list[TriMesh]:
        return self.static + [m for m, *_ in self.rotating] + [m for m, _ in self.removable]


def blender_section(
    length: float = 0.040,
    width: float = 0.080,
    height: float = 0.080,
    shaft_radius: float = 0.006,
    blade_length: float | None = None,
    blade_width: float = 0.012,
    blade_thickness: float = 0.003,
    tip_clearance: float = 0.003,
    pitch_deg: float = 20.0,
    blades_per_station: int = 2,
    n_stations: int = 2,
    rpm: float = 100.0,
    n_seg: int = 48,
) -> SceneGeometry:
    """Periodic section of a convective continuous blender (seed 4.2, 5.2.1, Figs 4.2/5.2).

    Domain x in [0, length] (periodic), y in [-width/2, width/2], z in [0, height]; the U-shaped
    trough is a half cylinder of radius width/2 about the axis (y=0, z=width/2) with vertical
    walls above it and a lid at z = height (the closed housing), open at the x ends. The shaft lies on the axis; ``n_stations`` blade
    stations are evenly spaced along x, each with ``blades_per_station`` paddles, and
    successive stations turned by 180/blades_per_station degrees (alternating configuration).
    Blades extend from the shaft to ``width/2 - tip_clearance`` (``blade_length`` None), or for
    ``blade_length``, capped there. Shorter blades leave an annulus between their tips and the
    trough that they never sweep: with 26 mm blades (the default before) the tips passed 8 mm
    (four 1 mm-particle diameters) above the trough bottom, and 36-42 % of the seed-size
    section's particles lay still in that annulus (docs/compartment.md).
    """
    R = width / 2
    zc = R
    if height < R:
        raise ValueError(f"height must be >= width/2, got {height}")
    reach = R - tip_clearance - shaft_radius
    if reach <= 0:
        raise ValueError(
            f"shaft_radius + tip_clearance must be < width/2, got {shaft_radius + tip_clearance}"
        )
    if blade_length is None or blade_length > reach:
        blade_length = reach
    prof = np.vstack(
        [[[-R, height]], _arc(0.0, zc, R, np.pi, 2 * np.pi, n_seg // 2), [[R, height]]]
    )
    trough = merge(
        [
            extrude_profile(prof, 0.0, length),
            rectangle([0.0, -R, height], [length, 0.0, 0.0], [0.0, width, 0.0]),
        ],
        name="trough",
    )
    axis_pt = np.array([0.0, 0.0, zc])
    axis = np.array([1.0, 0.0, 0.0])
    shaft = cylinder_mesh(
        [0.0, 0.0, zc], axis, shaft_radius, length, n_seg=16, caps=False, name="shaft"
    )
    blades = []
    dx = length / n_stations
    r_c = shaft_radius + blade_length / 2
    for s in range(n_stations):
        x = (s + 0.5) * dx
        for b in range(blades_per_station):
            ang = 2 * np.pi * b / blades_per_station + s * np.pi / blades_per_station
            radial = np.array([0.0, np.cos(ang), np.sin(ang)])
            blades.append(
                blade_mesh(
                    axis_pt + [x, 0, 0] + r_c * radial,
                    radial,
                    axis,
                    blade_length,
                    blade_width,
                    blade_thickness,
                    pitch_deg,
                    name=f"blade_{s}_{b}",
                )
            )
    rotor = merge([shaft, *blades], name="rotor")
    push = blade_axial_push(axis, [0.0, 1.0, 0.0], pitch_deg, rpm)
    geo = SceneGeometry(static=[trough], rotating=[(rotor, axis_pt, axis, rpm)])
    geo.info = {
        "domain_lo": [0.0, -R, 0.0],
        "domain_hi": [length, R, height],
        "axis_point": axis_pt.tolist(),
        "radius": R,
        "blade_push_sign_x": push,
        "trough_volume": length * (np.pi * R**2 / 2 + 2 * R * (height - zc)),
    }
    return geo


def drawdown_box(
    size_x: float = 0.2244,
    size_y: float = 0.051,
    size_z: float = 0.306,
    opening_width: float = 0.030,
    shelf_height: float | None = None,
    plate_remove_s: float = 1.0,
) -> SceneGeometry:
    """Drawdown test frame (seed 3.2.2, Fig. 3.2): a closed box x [0, size_x], y [0, size_y],
    z [0, size_z] split at ``shelf_height`` (default mid-height) by a horizontal shelf with a
    central slot of ``opening_width`` along x (through the full depth y); a plate covering the
    slot is active until ``plate_remove_s``.

    The seed gives the frame size only; the slot width is a parameter (default 30 mm).
    """
    if not 0 < opening_width < size_x:
        raise ValueError(f"opening_width must be in (0, size_x), got {opening_width}")
    zs = size_z / 2 if shelf_height is None else shelf_height
    frame = box_mesh([0, 0, 0], [size_x, size_y, size_z], name="frame")
    a0 = size_x / 2 - opening_width / 2
    a1 = size_x / 2 + opening_width / 2
    shelf = merge(
        [
            rectangle([0, 0, zs], [a0, 0, 0], [0, size_y, 0]),
            rectangle([a1, 0, zs], [size_x - a1, 0, 0], [0, size_y, 0]),
        ],
        name="shelf",
    )
    plate = rectangle([a0, 0, zs], [a1 - a0, 0, 0], [0, size_y, 0], name="plate")
    geo = SceneGeometry(static=[frame, shelf], removable=[(plate, plate_remove_s)])
    geo.info = {
        "domain_lo": [0.0, 0.0, 0.0],
        "domain_hi": [size_x, size_y, size_z],
        "shelf_z": zs,
        "opening": [a0, a1],
    }
    return geo


def helical_flight(
    x0: float,
    length: float,
    axis_yz: tuple[float, float],
    inner_radius: float,
    outer_radius: float,
    pitch: float,
    *,
    handedness: int = -1,
    phase: float = 0.0,
    n_per_turn: int = 24,
    n_radial: int = 1,
    name: str = "flight",
) -> TriMesh:
    """Helicoid ribbon (screw flight) between ``inner_radius`` and ``outer_radius`` around the
    axis parallel to x through (y, z) = ``axis_yz``: points (x0 + s, r cos th, r sin th) with
    th = phase + handedness * 2 pi s / pitch. Area per turn (analytic):
    pi [R sqrt(R^2 + c^2) - r sqrt(r^2 + c^2) + c^2 ln((R + sqrt(R^2 + c^2)) / (r + ...))],
    c = pitch / (2 pi)."""
    if not 0 <= inner_radius < outer_radius:
        raise ValueError(
            f"need 0 <= inner_radius < outer_radius, got {inner_radius}, {outer_radius}"
        )
    if pitch <= 0:
        raise ValueError(f"pitch must be > 0, got {pitch}")
    if n_radial < 1:
        raise ValueError(f"n_radial must be >= 1, got {n_radial}")
    n = max(2, int(np.ceil(length / pitch * n_per_turn)) + 1)
    s = np.linspace(0.0, length, n)
    th = phase + handedness * 2 * np.pi * s / pitch
    yc, zc = axis_yz
    rings = []
    for r in np.linspace(inner_radius, outer_radius, n_radial + 1):
        rings.append(np.c_[x0 + s, yc + r * np.cos(th), zc + r * np.sin(th)])
    v = np.vstack(rings)
    tris = []
    for k in range(n_radial):
        o0, o1 = k * n, (k + 1) * n
        for i in range(n - 1):
            tris += [[o0 + i, o0 + i + 1, o1 + i + 1], [o0 + i, o1 + i + 1, o1 + i]]
    return TriMesh(v, tris, name)


def feeder(
    hopper_x: float = 0.204,
    hopper_y: float = 0.204,
    height: float = 0.263,
    screw_radius: float = 0.0125,
    shaft_radius: float = 0.005,
    screw_pitch: float = 0.025,
    clearance: float = 0.002,
    outlet_length: float = 0.060,
    wedge_bottom_z: float = 0.040,
    wedge_top_z: float = 0.140,
    screw_rpm: float = 100.0,
    impeller_rpm: float = 25.0,
    impeller_z: float = 0.070,
    impeller_arms: int = 4,
    impeller_stations: int = 3,
    n_seg: int = 24,
) -> SceneGeometry:
    """Loss-in-weight twin-screw feeder (seed 3.2.3, Fig. 3.3).

    Coordinates: screws along x, axes at (y, z) = (+-c, 0) with c = screw_radius + clearance,
    twin U trough (two half cylinders of radius c meeting at y = 0) below; vertical walls up to
    ``wedge_bottom_z``, a wedge hopper opening to ``hopper_y`` at ``wedge_top_z`` and vertical
    walls to the top (overall height ``height`` from the trough bottom z = -c). The hopper
    spans x in [0, hopper_x]; the trough and screws continue as the outlet barrel to
    x = hopper_x + outlet_length (lid at z = c), open at its end. The screws are helical flights
    on shafts (handedness chosen so positive rpm conveys to +x, see :func:`helical_flight`);
    the bridge-breaking impeller is a shaft along x at ``impeller_z`` with radial arms.
    """
    c = screw_radius + clearance
    z_bot = -c
    z_top = z_bot + height
    if not 0 < wedge_bottom_z < wedge_top_z < z_top:
        raise ValueError(
            f"need 0 < wedge_bottom_z < wedge_top_z < top ({z_top:.4f}), got "
            f"{wedge_bottom_z}, {wedge_top_z}"
        )
    half = hopper_y / 2
    if half <= 2 * c:
        raise ValueError(f"hopper_y must exceed 4 (screw_radius + clearance), got {hopper_y}")
    x_end = hopper_x + outlet_length
    left = _arc(-c, 0.0, c, np.pi, 2 * np.pi, n_seg // 2)
    right = _arc(c, 0.0, c, np.pi, 2 * np.pi, n_seg // 2)
    trough_prof = np.vstack([left, right[1:]])  # from (-2c, 0) to (2c, 0) through the cusp
    side_l = np.array([[-half, z_top], [-half, wedge_top_z], [-2 * c, wedge_bottom_z], [-2 * c, 0]])
    side_r = np.array([[2 * c, 0], [2 * c, wedge_bottom_z], [half, wedge_top_z], [half, z_top]])
    hopper_prof = np.vstack([side_l, trough_prof[1:-1], side_r])
    walls = extrude_profile(hopper_prof, 0.0, hopper_x, name="hopper")
    barrel = merge(
        [
            extrude_profile(trough_prof, hopper_x, x_end),
            extrude_profile(np.array([[-2 * c, c], [-2 * c, 0.0]]), hopper_x, x_end),
            extrude_profile(np.array([[2 * c, 0.0], [2 * c, c]]), hopper_x, x_end),
            rectangle([hopper_x, -2 * c, c], [outlet_length, 0, 0], [0, 4 * c, 0]),
        ],
        name="barrel",
    )
    end0 = rectangle([0, -half, z_bot], [0, 2 * half, 0], [0, 0, height], name="end_wall_0")
    end1 = rectangle([hopper_x, -half, c], [0, 2 * half, 0], [0, 0, z_top - c], name="end_wall_1")
    end1b = merge(
        [
            rectangle([hopper_x, -half, z_bot], [0, half - 2 * c, 0], [0, 0, c - z_bot]),
            rectangle([hopper_x, 2 * c, z_bot], [0, half - 2 * c, 0], [0, 0, c - z_bot]),
        ],
        name="end_wall_1_sides",
    )
    axis = np.array([1.0, 0.0, 0.0])
    screws = []
    for k, yc in enumerate((-c, c)):
        shaft = cylinder_mesh([0, yc, 0], axis, shaft_radius, x_end, n_seg=12, caps=False)
        flight = helical_flight(
            0.0,
            x_end,
            (yc, 0.0),
            shaft_radius,
            screw_radius,
            screw_pitch,
            handedness=-1,
            phase=k * np.pi,
        )
        screws.append(
            (merge([shaft, flight], name=f"screw_{k}"), np.array([0, yc, 0.0]), axis, screw_rpm)
        )
    # impeller: the swept circle of the arms must clear the hopper walls and the screws
    tip = min(
        _distance_to_polyline(np.array([0.0, impeller_z]), hopper_prof), impeller_z - screw_radius
    )
    arm_len = tip - 0.003 - 0.004
    if arm_len <= 0.005:
        raise ValueError(f"impeller_z={impeller_z} leaves no room for impeller arms")
    imp_parts = [cylinder_mesh([0, 0, impeller_z], axis, 0.004, hopper_x, n_seg=12, caps=False)]
    for s in range(impeller_stations):
        x = (s + 0.5) * hopper_x / impeller_stations
        for b in range(impeller_arms):
            ang = 2 * np.pi * b / impeller_arms + s * np.pi / impeller_arms
            radial = np.array([0.0, np.cos(ang), np.sin(ang)])
            imp_parts.append(
                blade_mesh(
                    [x, 0, impeller_z] + (0.004 + arm_len / 2) * radial,
                    radial,
                    axis,
                    arm_len,
                    0.010,
                    0.003,
                    0.0,
                )
            )
    impeller = merge(imp_parts, name="impeller")
    geo = SceneGeometry(
        static=[walls, barrel, end0, end1, end1b],
        rotating=[*screws, (impeller, np.array([0, 0, impeller_z]), axis, impeller_rpm)],
    )
    geo.info = {
        "domain_lo": [0.0, -half, z_bot],
        "domain_hi": [x_end, half, z_top],
        "hopper_x": hopper_x,
        "outlet_x": x_end,
        "screw_axes_y": [-c, c],
        "trough_radius": c,
        "impeller_z": impeller_z,
        "wedge": [wedge_bottom_z, wedge_top_z],
        "z_top": z_top,
    }
    return geo


def _distance_to_polyline(p: np.ndarray, poly: np.ndarray) -> float:
    a = poly[:-1]
    b = poly[1:]
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.einsum("ij,ij->i", ab, ab), 0, 1)
    d = np.linalg.norm(a + t[:, None] * ab - p, axis=1)
    return float(d.min())


def hopper_half_width(z: np.ndarray | float, info: dict) -> np.ndarray:
    """Half width (y) of the feeder hopper cross-section at height z (above the trough)."""
    zb, zt = info["wedge"]
    c = info["trough_radius"]
    half = (info["domain_hi"][1] - info["domain_lo"][1]) / 2
    z = np.asarray(z, float)
    f = np.clip((z - zb) / (zt - zb), 0, 1)
    return 2 * c + f * (half - 2 * c)


def flat_silo(
    radius: float = 0.03,
    height: float = 0.12,
    orifice_diameter: float = 0.018,
    plug_remove_s: float = 0.2,
    n_seg: int = 48,
) -> SceneGeometry:
    """Flat-bottomed cylindrical silo (axis z, bottom at z = 0) with a central circular orifice
    closed by a plug removed at ``plug_remove_s`` (Beverloo discharge validation)."""
    if not 0 < orifice_diameter < 2 * radius:
        raise ValueError(f"orifice_diameter must be in (0, 2 radius), got {orifice_diameter}")
    wall = cylinder_mesh([0, 0, 0], [0, 0, 1], radius, height, n_seg=n_seg, caps=False, name="wall")
    r0 = orifice_diameter / 2
    th = 2 * np.pi * np.arange(n_seg) / n_seg
    inner = np.c_[r0 * np.cos(th), r0 * np.sin(th), np.zeros(n_seg)]
    outer = np.c_[radius * np.cos(th), radius * np.sin(th), np.zeros(n_seg)]
    v = np.vstack([inner, outer])
    tris = []
    for i in range(n_seg):
        j = (i + 1) % n_seg
        tris += [[i, n_seg + j, j], [i, n_seg + i, n_seg + j]]
    bottom = TriMesh(v, tris, name="bottom")
    pv = np.vstack([inner, [[0, 0, 0]]])
    plug = TriMesh(pv, [[n_seg, (i + 1) % n_seg, i] for i in range(n_seg)], name="plug")
    geo = SceneGeometry(static=[wall, bottom], removable=[(plug, plug_remove_s)])
    geo.info = {
        "domain_lo": [-radius, -radius, 0.0],
        "domain_hi": [radius, radius, height],
        "orifice_diameter": orifice_diameter,
        # inscribed polygon: effective orifice diameter of equal area
        "orifice_diameter_eff": orifice_diameter
        * np.sqrt(n_seg * np.sin(2 * np.pi / n_seg) / (2 * np.pi)),
    }
    return geo
