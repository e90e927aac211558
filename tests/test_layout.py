"""The package's floors: imports point down only, and inside a floor from a later room to an earlier one.

A module's floor and room come from its package path (:data:`FLOORS`): ``fempdl/core/`` is the
bottom floor, ``fempdl/app/`` the top one; the design card's import paths (``ksp_adjoint.py``,
``bridge_torch.py``, ``prdp.py``, ``mesh.py`` and ``io.py``) are placed by name.
Every ``import`` of a fempdl module, at module level or inside a function, is an edge; the test
reads the sources' ASTs, so it
sees imports that never run. A module may import its own room (no cycle), the earlier rooms of its
floor, and every floor below. ``fempdl/iterative/`` is torch-only: nothing it imports, directly or
through other fempdl modules, imports DOLFINx, UFL or basix.
"""
from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "fempdl"

# The design card's module paths: re-exports for users; nothing inside the package imports them.
PUBLIC_PATHS = ["fempdl.ksp_adjoint", "fempdl.bridge_torch", "fempdl.prdp"]
# Floors bottom to top, each a list of rooms in order; a room is a list of module prefixes.
FLOORS = [
    ("core", [["fempdl.core._dolfinx", "fempdl.core.checks", "fempdl.core.resources", "fempdl.core.parallel",
               "fempdl.core.meshgen", "fempdl.core.nullspaces", "fempdl.core.locks", "fempdl.core.ranks",
               "fempdl.core.pointwise", "fempdl.core.pointwise_forms"],
              ["fempdl.core.mesh", "fempdl.core.problem_base", "fempdl.core.matrices"],
              ["fempdl.core.problem", "fempdl.core.nonlinear_problem", "fempdl.core.io", "fempdl.core.time_series"],
              ["fempdl.forms"], ["fempdl.core"], ["fempdl.mesh", "fempdl.io"]]),
    ("solve", [["fempdl.solve.caps", "fempdl.solve.options", "fempdl.solve.option_checks",
                "fempdl.solve.newton_options", "fempdl.solve.round_off",
                "fempdl.solve.scaling", "fempdl.solve.default_solver"],
               ["fempdl.solve.stats", "fempdl.solve.petsc", "fempdl.solve.newton_stats", "fempdl.solve.newton_stop",
                "fempdl.solve.health", "fempdl.solve.lagged_preconditioner"],
               ["fempdl.solve.snes", "fempdl.solve.capped_solver", "fempdl.solve.batched_calls"],
               ["fempdl.solve.assembly", "fempdl.solve.control_forms", "fempdl.solve.call_state",
                "fempdl.solve.newton_solvers"],
               ["fempdl.solve.linear_system", "fempdl.solve.newton_reverse", "fempdl.solve.newton_run"],
               ["fempdl.solve.nonlinear_system"],
               ["fempdl.solve"]]),
    ("iterative", [["fempdl.iterative"]]),
    ("layer", [["fempdl.layer.cap_target", "fempdl.layer.implicit_diff", "fempdl.layer.unrolled_diff",
                "fempdl.layer.observation", "fempdl.layer.healthy_calls", "fempdl.layer.network"],
               ["fempdl.layer.system_layer", "fempdl.layer.newton_unrolled"],
               ["fempdl.layer.newton_layer", "fempdl.layer.revolve", "fempdl.layer.rollout_checkpoint",
                "fempdl.layer.rollout_inputs"],
               ["fempdl.layer.rollout"],
               ["fempdl.layer.solve_layer"], ["fempdl.layer.reference"], ["fempdl.layer"]]),
    ("methods", [["fempdl.methods"]]),
    # __init__ (the public names, lazily) and the card's import paths, thin re-exports of the floors below
    ("public", [["fempdl"], PUBLIC_PATHS]),
    ("app", [["fempdl.app.schema", "fempdl.app.scenes", "fempdl.app.scene_budget"], ["fempdl.app.tasks"],
             ["fempdl.app.scene"], ["fempdl.app.runs"], ["fempdl.app.reports"],
             ["fempdl.app.cli", "fempdl.app.commands"], ["fempdl.app"]]),
]
# Third-party packages the torch-only floor must not reach.
FEM_PACKAGES = ("dolfinx", "ufl", "basix", "ffcx")


def place(module: str) -> tuple[int, int, str]:
    """(floor index, room index, floor name) of ``module``: the room of its longest matching prefix."""
    best = None
    for f, (floor, rooms) in enumerate(FLOORS):
        for r, room in enumerate(rooms):
            for prefix in room:
                if (module == prefix or module.startswith(prefix + ".")) and (best is None or len(prefix) > best[0]):
                    best = (len(prefix), f, r, floor)
    if best is None:
        raise AssertionError(f"{module} is on no floor: give its package a place in tests/test_layout.py")
    return best[1], best[2], best[3]


def wrong_way(importer: str, imported: str) -> str | None:
    """Why ``importer`` may not import ``imported`` (None if it may)."""
    (f1, r1, floor1), (f2, r2, floor2) = place(importer), place(imported)
    if f2 > f1:
        return f"{importer} ({floor1}) imports {imported} ({floor2}), a floor above"
    if f2 == f1 and r2 > r1:
        return f"{importer} imports {imported}, a later room of the {floor1} floor"
    return None


def modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def imports_of(path: Path, name: str, known: set[str], *, external: bool = False) -> set[str]:
    """The fempdl modules ``path`` imports (with ``external``: the top-level names of everything it
    imports); ``from fempdl.x import y`` is an import of fempdl.x.y when that is a module, else of fempdl.x."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1]
                                + ([base] if base else []))
            for alias in node.names:
                candidate = f"{base}.{alias.name}"
                found.add(candidate if candidate in known else base)
    if external:
        return {m.split(".")[0] for m in found}
    return {m for m in found if m == "fempdl" or m.startswith("fempdl.")} - {name}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    mods = modules()
    return {name: imports_of(path, name, set(mods)) for name, path in mods.items()}


def test_every_module_has_a_place(graph):
    for name in graph:
        place(name)


def test_no_module_is_hidden_from_git():
    """A .gitignore pattern must not hide package files: a module present here but not committed
    passes every local test and is missing from a fresh clone (``runs/`` once hid ``fempdl/app/runs/``)."""
    git = subprocess.run(["git", "-C", str(PACKAGE.parent), "rev-parse", "--is-inside-work-tree"],
                         capture_output=True, text=True)
    if git.returncode != 0:
        pytest.skip("not a git checkout")
    files = [str(p.relative_to(PACKAGE.parent)) for p in PACKAGE.rglob("*") if p.is_file()
             and "__pycache__" not in p.parts]
    ignored = subprocess.run(["git", "-C", str(PACKAGE.parent), "check-ignore", "--no-index", *files],
                             capture_output=True, text=True).stdout.split()
    assert not ignored, f"files of the package that .gitignore hides: {ignored}"


def test_imports_point_down_only(graph):
    wrong = [why for a, targets in graph.items() for b in sorted(targets) if (why := wrong_way(a, b))]
    assert not wrong, "\n".join(wrong)


def test_nothing_inside_imports_the_card_paths(graph):
    """``fempdl.ksp_adjoint``, ``fempdl.bridge_torch`` and ``fempdl.prdp`` are the users' doors: a module of the
    package importing one would reach down through the public floor instead of the room that defines the name."""
    inside = {a: sorted(set(targets) & set(PUBLIC_PATHS)) for a, targets in graph.items() if a not in PUBLIC_PATHS}
    assert not {a: t for a, t in inside.items() if t}


def test_no_import_cycle(graph):
    # The package module fempdl runs its __init__ before any submodule: importing
    # "fempdl.x" does not import the names __init__ re-exports, so edges to the
    # package itself are left out; test_imports_point_down_only keeps them out of
    # the floors below it.
    edges = {a: {b for b in targets if b != "fempdl"} for a, targets in graph.items()}
    assert not find_cycles(edges), "\n".join(find_cycles(edges))


def find_cycles(edges: dict[str, set[str]]) -> list[str]:
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
    return cycles


def fem_imports_reached(start: str, graph: dict[str, set[str]], paths: dict[str, Path]) -> dict[str, set[str]]:
    """{module: FEM packages it imports} for every fempdl module reachable from ``start``."""
    seen, todo, out = set(), [start], {}
    while todo:
        name = todo.pop()
        if name in seen or name not in paths:
            continue
        seen.add(name)
        fem = imports_of(paths[name], name, set(paths), external=True) & set(FEM_PACKAGES)
        if fem:
            out[name] = fem
        todo.extend(graph.get(name, ()))
    return out


def test_iterative_reaches_no_dolfinx(graph):
    paths = modules()
    found = {}
    for name in (n for n in paths if n.startswith("fempdl.iterative")):
        found.update(fem_imports_reached(name, graph, paths))
    assert not found, f"fempdl/iterative/ reaches DOLFINx/UFL through {found}"


def test_the_checker_sees_wrong_way_imports_cycles_and_dolfinx(tmp_path):
    """The checks fail where they should: an import from a floor above, from a later room of the same
    floor (app's order), a -> b -> a, and a DOLFINx import reached from iterative/."""
    (tmp_path / "a.py").write_text("def f():\n    from fempdl.app.runs import runner\n")
    assert imports_of(tmp_path / "a.py", "fempdl.solve.linear_system", {"fempdl.app.runs.runner"}) \
        == {"fempdl.app.runs.runner"}
    assert "a floor above" in wrong_way("fempdl.solve.linear_system", "fempdl.app.runs.runner")
    assert "later room of the app floor" in wrong_way("fempdl.app.scene", "fempdl.app.runs.runner")
    assert "later room of the app floor" in wrong_way("fempdl.app.schema", "fempdl.app.tasks.base")
    assert "later room of the solve floor" in wrong_way("fempdl.solve.options", "fempdl.solve.capped_solver")
    assert "a floor above" in wrong_way("fempdl.solve.linear_system", "fempdl.ksp_adjoint")
    assert wrong_way("fempdl.app.runs.runner", "fempdl.app.scene") is None
    assert wrong_way("fempdl.bridge_torch", "fempdl.layer.solve_layer") is None
    (tmp_path / "b.py").write_text("from . import linear_system\n")
    assert imports_of(tmp_path / "b.py", "fempdl.core.problem", {"fempdl.core.linear_system"}) \
        == {"fempdl.core.linear_system"}
    assert find_cycles({"x": {"y"}, "y": {"x"}}) == ["x -> y -> x"]
    (tmp_path / "c.py").write_text("import numpy\nfrom fempdl.solve import helper\n")
    (tmp_path / "helper.py").write_text("import ufl.algorithms\n")
    paths = {"fempdl.iterative.c": tmp_path / "c.py", "fempdl.solve.helper": tmp_path / "helper.py"}
    assert fem_imports_reached("fempdl.iterative.c", {"fempdl.iterative.c": {"fempdl.solve.helper"}}, paths) \
        == {"fempdl.solve.helper": {"ufl"}}


def test_one_line_import_of_the_public_names():
    """``from fempdl import ...`` gives every public name, from the module that defines it."""
    import fempdl
    from fempdl import PRDP, CappedSolver, KSPOptions, Problem, SolveLayer, SolverFailedError, forms, mesh
    assert (Problem.__module__, SolveLayer.__module__, CappedSolver.__module__) \
        == ("fempdl.core.problem", "fempdl.layer.solve_layer", "fempdl.solve.capped_solver")
    assert KSPOptions is importlib.import_module("fempdl.ksp_adjoint").KSPOptions
    assert SolveLayer is importlib.import_module("fempdl.bridge_torch").SolveLayer
    assert CappedSolver is importlib.import_module("fempdl.ksp_adjoint").CappedSolver
    assert PRDP is importlib.import_module("fempdl.prdp").PRDP
    assert issubclass(SolverFailedError, RuntimeError) and callable(mesh.load) and forms.poisson.problem
    for name in fempdl.__all__:
        assert getattr(fempdl, name) is not None
    with pytest.raises(AttributeError, match="has no attribute 'Nothing'"):
        _ = fempdl.Nothing


def test_no_module_is_too_long_to_hold_in_one_head():
    """No module of the package is over about 400 lines: a longer one holds more than one job."""
    long = {str(p.relative_to(PACKAGE.parent)): n for p in PACKAGE.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 430}
    assert not long, long


def test_help_and_import_load_neither_dolfinx_nor_torch():
    """``import fempdl`` and ``fempdl --help`` answer without loading DOLFINx, PETSc, MPI or torch (they take
    seconds to import); the public names load them on first use."""
    code = ("import sys, contextlib, io\n"
            "import fempdl\n"
            "from fempdl.app import cli\n"
            "with contextlib.redirect_stdout(io.StringIO()) as out, contextlib.suppress(SystemExit):\n"
            "    cli.main(['--help'])\n"
            "assert 'usage: fempdl' in out.getvalue()\n"
            "print(sorted(m for m in ('dolfinx', 'petsc4py', 'mpi4py', 'torch', 'ufl') if m in sys.modules))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"
