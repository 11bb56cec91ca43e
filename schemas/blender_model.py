"""Serializable compartment model of the continuous blender (wire/file contract).

One periodic section of the blender as a conserving compartment network (compartments,
holdups, sparse flow triplets with a flag for the flows through the periodic face, the
inlet/outlet compartments of that face with their forward flows) plus the number of sections
in series, the section RTD form and the throughput basis. Pure data with its validators: the
numerics that use it (E(t), outlet prediction, RSD profile, flow scale for a blade speed) are
the ``blender_model_*`` functions of ``twin_core.compartment.blender_model``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

SCHEMA_VERSION = "1"


class BlenderModel(BaseModel):
    """Compartment model of a blender: ``n_sections`` identical open sections in series."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    schema_version: Literal["1"] = SCHEMA_VERSION
    n_compartments: int = Field(gt=0, description="compartments of one section")
    holdup_kg: list[float] = Field(description="holdup of each compartment of one section")
    flow_src: list[int] = Field(description="flow triplets: source compartment")
    flow_dst: list[int] = Field(description="flow triplets: destination compartment")
    flow_kg_s: list[float] = Field(description="flow triplets: mass flow (kg/s)")
    flow_wrap: list[bool] = Field(
        description="flow goes through the periodic face (forward from a higher slice to a "
        "lower one, backward the other way)"
    )
    compartment_slice: list[int] = Field(description="axial slice of each compartment")
    inlet_compartments: list[int] = Field(
        min_length=1, description="first-slice compartments fed through the periodic face"
    )
    inlet_kg_s: list[float] = Field(description="forward flow into each inlet compartment")
    outlet_compartments: list[int] = Field(
        min_length=1, description="last-slice compartments leaving through the periodic face"
    )
    outlet_kg_s: list[float] = Field(description="forward flow out of each outlet compartment")
    n_sections: int = Field(default=8, ge=1)
    section_form: Literal["transit", "closed"] = Field(
        default="transit",
        description="section RTD: record-passage transit time (DEM definition) or the "
        "closed-closed cut of the periodic face",
    )
    n_upstream: int = Field(default=2, ge=0, description="upstream copies of the transit form")
    coupling: Literal["mixing_cup"] = "mixing_cup"
    throughput_kg_h: float = Field(gt=0, description="throughput basis of the flows")
    rpm_basis: float | None = Field(default=None, gt=0)
    rpm_flow_scale: list[tuple[float, float]] | None = Field(
        default=None,
        description="(rpm, net axial flow / basis flow) measured on DEM runs at other blade "
        "speeds; flow_scale_for_rpm interpolates them (proportional to rpm without them)",
    )
    section_length_m: float = Field(gt=0)
    compartment_centroid_m: list[list[float]] | None = None
    rsd_ss: float | None = None
    rsd_0: float | None = None
    k_b_per_s: float | None = None
    source: str = ""
    notes: dict[str, float | str] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _check(self) -> BlenderModel:
        n = self.n_compartments
        if len(self.holdup_kg) != n:
            raise ValueError(
                f"holdup_kg must have n_compartments={n} values, got {len(self.holdup_kg)}"
            )
        if any(not (h > 0) for h in self.holdup_kg):
            raise ValueError("holdup_kg must be > 0")
        m = len(self.flow_kg_s)
        if len(self.flow_src) != m or len(self.flow_dst) != m or len(self.flow_wrap) != m:
            raise ValueError(
                f"flow_src, flow_dst, flow_kg_s, flow_wrap must have equal length, got "
                f"{len(self.flow_src)}, {len(self.flow_dst)}, {m}, {len(self.flow_wrap)}"
            )
        if len(self.compartment_slice) != n:
            raise ValueError(f"compartment_slice must have n_compartments={n} values")
        for name in ("flow_src", "flow_dst", "inlet_compartments", "outlet_compartments"):
            idx = getattr(self, name)
            if idx and (min(idx) < 0 or max(idx) >= n):
                raise ValueError(f"{name} must lie in [0, {n}), got [{min(idx)}, {max(idx)}]")
        for name in ("flow_kg_s", "inlet_kg_s", "outlet_kg_s"):
            v = np.asarray(getattr(self, name), dtype=float)
            if not np.all(np.isfinite(v)) or np.any(v < 0):
                raise ValueError(f"{name} must be finite and >= 0")
        for r, sc in self.rpm_flow_scale or []:
            if not (r > 0 and sc >= 0 and np.isfinite(r) and np.isfinite(sc)):
                raise ValueError(f"rpm_flow_scale needs rpm > 0 and scale >= 0, got ({r}, {sc})")
        if len(self.inlet_kg_s) != len(self.inlet_compartments):
            raise ValueError("inlet_kg_s must have one value per inlet compartment")
        if len(self.outlet_kg_s) != len(self.outlet_compartments):
            raise ValueError("outlet_kg_s must have one value per outlet compartment")
        bal = self._balance()
        scale = max(float(np.max(self.flow_kg_s, initial=0.0)), 1e-300)
        if np.abs(bal).max() > 1e-8 * scale:
            raise ValueError(
                f"flows must conserve mass: max |in - out| = {np.abs(bal).max():.3e} kg/s "
                f"(compartment {int(np.argmax(np.abs(bal)))})"
            )
        sl = np.asarray(self.compartment_slice)
        src = np.asarray(self.flow_src, dtype=np.int64)
        dst = np.asarray(self.flow_dst, dtype=np.int64)
        w = np.asarray(self.flow_wrap, dtype=bool)
        r = np.asarray(self.flow_kg_s, dtype=float)
        # through the periodic face forward: from a higher slice to a lower one (the last to
        # the first for face flows; shorter jumps of particle transitions), backward reversed
        fwd = w & (sl[src] > sl[dst])
        bwd = w & (sl[src] < sl[dst])
        if np.any(w & ~fwd & ~bwd):
            raise ValueError("flow_wrap flows must join two different slices")
        feed = np.zeros(n)
        np.add.at(feed, dst[fwd], r[fwd])
        dis = np.zeros(n)
        np.add.at(dis, src[fwd], r[fwd])
        for name, comp, val, ref in (
            ("inlet", self.inlet_compartments, self.inlet_kg_s, feed),
            ("outlet", self.outlet_compartments, self.outlet_kg_s, dis),
        ):
            got = np.zeros(n)
            np.add.at(got, comp, val)
            if np.abs(got - ref).max() > 1e-8 * scale:
                raise ValueError(
                    f"{name}_compartments/{name}_kg_s must equal the forward flows through "
                    f"the periodic face"
                )
        q = float(r[fwd].sum() - r[bwd].sum()) * 3600.0
        if q <= 0:
            raise ValueError(f"net flow through the periodic face must be > 0, got {q} kg/h")
        if abs(q - self.throughput_kg_h) > 1e-6 * self.throughput_kg_h:
            raise ValueError(
                f"throughput_kg_h={self.throughput_kg_h} differs from the net flow through "
                f"the periodic face {q} kg/h"
            )
        return self

    def _balance(self) -> np.ndarray:
        """Inflow minus outflow of every compartment of the periodic section (kg/s)."""
        n = self.n_compartments
        src = np.asarray(self.flow_src, dtype=np.int64)
        dst = np.asarray(self.flow_dst, dtype=np.int64)
        r = np.asarray(self.flow_kg_s, dtype=float)
        return np.bincount(dst, weights=r, minlength=n) - np.bincount(src, weights=r, minlength=n)

    # ------------------------------------------------------------------ derived data
    @property
    def flowing_holdup_kg(self) -> float:
        """Holdup of one section in compartments with any flow (stagnant ones excluded)."""
        used = np.zeros(self.n_compartments, dtype=bool)
        used[self.flow_src] = True
        used[self.flow_dst] = True
        return float(np.asarray(self.holdup_kg)[used].sum())

    @property
    def mean_residence_time_s(self) -> float:
        """tau = n_sections x flowing section holdup / throughput (s)."""
        return self.n_sections * self.flowing_holdup_kg / (self.throughput_kg_h / 3600.0)

    @property
    def holdup_total_kg(self) -> float:
        return self.n_sections * sum(self.holdup_kg)

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.write_text(self.model_dump_json(indent=1))
        return path

    @classmethod
    def load(cls, path: str | Path) -> BlenderModel:
        path = Path(path)
        if not path.exists():
            raise ValueError(f"model file {str(path)!r} does not exist")
        return cls.model_validate_json(path.read_text())
