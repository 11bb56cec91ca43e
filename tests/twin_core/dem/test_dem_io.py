"""STL, frames and VTK I/O of the DEM package (round trips and analytic mesh measures)."""

from __future__ import annotations

import numpy as np
import pytest

from twin_core.dem.frames import Frame, FrameReader, FrameWriter
from twin_core.dem.stl import facet_normals, read_stl, write_stl
from twin_core.scenes.geometry import box_mesh, cylinder_mesh, helical_flight


@pytest.mark.parametrize("binary", [True, False])
def test_stl_round_trip_box(tmp_path, binary):
    """A box written and read back keeps its 8 vertices, 12 triangles, area 2(ab+bc+ca) and
    volume abc (analytic)."""
    box = box_mesh([0.0, 0.0, 0.0], [0.1, 0.2, 0.3])
    path = write_stl(tmp_path / "box.stl", box.vertices, box.triangles, binary=binary)
    v, t = read_stl(path)
    assert v.shape == (8, 3) and t.shape == (12, 3)
    from twin_core.scenes.geometry import TriMesh

    m = TriMesh(v, t)
    assert m.area() == pytest.approx(2 * (0.02 + 0.06 + 0.03), rel=1e-6)
    assert m.volume() == pytest.approx(0.006, rel=1e-6)
    # normals survive: outward on every face
    n = facet_normals(v, t)
    centre = v.mean(axis=0)
    tri_c = v[t].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", n, tri_c - centre) > 0)


def test_stl_binary_and_ascii_agree(tmp_path):
    """Both encodings of a helicoid give the same triangles (float32 precision)."""
    m = helical_flight(0.0, 0.05, (0.0, 0.0), 0.005, 0.0125, 0.025)
    write_stl(tmp_path / "a.stl", m.vertices, m.triangles, binary=False, name="flight")
    write_stl(tmp_path / "b.stl", m.vertices, m.triangles, binary=True)
    va, ta = read_stl(tmp_path / "a.stl")
    vb, tb = read_stl(tmp_path / "b.stl", merge_decimals=6)
    assert len(ta) == len(tb) == m.n_triangles
    np.testing.assert_allclose(va[ta], m.vertices[m.triangles], atol=1e-9)
    np.testing.assert_allclose(vb[tb], m.vertices[m.triangles], atol=1e-7)


def test_stl_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="triangles"):
        write_stl(tmp_path / "x.stl", np.zeros((3, 3)), np.array([[0, 1, 5]]))
    (tmp_path / "bad.stl").write_bytes(b"\0" * 80 + np.uint32(10).tobytes() + b"\0" * 20)
    with pytest.raises(ValueError, match="truncated"):
        read_stl(tmp_path / "bad.stl")


def _frame(t: float, n: int, rng: np.random.Generator) -> Frame:
    return Frame(
        t,
        np.arange(n) + 7,
        rng.integers(1, 3, n),
        np.full(n, 1e-3),
        rng.random((n, 3)),
        rng.normal(size=(n, 3)),
    )


def test_frames_round_trip_and_chunks(tmp_path):
    """120 frames of varying particle number in chunks of 50: 3 chunk files, every array back
    exactly in float64 mode."""
    rng = np.random.default_rng(1)
    frames = [_frame(0.01 * i, 50 + (i % 7), rng) for i in range(120)]
    with FrameWriter(
        tmp_path / "f", chunk_frames=50, precision="float64", meta={"scene": "x"}
    ) as w:
        for f in frames:
            w.append(f)
    r = FrameReader(tmp_path / "f")
    assert len(r) == 120 and len(r.chunks) == 3 and r.meta == {"scene": "x"}
    np.testing.assert_allclose(r.times, [f.t for f in frames])
    for i in (0, 49, 50, 119, -1):
        a, b = r[i], frames[i]
        assert a.t == b.t
        for k in ("ids", "types", "radii", "positions", "velocities"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    assert sum(1 for _ in r) == 120
    assert r.nearest(0.333).t == pytest.approx(0.33)


def test_frames_float32_interval_and_resume(tmp_path):
    """float32 storage keeps 1e-7 relative precision; the interval filter drops close frames;
    resuming at t truncates later frames and continues."""
    rng = np.random.default_rng(2)
    w = FrameWriter(tmp_path / "f", chunk_frames=4, interval_s=0.1)
    stored = [w.append(_frame(0.05 * i, 10, rng)) for i in range(20)]
    w.close()
    assert sum(stored) == 10
    r = FrameReader(tmp_path / "f")
    assert len(r) == 10
    f = _frame(0.0, 10, np.random.default_rng(2))
    np.testing.assert_allclose(r[0].positions, f.positions, rtol=1e-6)
    w2 = FrameWriter(tmp_path / "f", chunk_frames=4, resume=True, resume_t=0.55)
    assert len(FrameReader(tmp_path / "f")) == 6  # t = 0.0 ... 0.5
    w2.append(_frame(0.6, 12, rng))
    w2.close()
    r = FrameReader(tmp_path / "f")
    assert len(r) == 7 and r[-1].n == 12
    with pytest.raises(ValueError, match="backwards"):
        FrameWriter(tmp_path / "f", resume=True).append(_frame(0.1, 3, rng))


def test_cylinder_measures():
    """Capped n-gon prism: volume n r^2 sin(2pi/n) L / 2 and area (analytic)."""
    n, r, L = 40, 0.02, 0.1
    c = cylinder_mesh([0, 0, 0], [0.3, 0.2, 1.0], r, L, n_seg=n)
    assert c.volume() == pytest.approx(n * r**2 * np.sin(2 * np.pi / n) * L / 2, rel=1e-10)
    side = 2 * n * r * np.sin(np.pi / n) * L
    caps = n * r**2 * np.sin(2 * np.pi / n)
    assert c.area() == pytest.approx(side + caps, rel=1e-10)


def _parse_vtp_array(text: str, name: str) -> np.ndarray:
    import base64
    import re

    m = re.search(
        rf'type="(\w+)" Name="{name}" NumberOfComponents="(\d)" format="binary">([^<]+)<', text
    )
    assert m, name
    raw = base64.b64decode(m.group(3))
    n = int(np.frombuffer(raw[:4], "<u4")[0])
    dt = {"Float64": "<f8", "Int64": "<i8"}[m.group(1)]
    return np.frombuffer(raw[4 : 4 + n], dt).reshape(-1, int(m.group(2))).squeeze()


def test_vtk_particles_and_mesh(tmp_path):
    """Legacy and XML VTK files carry the particle arrays back exactly (parsed here from the
    format definition in the VTK User's Guide)."""
    from twin_core.dem.vtk import (
        write_mesh_vtk,
        write_mesh_vtp,
        write_particles_vtk,
        write_particles_vtp,
        write_pvd,
    )

    f = _frame(0.5, 9, np.random.default_rng(3))
    p = write_particles_vtk(tmp_path / "p.vtk", f, binary=False)
    lines = p.read_text().splitlines()
    assert lines[3] == "DATASET POLYDATA" and lines[4] == "POINTS 9 double"
    pts = np.array([list(map(float, s.split())) for s in lines[5:14]])
    np.testing.assert_allclose(pts, f.positions, rtol=1e-8)
    pb = write_particles_vtk(tmp_path / "pb.vtk", f, binary=True).read_bytes()
    i = pb.index(b"POINTS 9 double\n") + len(b"POINTS 9 double\n")
    np.testing.assert_array_equal(
        np.frombuffer(pb[i : i + 9 * 24], ">f8").reshape(9, 3), f.positions
    )
    text = write_particles_vtp(tmp_path / "p.vtp", f).read_text()
    np.testing.assert_array_equal(_parse_vtp_array(text, "Points"), f.positions)
    np.testing.assert_array_equal(_parse_vtp_array(text, "velocity"), f.velocities)
    np.testing.assert_array_equal(_parse_vtp_array(text, "id"), f.ids)
    box = box_mesh([0, 0, 0], [1, 1, 1])
    mt = write_mesh_vtp(tmp_path / "m.vtp", box.vertices, box.triangles).read_text()
    np.testing.assert_array_equal(_parse_vtp_array(mt, "connectivity"), box.triangles.ravel())
    assert (
        "POLYGONS 12 48"
        in write_mesh_vtk(tmp_path / "m.vtk", box.vertices, box.triangles, binary=False).read_text()
    )
    pvd = write_pvd(tmp_path / "s.pvd", [(0.0, "a.vtp"), (0.1, "b.vtp")]).read_text()
    assert 'timestep="0.1"' in pvd and 'file="b.vtp"' in pvd
