"""The layering rules of ``schemas`` and ``twin_core``, checked on the source (ast).

- ``schemas`` imports nothing from ``twin_core`` or ``services`` (pure data, validators and key
  builders).
- The packages of ``twin_core`` import each other without a cycle (every import, module or
  function level, counts).
- In ``twin_core`` only modules named ``plots.py`` import matplotlib (they draw; the workflows
  and the CLI save what they return).

Each rule is also run on a synthetic case that breaks it, so a violation is seen to fail.
"""

from __future__ import annotations

from collections.abc import Mapping

from test_services_layers import ROOT, imports, sources


def schemas_violations(source: str) -> list[str]:
    """Imports of a schemas module from twin_core or services."""
    return sorted({n for n in imports(source) if n.split(".")[0] in ("twin_core", "services")})


def package_of(path_parts: tuple[str, ...]) -> str:
    """``twin_core.<package>`` of a module path inside twin_core."""
    return f"twin_core.{path_parts[1].removesuffix('.py')}"


def package_graph() -> dict[str, set[str]]:
    """twin_core package -> the other twin_core packages it imports."""
    graph: dict[str, set[str]] = {}
    for p in sources("twin_core/**/*.py"):
        src = package_of(p.relative_to(ROOT).parts)
        for name in imports(p.read_text()):
            parts = name.split(".")
            if parts[0] == "twin_core" and len(parts) > 1 and f"twin_core.{parts[1]}" != src:
                graph.setdefault(src, set()).add(f"twin_core.{parts[1]}")
    return graph


def cycle(graph: Mapping[str, set[str]]) -> list[str]:
    """One cycle of a directed graph (its nodes in order, the first repeated at the end), or []
    (depth-first search with the nodes on the current path marked)."""
    state: dict[str, int] = {}  # 1 on the path, 2 done
    path: list[str] = []

    def visit(node: str) -> list[str]:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt) :] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        path.pop()
        state[node] = 2
        return []

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return []


def draws_figures(source: str) -> bool:
    return any(n.split(".")[0] == "matplotlib" for n in imports(source))


def test_schemas_import_nothing_from_twin_core_or_services():
    bad = {
        str(p.relative_to(ROOT)): schemas_violations(p.read_text()) for p in sources("schemas/*.py")
    }
    assert {k: v for k, v in bad.items() if v} == {}


def test_twin_core_packages_import_each_other_without_a_cycle():
    assert cycle(package_graph()) == []


def test_twin_core_draws_figures_only_in_plots_modules():
    bad = [
        str(p.relative_to(ROOT))
        for p in sources("twin_core/**/*.py")
        if p.name != "plots.py" and draws_figures(p.read_text())
    ]
    assert bad == []


def test_each_rule_fails_on_a_case_that_breaks_it():
    """Synthetic cases: a schema calling into twin_core, the rtd <-> quality and feeder ->
    calibration -> scenes -> feeder cycles of before, a figure drawn outside plots.py."""
    schema = "from pydantic import BaseModel\nfrom twin_core.compartment.network import rsd\n"
    assert schemas_violations(schema) == [
        "twin_core.compartment.network",
        "twin_core.compartment.network.rsd",
    ]
    assert schemas_violations("from services.common import state_dir\n") == [
        "services.common",
        "services.common.state_dir",
    ]
    two = {"twin_core.rtd": {"twin_core.quality"}, "twin_core.quality": {"twin_core.rtd"}}
    assert cycle(two) == ["twin_core.quality", "twin_core.rtd", "twin_core.quality"]
    three = {
        "twin_core.feeder": {"twin_core.calibration"},
        "twin_core.calibration": {"twin_core.scenes"},
        "twin_core.scenes": {"twin_core.feeder", "twin_core.dem"},
    }
    assert cycle(three) == [
        "twin_core.calibration",
        "twin_core.scenes",
        "twin_core.feeder",
        "twin_core.calibration",
    ]
    assert cycle({"twin_core.scenes": {"twin_core.dem"}, "twin_core.dem": set()}) == []
    assert draws_figures("def f():\n    import matplotlib.pyplot as plt\n")
    assert not draws_figures("from twin_core.mixing.plots import plot_analysis\n")
