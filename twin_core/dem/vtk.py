"""VTK export of particles and meshes for ParaView.

* :func:`write_particles_vtk` / :func:`write_mesh_vtk` - legacy ``.vtk`` POLYDATA (ASCII or
  big-endian binary, as the legacy format requires).
* :func:`write_particles_vtp` / :func:`write_mesh_vtp` - XML ``.vtp`` PolyData with inline
  base64 binary arrays (``header_type="UInt32"``, little-endian).
* :func:`write_pvd` - a ``.pvd`` collection that strings time steps together.

Particles are written as vertices with point data ``radius``, ``type``, ``id``, ``velocity``
(use ParaView's Glyph filter, sphere source, scale by ``radius``, scale factor 2 for diameter).

Format reference: "VTK File Formats", VTK User's Guide (Kitware), legacy and XML sections.
"""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

import numpy as np

from twin_core.dem.frames import frame_from_state

__all__ = [
    "write_mesh_vtk",
    "write_mesh_vtp",
    "write_particles_vtk",
    "write_particles_vtp",
    "write_pvd",
]


def _legacy(
    path: Path,
    points: np.ndarray,
    cells_kw: str,
    cells: list[np.ndarray],
    point_data: dict[str, np.ndarray],
    binary: bool,
    title: str,
) -> Path:
    n = len(points)
    ncell_entries = sum(len(c) + 1 for c in cells)
    with path.open("wb") as fh:

        def w(s: str) -> None:
            fh.write(s.encode("ascii"))

        w("# vtk DataFile Version 3.0\n")
        w(title[:250].replace("\n", " ") + "\n")
        w("BINARY\n" if binary else "ASCII\n")
        w("DATASET POLYDATA\n")
        w(f"POINTS {n} double\n")
        if binary:
            fh.write(np.asarray(points, ">f8").tobytes())
            w("\n")
        else:
            np.savetxt(fh, points, fmt="%.9e")
        w(f"{cells_kw} {len(cells)} {ncell_entries}\n")
        if cells:
            flat = np.concatenate([np.r_[len(c), c] for c in cells]).astype(np.int64)
            if binary:
                fh.write(flat.astype(">i4").tobytes())
                w("\n")
            else:
                for c in cells:
                    w(" ".join(map(str, np.r_[len(c), c])) + "\n")
        if point_data:
            w(f"POINT_DATA {n}\n")
            for name, arr in point_data.items():
                a = np.asarray(arr)
                is_int = np.issubdtype(a.dtype, np.integer)
                typ, big = ("int", ">i4") if is_int else ("double", ">f8")
                if a.ndim == 2 and a.shape[1] == 3:
                    w(f"VECTORS {name} {typ}\n")
                else:
                    w(f"SCALARS {name} {typ} 1\nLOOKUP_TABLE default\n")
                if binary:
                    fh.write(a.astype(big).tobytes())
                    w("\n")
                else:
                    np.savetxt(fh, a.reshape(n, -1), fmt="%d" if is_int else "%.9e")
    return path


def _particle_arrays(state: Any) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    f = frame_from_state(state)
    data = {
        "radius": f.radii,
        "type": f.types.astype(np.int32),
        "id": f.ids.astype(np.int32),
        "velocity": f.velocities,
    }
    return f.positions, data


def write_particles_vtk(path: str | Path, state: Any, *, binary: bool = True) -> Path:
    """Legacy VTK polydata of the particles of ``state`` (a Frame or a Simulation)."""
    pts, data = _particle_arrays(state)
    cells = [np.array([i]) for i in range(len(pts))]
    t = frame_from_state(state).t
    return _legacy(Path(path), pts, "VERTICES", cells, data, binary, f"particles t={t:.6f} s")


def write_mesh_vtk(
    path: str | Path, vertices: np.ndarray, triangles: np.ndarray, *, binary: bool = True
) -> Path:
    """Legacy VTK polydata of a triangle mesh."""
    tris = np.asarray(triangles, np.int64)
    return _legacy(
        Path(path), np.asarray(vertices, float), "POLYGONS", list(tris), {}, binary, "mesh"
    )


def _b64(a: np.ndarray) -> str:
    raw = np.ascontiguousarray(a).tobytes()
    return base64.b64encode(np.uint32(len(raw)).tobytes() + raw).decode("ascii")


_VTK_TYPES = {np.dtype("<f8"): "Float64", np.dtype("<i4"): "Int32", np.dtype("<i8"): "Int64"}


def _data_array(name: str, a: np.ndarray) -> str:
    a = np.asarray(a)
    if np.issubdtype(a.dtype, np.integer):
        a = a.astype("<i8")
    else:
        a = a.astype("<f8")
    ncomp = a.shape[1] if a.ndim == 2 else 1
    return (
        f'<DataArray type="{_VTK_TYPES[a.dtype]}" Name="{name}" '
        f'NumberOfComponents="{ncomp}" format="binary">{_b64(a)}</DataArray>'
    )


def _vtp(
    path: Path,
    points: np.ndarray,
    verts: np.ndarray | None,
    polys: np.ndarray | None,
    point_data: dict[str, np.ndarray],
) -> Path:
    n = len(points)
    nv = 0 if verts is None else len(verts)
    npoly = 0 if polys is None else len(polys)
    parts = [
        '<?xml version="1.0"?>',
        '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" header_type="UInt32">',
        "<PolyData>",
        f'<Piece NumberOfPoints="{n}" NumberOfVerts="{nv}" NumberOfLines="0" '
        f'NumberOfStrips="0" NumberOfPolys="{npoly}">',
        "<PointData>",
        *[_data_array(k, v) for k, v in point_data.items()],
        "</PointData>",
        "<Points>",
        _data_array("Points", np.asarray(points, float).reshape(-1, 3)),
        "</Points>",
    ]
    for tag, conn in (("Verts", verts), ("Polys", polys)):
        if conn is None:
            continue
        conn = np.asarray(conn, np.int64).reshape(len(conn), -1)
        offsets = np.arange(1, len(conn) + 1) * conn.shape[1]
        parts += [
            f"<{tag}>",
            _data_array("connectivity", conn.ravel()),
            _data_array("offsets", offsets),
            f"</{tag}>",
        ]
    parts += ["</Piece>", "</PolyData>", "</VTKFile>"]
    path.write_text("\n".join(parts) + "\n", encoding="ascii")
    return path


def write_particles_vtp(path: str | Path, state: Any) -> Path:
    """XML PolyData (.vtp) of the particles of ``state``."""
    pts, data = _particle_arrays(state)
    return _vtp(Path(path), pts, np.arange(len(pts)).reshape(-1, 1), None, data)


def write_mesh_vtp(path: str | Path, vertices: np.ndarray, triangles: np.ndarray) -> Path:
    """XML PolyData (.vtp) of a triangle mesh."""
    return _vtp(Path(path), np.asarray(vertices, float), None, np.asarray(triangles), {})


def write_pvd(path: str | Path, entries: list[tuple[float, str]]) -> Path:
    """ParaView collection: ``entries`` = [(time_s, relative file name), ...]."""
    lines = [
        '<?xml version="1.0"?>',
        '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
        "<Collection>",
        *[f'<DataSet timestep="{t:.9g}" group="" part="0" file="{f}"/>' for t, f in entries],
        "</Collection>",
        "</VTKFile>",
    ]
    path = Path(path)
    path.write_text("\n".join(lines) + "\n", encoding="ascii")
    return path
