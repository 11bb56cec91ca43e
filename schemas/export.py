"""JSON Schema export of every pydantic model in every ``schemas.*`` module."""

from __future__ import annotations

import importlib
import inspect
import json
import pkgutil
from pathlib import Path

from pydantic import BaseModel

from schemas.base import json_schema


def all_models() -> dict[str, type[BaseModel]]:
    """Every pydantic model defined in a ``schemas.*`` module, keyed ``module.Class``.

    Modules are discovered with :mod:`pkgutil`, so schema modules of every area are included.
    A module that fails to import raises (an export must not silently miss a schema).
    """
    import schemas

    models: dict[str, type[BaseModel]] = {}
    for info in sorted(pkgutil.iter_modules(schemas.__path__), key=lambda i: i.name):
        name = f"schemas.{info.name}"
        module = importlib.import_module(name)
        for cls_name, obj in inspect.getmembers(module, inspect.isclass):
            if (
                issubclass(obj, BaseModel)
                and obj.__module__ == name
                and not cls_name.startswith("_")
            ):
                models[f"{name}.{cls_name}"] = obj
    return models


def export_json_schemas(directory: str | Path) -> list[Path]:
    """Write ``<module>.<Class>.json`` for every model of :func:`all_models` into ``directory``.

    Returns the written paths (sorted). Models whose schema cannot be generated raise.
    """
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for qualname, model in sorted(all_models().items()):
        path = out / f"{qualname}.json"
        path.write_text(json.dumps(json_schema(model), indent=2, sort_keys=True) + "\n")
        paths.append(path)
    return paths
