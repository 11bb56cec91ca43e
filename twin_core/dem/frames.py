"""Particle frames: a compressed, chunked on-disk time series of DEM states, with a reader.

Format (a directory, numpy only, no HDF5):

* ``frames.json`` - manifest: ``{"format": "powder-twin-frames", "version": 1,
  "precision": "float32"|"float64", "chunks": [{"file", "n_frames", "t0", "t1"}, ...],
  "meta": {...}}``. The manifest is rewritten atomically after each chunk, so a reader never
  sees a half-written chunk and an interrupted run can be resumed.
* ``chunk_00000.npz`` ... - ``numpy.savez_compressed`` archives holding ``n_frames`` frames
  concatenated: ``t`` (n_frames,), ``offsets`` (n_frames + 1,) into the per-particle arrays
  ``ids`` (int64), ``types`` (int32), ``radii``, ``positions`` (n, 3), ``velocities`` (n, 3)
  (SI units; frame i is rows ``offsets[i]:offsets[i+1]``). Particle numbers may change between
  frames (insertion, removal).

A frame (:class:`Frame`) has ``t, ids, types, radii, positions, velocities``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Frame", "FrameReader", "FrameWriter", "frame_from_state"]

FORMAT = "powder-twin-frames"
VERSION = 1


@dataclass
class Frame:
    """One particle state (SI units)."""

    t: float
    ids: np.ndarray
    types: np.ndarray
    radii: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.ids)
        for name in ("types", "radii"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"{name} must have {n} entries, got {len(getattr(self, name))}")
        for name in ("positions", "velocities"):
            a = np.asarray(getattr(self, name))
            if a.shape != (n, 3):
                raise ValueError(f"{name} must have shape ({n}, 3), got {a.shape}")

    @property
    def n(self) -> int:
        return len(self.ids)

    # attribute aliases matching the engine's Simulation, so sensors accept frames too
    @property
    def type_id(self) -> np.ndarray:
        return self.types

    @property
    def radius(self) -> np.ndarray:
        return self.radii

    @property
    def pos(self) -> np.ndarray:
        return self.positions

    @property
    def vel(self) -> np.ndarray:
        return self.velocities


def _get(state: Any, *names: str) -> Any:
    for n in names:
        if hasattr(state, n):
            return getattr(state, n)
    raise AttributeError(f"state has none of the attributes {names}")


def frame_from_state(state: Any) -> Frame:
    """Copy a :class:`Frame` out of any object with the engine's attribute names
    (``t, ids, type_id, radius, pos, vel``) or the frame names."""
    return Frame(
        t=float(_get(state, "t")),
        ids=np.array(_get(state, "ids"), dtype=np.int64),
        types=np.array(_get(state, "type_id", "types"), dtype=np.int32),
        radii=np.array(_get(state, "radius", "radii"), dtype=float),
        positions=np.array(_get(state, "pos", "positions"), dtype=float),
        velocities=np.array(_get(state, "vel", "velocities"), dtype=float),
    )


class FrameWriter:
    """Append frames to a frame directory, flushing one compressed chunk every
    ``chunk_frames`` frames (and on :meth:`close`).

    With ``resume=True`` an existing directory is continued: frames at or after ``resume_t``
    (if given) are dropped from the stored chunks so the resumed run can write them again.
    ``interval_s`` (optional) skips frames closer than that to the previous stored frame.
    """

    def __init__(
        self,
        directory: str | Path,
        *,
        chunk_frames: int = 50,
        precision: str = "float32",
        interval_s: float | None = None,
        meta: dict | None = None,
        resume: bool = False,
        resume_t: float | None = None,
    ) -> None:
        if chunk_frames < 1:
            raise ValueError(f"chunk_frames must be >= 1, got {chunk_frames}")
        if precision not in ("float32", "float64"):
            raise ValueError(f"precision must be 'float32' or 'float64', got {precision!r}")
        if interval_s is not None and interval_s < 0:
            raise ValueError(f"interval_s must be >= 0, got {interval_s}")
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.chunk_frames = chunk_frames
        self.precision = precision
        self.interval_s = interval_s
        self._buf: list[Frame] = []
        self._last_t: float | None = None
        manifest = self.dir / "frames.json"
        if resume and manifest.exists():
            self.manifest = json.loads(manifest.read_text())
            if self.manifest.get("format") != FORMAT:
                raise ValueError(f"{manifest} is not a {FORMAT} manifest")
            self.precision = self.manifest["precision"]
            if resume_t is not None:
                self._truncate(resume_t)
            if self.manifest["chunks"]:
                self._last_t = self.manifest["chunks"][-1]["t1"]
        else:
            for old in self.dir.glob("chunk_*.npz"):
                old.unlink()
            self.manifest = {
                "format": FORMAT,
                "version": VERSION,
                "precision": self.precision,
                "chunks": [],
                "meta": meta or {},
            }
            self._write_manifest()

    def _truncate(self, t_keep: float) -> None:
        chunks = []
        for ch in self.manifest["chunks"]:
            if ch["t0"] >= t_keep:
                (self.dir / ch["file"]).unlink(missing_ok=True)
                continue
            if ch["t1"] >= t_keep:
                frames = [f for f in _read_chunk(self.dir / ch["file"]) if f.t < t_keep]
                ch = self._save_chunk(frames, ch["file"])
            chunks.append(ch)
        self.manifest["chunks"] = chunks
        self._write_manifest()

    def _write_manifest(self) -> None:
        tmp = self.dir / "frames.json.tmp"
        tmp.write_text(json.dumps(self.manifest, indent=1))
        os.replace(tmp, self.dir / "frames.json")

    def _save_chunk(self, frames: list[Frame], name: str) -> dict:
        fdt = np.float32 if self.precision == "float32" else np.float64
        counts = np.array([f.n for f in frames], dtype=np.int64)
        arrays = {
            "t": np.array([f.t for f in frames], dtype=np.float64),
            "offsets": np.concatenate([[0], np.cumsum(counts)]),
            "ids": np.concatenate([f.ids for f in frames]).astype(np.int64),
            "types": np.concatenate([f.types for f in frames]).astype(np.int32),
            "radii": np.concatenate([f.radii for f in frames]).astype(fdt),
            "positions": np.concatenate([f.positions for f in frames]).astype(fdt),
            "velocities": np.concatenate([f.velocities for f in frames]).astype(fdt),
        }
        tmp = self.dir / (name + ".tmp.npz")
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, self.dir / name)
        return {
            "file": name,
            "n_frames": len(frames),
            "t0": float(frames[0].t),
            "t1": float(frames[-1].t),
        }

    def append(self, state: Any) -> bool:
        """Store the state (a :class:`Frame` or an engine ``Simulation``); returns whether it
        was stored (False when closer than ``interval_s`` to the previous frame)."""
        frame = state if isinstance(state, Frame) else frame_from_state(state)
        if self._last_t is not None:
            if frame.t < self._last_t:
                raise ValueError(f"frame t must not go backwards: {frame.t} < {self._last_t}")
            if self.interval_s and frame.t - self._last_t < self.interval_s * (1 - 1e-9):
                return False
        self._buf.append(frame)
        self._last_t = frame.t
        if len(self._buf) >= self.chunk_frames:
            self.flush()
        return True

    def flush(self) -> None:
        if not self._buf:
            return
        name = f"chunk_{len(self.manifest['chunks']):05d}.npz"
        self.manifest["chunks"].append(self._save_chunk(self._buf, name))
        self._buf = []
        self._write_manifest()

    def close(self) -> None:
        self.flush()

    def __enter__(self) -> FrameWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _read_chunk(path: Path) -> list[Frame]:
    with np.load(path) as z:
        t, off = z["t"], z["offsets"]
        ids, types, radii = z["ids"], z["types"], z["radii"].astype(float)
        pos, vel = z["positions"].astype(float), z["velocities"].astype(float)
    return [
        Frame(
            float(t[i]),
            ids[off[i] : off[i + 1]],
            types[off[i] : off[i + 1]],
            radii[off[i] : off[i + 1]],
            pos[off[i] : off[i + 1]],
            vel[off[i] : off[i + 1]],
        )
        for i in range(len(t))
    ]


class FrameReader:
    """Random and sequential access to a frame directory written by :class:`FrameWriter`.

    ``len(reader)``, ``reader.times``, ``reader[i]`` (a :class:`Frame`, float64 arrays) and
    iteration; one chunk is cached at a time.
    """

    def __init__(self, directory: str | Path) -> None:
        self.dir = Path(directory)
        manifest = self.dir / "frames.json"
        if not manifest.exists():
            raise ValueError(f"directory must hold a frames.json manifest: {self.dir}")
        self.manifest = json.loads(manifest.read_text())
        if self.manifest.get("format") != FORMAT:
            raise ValueError(f"{manifest} is not a {FORMAT} manifest")
        self.chunks = self.manifest["chunks"]
        self._starts = np.cumsum([0] + [c["n_frames"] for c in self.chunks])
        self._cache: tuple[int, list[Frame]] | None = None
        self._times: np.ndarray | None = None

    @property
    def meta(self) -> dict:
        return self.manifest.get("meta", {})

    def __len__(self) -> int:
        return int(self._starts[-1])

    def _chunk(self, k: int) -> list[Frame]:
        if self._cache is None or self._cache[0] != k:
            self._cache = (k, _read_chunk(self.dir / self.chunks[k]["file"]))
        return self._cache[1]

    def __getitem__(self, i: int) -> Frame:
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame index {i} out of range [0, {n})")
        k = int(np.searchsorted(self._starts, i, side="right") - 1)
        return self._chunk(k)[i - self._starts[k]]

    def __iter__(self) -> Iterator[Frame]:
        for k in range(len(self.chunks)):
            yield from self._chunk(k)

    @property
    def times(self) -> np.ndarray:
        if self._times is None:
            ts = []
            for c in self.chunks:
                with np.load(self.dir / c["file"]) as z:
                    ts.append(z["t"])
            self._times = np.concatenate(ts) if ts else np.zeros(0)
        return self._times

    def nearest(self, t: float) -> Frame:
        """Frame whose time is closest to ``t``."""
        return self[int(np.argmin(np.abs(self.times - t)))]
