"""DEM scenes as campaign run functions: design factors (seed Table 3.1 names) -> scene config
-> DEM run -> responses (seed Table 3.3 names).

``DrawdownRunner(base_scene, run_root)`` is a picklable ``run(params, seed) -> dict`` for
:func:`~.campaign.run_campaign`; each run writes into its own directory under ``run_root``
(named from the parameters and seed) and resumes from its checkpoint if interrupted.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["SEED_TO_MATERIAL", "material_update", "DrawdownRunner"]

#: seed factor name -> field of ``schemas.dem_scene.MaterialConfig``
SEED_TO_MATERIAL = {
    "PP_SF": "pp_friction",
    "PP_RF": "pp_rolling_friction",
    "PP_COR": "pp_restitution",
    "PW_SF": "pw_friction",
    "PW_RF": "pw_rolling_friction",
    "PW_COR": "pw_restitution",
    "SM": "shear_modulus",
    "PR": "poisson",
}


def material_update(params: Mapping[str, float], max_poisson: float = 0.499) -> dict[str, float]:
    """Material fields for a design point. Unknown factor names raise. Poisson's ratio is
    capped at ``max_poisson`` (the scene's contact law needs nu < 0.5; the seed's design uses
    0.5 as its upper level): the value used is reported by the runner as ``PR_used``."""
    unknown = [k for k in params if k not in SEED_TO_MATERIAL]
    if unknown:
        raise ValueError(f"params {unknown} are not DEM material factors {list(SEED_TO_MATERIAL)}")
    out = {SEED_TO_MATERIAL[k]: float(v) for k, v in params.items()}
    if "poisson" in out:
        out["poisson"] = min(out["poisson"], max_poisson)
    return out


class DrawdownRunner:
    """Run the DEM drawdown test (seed 3.2.2) at one design point; picklable.

    ``base``: a ``schemas.dem_scene.DrawdownScene`` (or its dict) giving everything but the
    material factors; ``run_root``: directory of the per-run directories.
    Returns ``AOR_deg, shear_angle_deg, mass_lower_kg, max_flowrate_kg_s`` (Table 3.3 names)
    plus ``PR_used``.
    """

    def __init__(
        self,
        base: Any = None,
        run_root: str | Path = "drawdown_runs",
        max_poisson: float = 0.499,
    ) -> None:
        from schemas.dem_scene import DrawdownScene

        if base is None:
            base = DrawdownScene()
        elif isinstance(base, Mapping):
            base = DrawdownScene(**base)
        self.base = base
        self.run_root = str(run_root)
        self.max_poisson = max_poisson

    def config(self, params: Mapping[str, float], seed: int) -> Any:
        """The scene config of one run (validated)."""
        from schemas.dem_scene import DrawdownScene

        data = self.base.model_dump()
        data["material"] = {**data["material"], **material_update(params, self.max_poisson)}
        data["seed"] = int(seed) % (2**31)
        data["output"] = {**data["output"], "figures": False}
        return DrawdownScene(**data)

    def run_dir(self, params: Mapping[str, float], seed: int) -> Path:
        key = json.dumps({"p": {k: float(v) for k, v in sorted(params.items())}, "s": int(seed)})
        return Path(self.run_root) / f"drawdown_{hashlib.sha1(key.encode()).hexdigest()[:12]}"

    def __call__(self, params: dict[str, float], seed: int) -> dict[str, float]:
        from twin_core.scenes import drawdown

        cfg = self.config(params, seed)
        res = drawdown.run(cfg, self.run_dir(params, seed), resume=True, progress=False)
        return {
            "AOR_deg": float(res["angle_of_repose_deg"]),
            "shear_angle_deg": float(res["shear_angle_deg"]),
            "mass_lower_kg": float(res["mass_lower_kg"]),
            "max_flowrate_kg_s": float(res["max_flow_kg_s"]),
            "PR_used": float(cfg.material.poisson),
        }
