"""The layering rules of ``services/`` and the key rule, checked on the source (ast).

- A *service module* (a process of the live twin: blender, oos, rtd, feeder, closeloop,
  recorder, dem) imports only ``schemas``, ``twin_core`` and the infrastructure modules
  (:data:`INFRASTRUCTURE`); it imports no other service and not the CLI.
- No module of ``services`` outside ``services/cli`` imports the CLI.
- ``twin_core`` imports nothing from ``services``, zenoh or mcap.
- No module builds a key expression with an f-string: keys come from ``schemas.keys``.

Each rule is also run on a synthetic module that breaks it, so a violation is seen to fail.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

#: the processes of the live twin (``services.runner``; ``bridge`` is ``opcua_bridge``)
SERVICE_MODULES = (
    "blender",
    "oos",
    "rtd",
    "feeder",
    "closeloop",
    "recorder",
    "dem",
    "opcua_bridge",
)
#: what a service may build on besides schemas and twin_core: the bus and its one publisher and
#: subscribers, the one service base, run-state helpers, MCAP recordings
INFRASTRUCTURE = ("services.bus", "services.service", "services.common", "services.recording")


def imports(source: str) -> Iterator[str]:
    """Every module a source imports (absolute names; ``from x import y`` gives ``x`` and
    ``x.y``)."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module
            yield from (f"{node.module}.{a.name}" for a in node.names)


def service_violations(source: str) -> list[str]:
    """Imports of a service module that break the rule."""
    bad = []
    for name in imports(source):
        top = name.split(".")[0]
        if top != "services":
            continue
        if not any(name == m or name.startswith(m + ".") for m in INFRASTRUCTURE):
            bad.append(name)
    return sorted(set(bad))


def twin_core_violations(source: str) -> list[str]:
    return sorted({n for n in imports(source) if n.split(".")[0] in ("services", "zenoh", "mcap")})


def fstring_keys(source: str) -> list[int]:
    """Lines of f-strings that start like a key expression (``twin/...``)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.JoinedStr) and node.values:
            head = node.values[0]
            if isinstance(head, ast.Constant) and str(head.value).startswith("twin/"):
                out.append(node.lineno)
    return out


def sources(*globs: str) -> list[Path]:
    return sorted(p for g in globs for p in ROOT.glob(g) if "/.venv/" not in str(p))


@pytest.mark.parametrize("name", SERVICE_MODULES)
def test_a_service_imports_only_schemas_twin_core_and_infrastructure(name):
    source = (ROOT / "services" / f"{name}.py").read_text()
    assert service_violations(source) == []


def test_nothing_in_services_but_the_cli_imports_the_cli():
    bad = {
        str(p.relative_to(ROOT)): [
            n for n in imports(p.read_text()) if n.startswith("services.cli")
        ]
        for p in sources("services/*.py")
    }
    assert {k: v for k, v in bad.items() if v} == {}


def test_twin_core_imports_no_services_zenoh_or_mcap():
    bad = {
        str(p.relative_to(ROOT)): twin_core_violations(p.read_text())
        for p in sources("twin_core/**/*.py")
    }
    assert {k: v for k, v in bad.items() if v} == {}


def test_no_key_is_spelled_by_an_f_string_outside_schemas_keys():
    keys_module = ROOT / "schemas" / "keys.py"
    bad = {
        str(p.relative_to(ROOT)): fstring_keys(p.read_text())
        for p in sources("schemas/*.py", "services/**/*.py", "twin_core/**/*.py", "benchmarks/*.py")
        if p != keys_module
    }
    assert {k: v for k, v in bad.items() if v} == {}


def test_each_rule_fails_on_a_module_that_breaks_it():
    """Synthetic modules: a service importing another service and the CLI, twin_core importing
    zenoh and a service, an f-string key."""
    service = "from services.blender import BlenderService\nimport services.cli.live\nfrom services.bus import Publisher\n"
    assert service_violations(service) == [
        "services.blender",
        "services.blender.BlenderService",
        "services.cli.live",
    ]
    assert twin_core_violations("import zenoh\nfrom services.common import OutputLog\n") == [
        "services.common",
        "services.common.OutputLog",
        "zenoh",
    ]
    assert fstring_keys('line = "l"\nk = f"twin/{line}/feeder/*/flow"\n') == [2]
    assert fstring_keys('k = f"{line}/twin/"\n') == []
