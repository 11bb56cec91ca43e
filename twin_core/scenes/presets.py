"""Scene configurations built from the packaged presets (``twin_core/scenes/configs``): the
scene of a DEM job request (``services.dem``) and of the blender's request for a section run at
a new blade speed."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

__all__ = ["PRESETS", "scene_data"]

#: packaged scene configurations a request may start from (``params.preset``)
PRESETS = Path(__file__).resolve().parent / "configs"


def scene_data(scene: str, job_id: str, params: dict[str, Any], seed: int | None) -> dict[str, Any]:
    """The scene configuration of a request: ``params.preset`` (the name of a packaged scene
    configuration, e.g. ``blender_small``) overridden by the other parameters."""
    params = dict(params)
    preset = params.pop("preset", None)
    data: dict[str, Any] = {}
    if preset is not None:
        names = sorted(p.stem for p in PRESETS.glob("*.yaml"))
        if preset not in names:
            raise ValueError(f"params.preset must be one of {names}, got {preset!r}")
        data = yaml.safe_load((PRESETS / f"{preset}.yaml").read_text())
        if data.get("scene") != scene:
            raise ValueError(
                f"params.preset {preset!r} is a {data.get('scene')!r} scene, not {scene!r}"
            )
    data.update({"scene": scene, "name": job_id, **params})
    if seed is not None:
        data["seed"] = seed
    return data
