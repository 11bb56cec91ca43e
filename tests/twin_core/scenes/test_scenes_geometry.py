"""Parametric scene geometry against analytic areas and volumes."""

from __future__ import annotations

import numpy as np
import pytest

from twin_core.dem.stl import read_stl, write_stl
from twin_core.scenes import geometry as g


def test_box_and_blade_volumes():
    """Box volume abc, area 2(ab+bc+ca); a pitched blade keeps volume L W T (rotation)."""
    b = g.box_mesh([0, 0, 0], [0.1, 0.2, 0.3])
    assert b.volume() == pytest.approx(0.006) and b.area() == pytest.approx(0.22)
    for pitch in (0.0, 20.0, -35.0):
        bl = g.blade_mesh([0, 0.01, 0.04], [0, 1, 0], [1, 0, 0], 0.026, 0.012, 0.003, pitch)
        assert bl.volume() == pytest.approx(0.026 * 0.012 * 0.003, rel=1e-9)
    open_box = g.box_mesh([0, 0, 0], [1, 1, 1], omit=("+z",))
    assert open_box.n_triangles == 10
    with pytest.raises(ValueError, match="omit"):
        g.box_mesh([0, 0, 0], [1, 1, 1], omit=("top",))


def test_blade_push_direction():
    """Leading-face normal of a pitched paddle: no axial push at pitch 0, opposite pushes for
    opposite pitch or rotation sense (rigid-body kinematics of an inclined plane)."""
    ax, rad = [1, 0, 0], [0, 1, 0]
    assert g.blade_axial_push(ax, rad, 0.0, 100) == 0
    s = g.blade_axial_push(ax, rad, 20.0, 100)
    assert s in (-1, 1)
    assert g.blade_axial_push(ax, rad, -20.0, 100) == -s
    assert g.blade_axial_push(ax, rad, 20.0, -100) == -s
    # the same for every blade around the shaft
    for ang in np.linspace(0, 2 * np.pi, 7):
        assert g.blade_axial_push(ax, [0, np.cos(ang), np.sin(ang)], 20.0, 100) == s


def test_helicoid_area():
    """Helicoid area per turn: pi [R sqrt(R^2+c^2) - r sqrt(r^2+c^2) + c^2 ln((R + sqrt(R^2+c^2))
    / (r + sqrt(r^2+c^2)))], c = pitch / 2 pi (classical surface integral)."""
    r, Rr, p = 0.005, 0.0125, 0.025
    c = p / (2 * np.pi)
    a = np.pi * (
        Rr * np.hypot(Rr, c)
        - r * np.hypot(r, c)
        + c**2 * np.log((Rr + np.hypot(Rr, c)) / (r + np.hypot(r, c)))
    )
    m = g.helical_flight(0.0, 4 * p, (0.0, 0.0), r, Rr, p, n_per_turn=200, n_radial=16)
    assert m.area() == pytest.approx(4 * a, rel=2e-3)


def test_blender_section_dimensions(tmp_path):
    """Seed Fig. 5.2: 40 x 80 x 80 mm; the trough cross-section is a half disc plus a rectangle
    (area pi R^2 / 2 + 2 R (H - R)), and every mesh lies inside the domain."""
    geo = g.blender_section()
    lo, hi = np.array(geo.info["domain_lo"]), np.array(geo.info["domain_hi"])
    np.testing.assert_allclose(hi - lo, [0.04, 0.08, 0.08])
    for m in geo.all_meshes():
        mlo, mhi = m.bounds()
        assert np.all(mlo >= lo - 1e-9) and np.all(mhi <= hi + 1e-9), m.name
    trough = geo.static[0]
    # area: (half-cylinder polygon perimeter + 2 walls (H - R) + lid W) L
    n_half = 24
    arc = 2 * n_half * 0.04 * np.sin(np.pi / (2 * n_half))
    assert trough.area() == pytest.approx((arc + 2 * 0.04 + 0.08) * 0.04, rel=1e-9)
    path = write_stl(
        tmp_path / "rotor.stl", geo.rotating[0][0].vertices, geo.rotating[0][0].triangles
    )
    v, t = read_stl(path)
    assert len(t) == geo.rotating[0][0].n_triangles


def _rotor_reach(geo) -> float:
    """Largest distance of a rotor vertex from the shaft axis (y = 0, z = R)."""
    v = geo.rotating[0][0].vertices
    return float(np.max(np.hypot(v[:, 1], v[:, 2] - geo.info["radius"])))


def test_blender_blades_reach_the_tip_clearance_unless_shorter():
    """By default the paddles reach to ``tip_clearance`` from the trough (their tip corners, a
    paddle being a pitched plate of finite width, reach a little further out than its
    centreline); a given ``blade_length`` is kept when shorter and capped when longer; a shaft
    and clearance that leave no room raise."""
    R = 0.04
    full = _rotor_reach(g.blender_section())
    assert R - 0.003 - 1e-9 <= full < R  # tips within the clearance of the trough, inside it
    short = _rotor_reach(g.blender_section(blade_length=0.026))
    assert 0.006 + 0.026 - 1e-9 <= short < 0.006 + 0.026 + 0.002  # 8 mm above the bottom
    assert _rotor_reach(g.blender_section(blade_length=0.05)) == pytest.approx(full)
    with pytest.raises(ValueError, match="tip_clearance"):
        g.blender_section(shaft_radius=0.03, tip_clearance=0.011)


def test_drawdown_and_silo():
    """Seed 3.2.2: 224.4 x 51 x 306 mm frame; shelf area (X - w) Y, plate area w Y; silo floor
    annulus (polygon) area n sin(2 pi / n)(R^2 - r0^2) / 2 and plug n sin(2 pi/n) r0^2 / 2."""
    geo = g.drawdown_box(opening_width=0.03)
    frame, shelf = geo.static
    assert frame.volume() == pytest.approx(0.2244 * 0.051 * 0.306)
    assert shelf.area() == pytest.approx((0.2244 - 0.03) * 0.051)
    assert geo.removable[0][0].area() == pytest.approx(0.03 * 0.051)
    n = 48
    s = g.flat_silo(radius=0.03, orifice_diameter=0.018, n_seg=n)
    k = n * np.sin(2 * np.pi / n) / 2
    assert s.static[1].area() == pytest.approx(k * (0.03**2 - 0.009**2))
    assert s.removable[0][0].area() == pytest.approx(k * 0.009**2)
    with pytest.raises(ValueError, match="orifice_diameter"):
        g.flat_silo(radius=0.01, orifice_diameter=0.03)


def test_feeder_geometry():
    """Seed 3.2.3: hopper 20.4 x 20.4 x 26.3 cm; screws inside the trough, impeller clear of
    walls and screws."""
    geo = g.feeder()
    lo, hi = np.array(geo.info["domain_lo"]), np.array(geo.info["domain_hi"])
    assert hi[2] - lo[2] == pytest.approx(0.263)
    assert hi[1] - lo[1] == pytest.approx(0.204)
    assert geo.info["hopper_x"] == pytest.approx(0.204)
    c = geo.info["trough_radius"]
    for mesh, pt, _axis, rpm in geo.rotating[:2]:
        d = np.hypot(mesh.vertices[:, 1] - pt[1], mesh.vertices[:, 2] - pt[2])
        assert d.max() < c and rpm == 100.0
    imp, pt, _, rpm = geo.rotating[2]
    assert rpm == 25.0
    rr = np.hypot(imp.vertices[:, 1], imp.vertices[:, 2] - pt[2])
    assert pt[2] - rr.max() > 0.0125  # clears the screw tops
    assert all(abs(y) <= hi[1] for y in imp.vertices[:, 1])
