"""STL read/write (ASCII and binary) for triangle meshes.

A mesh is a pair ``(vertices, triangles)``: ``vertices`` float (n, 3) in metres (or whatever
unit the caller uses; STL itself is unitless) and ``triangles`` int (m, 3) indices into
``vertices``. STL stores every triangle with its own three corner coordinates; on reading,
identical corners are merged again so the indexed mesh is recovered.

Format reference: the 3D Systems "StereoLithography Interface Specification" (1989):
binary = 80-byte header, uint32 triangle count, then per triangle 12 little-endian float32
(normal, v1, v2, v3) and a uint16 attribute byte count; ASCII = ``solid name`` /
``facet normal nx ny nz`` / ``outer loop`` / 3 x ``vertex x y z`` / ``endloop`` /
``endfacet`` / ``endsolid name``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["facet_normals", "read_stl", "write_stl"]

_BINARY_DTYPE = np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])


def _check_mesh(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=float)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must have shape (n, 3), got {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"triangles must have shape (m, 3), got {t.shape}")
    if t.size and (t.min() < 0 or t.max() >= len(v)):
        raise ValueError(
            f"triangles must index vertices in [0, {len(v) - 1}], got range [{t.min()}, {t.max()}]"
        )
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices must be finite")
    return v, t.astype(np.int64)


def facet_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit normals n = (v1 - v0) x (v2 - v0) / |...| of each triangle (right-hand rule).

    Degenerate triangles get a zero normal.
    """
    v, t = _check_mesh(vertices, triangles)
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def write_stl(
    path: str | Path,
    vertices: np.ndarray,
    triangles: np.ndarray,
    *,
    binary: bool = True,
    name: str = "mesh",
) -> Path:
    """Write a triangle mesh to ``path`` as binary (default) or ASCII STL; returns the path."""
    v, t = _check_mesh(vertices, triangles)
    path = Path(path)
    normals = facet_normals(v, t)
    corners = v[t]  # (m, 3, 3)
    if binary:
        rec = np.zeros(len(t), dtype=_BINARY_DTYPE)
        rec["normal"] = normals
        rec["v"] = corners
        header = f"binary STL {name}".encode("ascii", "replace")[:80].ljust(80, b" ")
        with path.open("wb") as fh:
            fh.write(header)
            fh.write(np.uint32(len(t)).tobytes())
            fh.write(rec.tobytes())
    else:
        safe = "".join(ch if ch.isalnum() or ch in "_-." else "_" for ch in name) or "mesh"
        lines = [f"solid {safe}"]
        for n, c in zip(normals, corners):
            lines.append(f"  facet normal {n[0]:.9e} {n[1]:.9e} {n[2]:.9e}")
            lines.append("    outer loop")
            for p in c:
                lines.append(f"      vertex {p[0]:.9e} {p[1]:.9e} {p[2]:.9e}")
            lines.append("    endloop")
            lines.append("  endfacet")
        lines.append(f"endsolid {safe}")
        path.write_text("\n".join(lines) + "\n", encoding="ascii")
    return path


def _merge_corners(corners: np.ndarray, decimals: int | None) -> tuple[np.ndarray, np.ndarray]:
    flat = corners.reshape(-1, 3).astype(float)
    key = flat if decimals is None else np.round(flat, decimals)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # keep vertices in order of first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    vertices = flat[first[order]]
    triangles = rank[inverse.reshape(-1)].reshape(-1, 3)
    return vertices, triangles


def _is_binary(data: bytes) -> bool:
    if len(data) < 84:
        return False
    count = int(np.frombuffer(data[80:84], dtype="<u4")[0])
    if 84 + 50 * count == len(data):
        return True
    return not data.lstrip()[:5].lower().startswith(b"solid")


def read_stl(path: str | Path, *, merge_decimals: int | None = 9) -> tuple[np.ndarray, np.ndarray]:
    """Read an ASCII or binary STL file (detected from its content).

    Returns ``(vertices, triangles)`` with coincident corners merged (coordinates rounded to
    ``merge_decimals`` decimals for the comparison; ``None`` merges exact matches only).
    """
    data = Path(path).read_bytes()
    if _is_binary(data):
        count = int(np.frombuffer(data[80:84], dtype="<u4")[0])
        need = 84 + 50 * count
        if len(data) < need:
            raise ValueError(
                f"binary STL {path} is truncated: {count} triangles need {need} bytes, "
                f"file has {len(data)}"
            )
        rec = np.frombuffer(data[84:need], dtype=_BINARY_DTYPE)
        corners = rec["v"].astype(float)
    else:
        text = data.decode("ascii", errors="replace")
        coords = [
            line.split()[1:4]
            for line in text.splitlines()
            if line.strip().lower().startswith("vertex")
        ]
        if len(coords) % 3:
            raise ValueError(f"ASCII STL {path} has {len(coords)} vertices, not a multiple of 3")
        corners = np.asarray(coords, dtype=float).reshape(-1, 3, 3)
    if len(corners) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    return _merge_corners(corners, merge_decimals)
