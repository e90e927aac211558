"""Resource estimates and budgets: available memory, the memory budget, and mesh sizes by h.

fempdl refuses work whose estimated size is far beyond the machine before
starting it, with a message giving the estimate, instead of failing inside
an allocator or gmsh after minutes:

* :func:`memory_budget`: the bytes a single allocation plan may take, by
  default half of the memory available now (``MemAvailable``);
* :func:`estimated_cells`: the cell count of a bundled geometry meshed at size
  h, cells ~ density * h^-dim, with the densities measured by
  :mod:`fempdl.core.meshgen` (gmsh 4.8.4; its docstring lists the sizes);
  :data:`DEFAULT_MAX_CELLS` is the default cell budget of ``mesh.load``.

This module imports nothing heavy, so the scene parser can use it.
"""
from __future__ import annotations

import dataclasses
import importlib.resources
import os
from pathlib import Path

__all__ = ["msh_size", "bundled_meshes", "DEFAULT_MEMORY_FRACTION", "DEFAULT_MAX_CELLS", "GEOMETRIES",
           "available_memory", "memory_budget", "format_bytes", "estimated_cells", "estimated_dofs", "Geometry"]

DEFAULT_MEMORY_FRACTION = 0.5


def bundled_meshes():
    """The folder of the bundled ``.msh`` files: ``meshes/`` beside the package in a
    checkout (or an editable install), ``fempdl/meshes/`` inside an installed wheel."""
    checkout = Path(__file__).resolve().parents[2] / "meshes"
    return checkout if checkout.is_dir() else importlib.resources.files("fempdl") / "meshes"


# About 1M P1 DOFs in 2D; gmsh takes about a minute and a few GB for it.
DEFAULT_MAX_CELLS = 2_000_000


@dataclasses.dataclass(frozen=True)
class Geometry:
    """Size facts of a bundled geometry: cells ~ ``cell_density`` * h^-``dim``;
    ``max_h`` is its shortest feature (a larger h no longer resolves it);
    ``vertices_per_cell`` the P1 DOFs per cell."""

    dim: int
    cell_density: float
    max_h: float
    vertices_per_cell: float


# cells ~ density * h^-dim: the larger of the densities at the coarsest and finest sizes of the
# bundled-mesh table in docs/meshes.md.
GEOMETRIES = {
    "lshape": Geometry(dim=2, cell_density=7.0, max_h=1.0, vertices_per_cell=0.53),
    "obstacle": Geometry(dim=2, cell_density=3.2, max_h=0.41, vertices_per_cell=0.54),
    "box": Geometry(dim=3, cell_density=4.9, max_h=1.0, vertices_per_cell=0.24),
}


def available_memory() -> int:
    """Bytes of memory available to new allocations now (Linux ``MemAvailable``; else free pages)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def memory_budget(fraction: float = DEFAULT_MEMORY_FRACTION) -> int:
    """``fraction`` of :func:`available_memory`, in bytes."""
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"fraction must be in (0, 1], got {fraction!r}")
    return int(fraction * available_memory())


def format_bytes(count: float) -> str:
    """``count`` bytes as e.g. ``"3.2 GiB"``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(count) < 1024 or unit == "PiB":
            return f"{count:.0f} {unit}" if unit == "B" else f"{count:.1f} {unit}"
        count /= 1024
    raise AssertionError("unreachable")


def estimated_cells(name: str, h: float) -> float:
    """Cells of the bundled geometry ``name`` meshed at size ``h`` (an estimate, within about 10%)."""
    geometry = GEOMETRIES[name]
    return geometry.cell_density * float(h) ** -geometry.dim


def estimated_dofs(name: str, h: float, degree: int = 1, components: int = 1) -> float:
    """Lagrange DOFs of degree ``degree`` with ``components`` per node on that mesh (an estimate)."""
    geometry = GEOMETRIES[name]
    return estimated_cells(name, h) * geometry.vertices_per_cell * degree ** geometry.dim * components


def msh_size(path) -> tuple[int, int] | None:
    """(nodes, dimension) of a gmsh ``.msh`` file from its headers alone, or None when they cannot
    be read as text (a binary file). The dimension is that of its highest entities (format 4), or 2
    when the file does not say (format 2)."""
    dim = 2
    try:
        with open(path, "rb") as fh:
            for line in fh:
                tag = line.strip()
                if tag == b"$Entities":
                    counts = [int(c) for c in next(fh).split()[:4]]
                    dim = max((d for d, n in enumerate(counts) if n > 0), default=2)
                elif tag == b"$Nodes":
                    head = next(fh).split()
                    return int(head[1] if len(head) >= 4 else head[0]), max(dim, 1)
    except (OSError, ValueError, IndexError, StopIteration):
        return None
    return None
