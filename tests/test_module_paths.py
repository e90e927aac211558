"""Every module path the documentation names imports, as the module it names.

The package moved its modules into folders (``fempdl/core/mesh.py``, ...); the paths users were told
about (``fempdl.mesh``, ``fempdl.io``, ``fempdl.prdp``, ...) stay importable as thin re-exports, and
``from fempdl import mesh`` is the same module as ``import fempdl.mesh``.
"""
from __future__ import annotations

import importlib
import re
import subprocess
import sys
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCUMENTS = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md"), *(ROOT / "examples").glob("*.py")])
DOTTED = re.compile(r"\bfempdl(?:\.[A-Za-z_]\w*)+")


def documented_paths() -> list[str]:
    found = set()
    for path in DOCUMENTS:
        found.update(DOTTED.findall(path.read_text()))
    return sorted(found)


def resolve(dotted: str):
    """The object ``dotted`` names: the longest prefix that imports as a module, then attributes.
    A module reached through an attribute must be the module of that name (``fempdl.mesh`` must not
    be another module that ``fempdl``'s lazy names hand out)."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
            break
        except ModuleNotFoundError:
            continue
    for k in range(cut, len(parts)):
        obj = getattr(obj, parts[k])
        if isinstance(obj, types.ModuleType):
            assert obj.__name__ == ".".join(parts[:k + 1]), \
                f"{'.'.join(parts[:k + 1])} is the module {obj.__name__}, not an importable module of that name"
    return obj


def test_the_docs_name_module_paths():
    paths = documented_paths()
    assert {"fempdl.core.io", "fempdl.prdp.k_eps", "fempdl.methods.sip"} <= set(paths), paths


@pytest.mark.parametrize("dotted", documented_paths())
def test_every_documented_path_resolves(dotted):
    resolve(dotted)


@pytest.mark.parametrize("path, names", [
    ("fempdl.mesh", ["load", "available", "as_tagged", "TaggedMesh"]),
    ("fempdl.io", ["write_fields", "write_xdmf", "plot_fields", "nodal_field"]),
    ("fempdl.prdp", ["PRDP", "k_eps"]),
    ("fempdl.ksp_adjoint", ["KSPOptions", "CappedSolver", "SolveStats"]),
    ("fempdl.bridge_torch", ["SolveLayer"]),
])
def test_public_module_paths_import(path, names):
    module = importlib.import_module(path)
    for name in names:
        assert callable(getattr(module, name)), f"{path}.{name}"


def test_mesh_and_io_are_one_module_whichever_import_comes_first():
    """``from fempdl import mesh`` before or after ``import fempdl.mesh`` gives the same module, whose
    functions are the ones in fempdl.core; ``from fempdl.io import write_fields`` works."""
    code = ("import sys\n"
            "first = sys.argv[1]\n"
            "if first == 'attribute':\n"
            "    from fempdl import mesh, io\n"
            "import fempdl.mesh, fempdl.io\n"
            "from fempdl import mesh, io\n"
            "from fempdl.io import write_fields\n"
            "import fempdl.core.mesh, fempdl.core.io\n"
            "assert mesh is fempdl.mesh and io is fempdl.io, (mesh, io)\n"
            "assert fempdl.mesh.load is fempdl.core.mesh.load\n"
            "assert write_fields is fempdl.core.io.write_fields\n"
            "assert fempdl.mesh.load('lshape').mesh.topology.dim == 2\n")
    for first in ("attribute", "module"):
        done = subprocess.run([sys.executable, "-c", code, first], capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-3000:]


def test_the_card_modules_are_attributes_of_fempdl_in_a_fresh_interpreter():
    """``import fempdl`` alone reaches the card's modules (``fempdl.ksp_adjoint.KSPOptions``) and every public
    name, and each is the one object whichever path names it."""
    code = ("import fempdl\n"
            "assert fempdl.ksp_adjoint.KSPOptions is fempdl.KSPOptions\n"
            "assert fempdl.bridge_torch.SolveLayer is fempdl.SolveLayer\n"
            "assert fempdl.prdp.PRDP is fempdl.PRDP and fempdl.prdp.k_eps is fempdl.k_eps\n"
            "assert fempdl.Caps(3).max_it == 3\n"
            "missing = [name for name in fempdl.__all__ if getattr(fempdl, name, None) is None]\n"
            "assert not missing, missing\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
