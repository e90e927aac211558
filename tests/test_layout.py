"""The package's floors: imports point down only (app -> methods -> layer -> core), with no cycle.

Every ``import`` of a fempdl module, at module level or inside a function, is
an edge; the test reads the sources' ASTs, so it sees imports that never run.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "fempdl"

# The floor of each module; a module may import its own floor and the ones below.
FLOORS = {"core": 0, "layer": 1, "methods": 2, "public": 3, "app": 4}
CORE = {"fempdl._dolfinx", "fempdl.resources", "fempdl.mesh", "fempdl.meshgen", "fempdl.problem", "fempdl.io"}
LAYER = {"fempdl.ksp_adjoint", "fempdl.system", "fempdl.implicit", "fempdl.bridge_torch", "fempdl.marker_flow"}
METHODS = {"fempdl.prdp", "fempdl.sip", "fempdl.hig", "fempdl.parallel"}


def floor_of(module: str) -> str:
    if module == "fempdl":
        return "public"                         # __init__ re-exports the public names
    if module in CORE or module.startswith("fempdl.forms"):
        return "core"
    if module in LAYER or module.startswith("fempdl.iterative"):
        return "layer"
    if module in METHODS:
        return "methods"
    if module.startswith("fempdl.app"):
        return "app"
    raise AssertionError(f"{module} is on no floor: add it to tests/test_layout.py")


def modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def imports_of(path: Path, name: str, known: set[str]) -> set[str]:
    """The fempdl modules ``path`` imports; ``from fempdl.x import y`` is an import of fempdl.x.y when that
    is a module, else of fempdl.x."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1] + ([base] if base else []))
            for alias in node.names:
                candidate = f"{base}.{alias.name}"
                found.add(candidate if candidate in known else base)
    return {m for m in found if m == "fempdl" or m.startswith("fempdl.")} - {name}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    mods = modules()
    return {name: imports_of(path, name, set(mods)) for name, path in mods.items()}


def test_every_module_has_a_floor(graph):
    for name in graph:
        floor_of(name)


def test_imports_point_down_only(graph):
    upward = [f"{a} ({floor_of(a)}) imports {b} ({floor_of(b)})"
              for a, targets in graph.items() for b in sorted(targets)
              if FLOORS[floor_of(b)] > FLOORS[floor_of(a)]]
    assert not upward, "\n".join(upward)


def test_no_import_cycle(graph):
    # The package module fempdl runs its __init__ before any submodule: importing
    # "fempdl.x" does not import the names __init__ re-exports, so edges to the
    # package itself are left out; test_imports_point_down_only keeps them out of
    # the floors below it.
    edges = {a: {b for b in targets if b != "fempdl"} for a, targets in graph.items()}
    state, stack, cycles = {}, [], []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == "open":
                cycles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = "done"

    for node in sorted(edges):
        if node not in state:
            visit(node)
    assert not cycles, "\n".join(cycles)


def test_the_checker_sees_a_cycle_and_an_upward_import(tmp_path):
    """The two checks fail where they should: a layer module importing the app, and a -> b -> a."""
    (tmp_path / "a.py").write_text("def f():\n    from fempdl.app import runner\n")
    assert imports_of(tmp_path / "a.py", "fempdl.system", {"fempdl.app.runner"}) == {"fempdl.app.runner"}
    assert FLOORS[floor_of("fempdl.app.runner")] > FLOORS[floor_of("fempdl.system")]
    (tmp_path / "b.py").write_text("from . import system\n")
    assert imports_of(tmp_path / "b.py", "fempdl.problem", {"fempdl.system"}) == {"fempdl.system"}
