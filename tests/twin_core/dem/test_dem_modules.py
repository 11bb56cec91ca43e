"""Layout of the DEM engine package (docs/dem_engine.md, "Module layout"): each module imports
only the modules of the layers below it (so the package has no import cycle, type-checking
imports included), and no function grows past ~80 lines. Static checks of the source (ast):
no numba compilation."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import twin_core.dem

DEM = Path(twin_core.dem.__file__).parent

# lowest layer first; a module may import only modules of strictly lower layers
LAYERS = [
    {"space", "materials", "motion", "stl", "frames", "threads"},
    {"contact", "vtk"},
    {"meshes"},
    {"partition"},
    {"pairs", "walls", "mesh_contacts"},
    {"integrator", "energy", "insertion"},
    {"simulation"},
    {"sensors"},
    {"warmup"},
]
LAYER_OF = {name: k for k, layer in enumerate(LAYERS) for name in layer}
MAX_FUNCTION_LINES = 80


def _sources(package: Path) -> dict[str, ast.Module]:
    return {
        p.stem: ast.parse(p.read_text(), filename=str(p))
        for p in sorted(package.glob("*.py"))
        if p.stem != "__init__"
    }


def _engine_imports(tree: ast.Module, modules: set[str]) -> set[str]:
    """Sibling modules imported anywhere in the module (relative or absolute, including imports
    under ``if TYPE_CHECKING`` and inside functions)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level == 1:
                parts = [mod.split(".")[0]] if mod else [a.name for a in node.names]
            elif mod.startswith("twin_core.dem."):
                parts = [mod.split(".")[2]]
            elif mod == "twin_core.dem":
                parts = [a.name for a in node.names]
            else:
                parts = []
            found.update(p for p in parts if p in modules)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("twin_core.dem."):
                    found.add(a.name.split(".")[2])
    return found


def _layer_violations(package: Path) -> list[str]:
    trees = _sources(package)
    out = [f"{m}: not placed in a layer" for m in trees if m not in LAYER_OF]
    for m, tree in trees.items():
        for dep in sorted(_engine_imports(tree, set(trees))):
            if m in LAYER_OF and LAYER_OF.get(dep, len(LAYERS)) >= LAYER_OF[m]:
                out.append(f"{m} imports {dep}")
    return out


def test_dem_modules_import_only_lower_layers():
    assert _layer_violations(DEM) == []


def test_layer_check_catches_a_cycle_through_type_checking_imports(tmp_path):
    """The check fails on the cycle the split removed (insertion importing simulation for a
    type annotation) and on a module placed in no layer."""
    (tmp_path / "simulation.py").write_text("from .insertion import ParticleFactory\n")
    (tmp_path / "insertion.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .simulation import X\n"
    )
    (tmp_path / "extra.py").write_text("import numpy\n")
    assert _layer_violations(tmp_path) == [
        "extra: not placed in a layer",
        "insertion imports simulation",
    ]


def _long_functions(package: Path) -> list[str]:
    out = []
    for name, tree in _sources(package).items():
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    out.append(f"{name}.{node.name}: {n} lines")
    return out


def test_no_dem_function_over_80_lines():
    assert _long_functions(DEM) == []


@pytest.mark.parametrize("lines", [MAX_FUNCTION_LINES, MAX_FUNCTION_LINES + 1])
def test_function_length_check_counts_lines(tmp_path, lines):
    body = "".join(f"    x{k} = {k}\n" for k in range(lines - 1))
    (tmp_path / "m.py").write_text(f"def f():\n{body}")
    expected = [] if lines <= MAX_FUNCTION_LINES else [f"m.f: {lines} lines"]
    assert _long_functions(tmp_path) == expected
