"""Gmsh geometry of the bundled meshes, and the script that regenerates them.

Three unstructured meshes ship with fempdl (in the top-level ``meshes/``); each is
built here from a gmsh (OpenCASCADE) geometry for a target mesh size ``h``.

``"lshape"``
    2D L-shape ``[-1, 1]^2`` minus ``[0, 1] x [-1, 0]``, with the reentrant
    corner at the origin (the classic corner-singularity domain). Uniform size.
``"obstacle"``
    2D channel ``[0, 2.2] x [0, 0.41]`` with a circular hole of radius 0.05
    centred at ``(0.2, 0.2)`` (the DFG flow-around-a-cylinder benchmark).
    The size falls from ``h`` to ``h / 3`` towards the circle.
``"box"``
    3D unit cube ``[0, 1]^3`` in tetrahedra. Uniform size.

Every cell has tag ``CELL_TAG``; every exterior facet one tag of
``FACET_TAGS[name]``: "reentrant" is the two edges meeting at the origin (``x = 0, y <= 0`` and
``y = 0, x >= 0``), "outer" the other four; "inlet" is ``x = 0``, "outlet"
``x = 2.2``, "walls" ``y = 0`` and ``y = 0.41``; "bottom" is ``z = 0``, "top"
``z = 1``, "sides" the four vertical faces. Every exterior facet carries
exactly one facet tag; interior facets carry none.

Cell and DOF counts per h are in docs/meshes.md. Regenerate the committed files with
``python tools/regenerate_meshes.py`` (options ``--out DIR``, ``--name NAME``, ``--h H``). Meshing runs
on one thread with the user's gmsh configuration files ignored, so the output is reproducible for a
given gmsh version.
"""
from __future__ import annotations

import contextlib
import ctypes
import math
import numbers
import signal
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from mpi4py import MPI

from fempdl.core import _dolfinx
from fempdl.core._dolfinx import gmsh  # imported there with Python's SIGINT handler kept

CELL_TAG = 1
#: The gmsh release (major, minor) that wrote the committed files: Debian
#: bookworm's 4.8. Other releases mesh the same geometry and size slightly
#: differently (PyPI's 4.15: 2802 L-shape cells against 2800).
COMMITTED_WITH_GMSH = (4, 8)
FACET_TAGS: dict[str, dict[str, int]] = {
    "lshape": {"outer": 1, "reentrant": 2},
    "obstacle": {"inlet": 1, "outlet": 2, "walls": 3, "obstacle": 4},
    "box": {"bottom": 1, "top": 2, "sides": 3},
}

BUNDLED_DIR = Path(__file__).resolve().parents[2] / "meshes"   # the checkout's top-level folder

# Tolerance for classifying boundary pieces by their bounding box: OpenCASCADE
# enlarges every bounding box by its 1e-7 confusion tolerance.
_TOL = 1e-6

_CHANNEL_LENGTH = 2.2
_CHANNEL_HEIGHT = 0.41
_OBSTACLE_CENTRE = (0.2, 0.2)
_OBSTACLE_RADIUS = 0.05


@dataclass(frozen=True)
class _MeshSpec:
    """How to build one bundled mesh: its dimension, default size and geometry."""

    dim: int
    default_h: float
    build: Callable[[float], None]


def _set_max_size(h: float) -> None:
    """Cap the mesh size at ``h``, with no other size source but a background field.

    Point sizes, curvature and extension from the boundary are off, so without
    a field the mesh is uniform at size ``h``.
    """
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeMax", h)


def _add_physical_groups(dim: int, cells: list[int], pieces: dict[str, list[int]],
                         tags: dict[str, int]) -> None:
    """Tag the cells with ``CELL_TAG`` and each boundary piece with its tag."""
    gmsh.model.addPhysicalGroup(dim, cells, CELL_TAG)
    gmsh.model.setPhysicalName(dim, CELL_TAG, "domain")
    for label, tag in tags.items():
        gmsh.model.addPhysicalGroup(dim - 1, pieces[label], tag)
        gmsh.model.setPhysicalName(dim - 1, tag, label)


def _classify_boundary(dim: int, classify: Callable[[tuple[float, ...]], str],
                       labels: dict[str, int]) -> dict[str, list[int]]:
    """Group the boundary entities of the (single) domain by ``classify(bbox)``."""
    pieces: dict[str, list[int]] = {label: [] for label in labels}
    for _, tag in gmsh.model.getEntities(dim - 1):
        pieces[classify(gmsh.model.getBoundingBox(dim - 1, tag))].append(tag)
    empty = [label for label, tags in pieces.items() if not tags]
    if empty:
        raise RuntimeError(f"gmsh geometry has no boundary entity for {empty}")
    return pieces


def _build_lshape(h: float) -> None:
    occ = gmsh.model.occ
    square = occ.addRectangle(-1.0, -1.0, 0.0, 2.0, 2.0)
    cut_out = occ.addRectangle(0.0, -1.0, 0.0, 1.0, 1.0)
    domain, _ = occ.cut([(2, square)], [(2, cut_out)])
    occ.synchronize()

    def classify(bbox):
        xmin, ymin, _, xmax, ymax, _ = bbox
        on_x_axis_right = abs(ymin) < _TOL and abs(ymax) < _TOL and xmin > -_TOL
        on_y_axis_below = abs(xmin) < _TOL and abs(xmax) < _TOL and ymax < _TOL
        return "reentrant" if on_x_axis_right or on_y_axis_below else "outer"

    tags = FACET_TAGS["lshape"]
    pieces = _classify_boundary(2, classify, tags)
    _add_physical_groups(2, [tag for _, tag in domain], pieces, tags)
    _set_max_size(h)


def _build_obstacle(h: float) -> None:
    occ = gmsh.model.occ
    channel = occ.addRectangle(0.0, 0.0, 0.0, _CHANNEL_LENGTH, _CHANNEL_HEIGHT)
    hole = occ.addDisk(*_OBSTACLE_CENTRE, 0.0, _OBSTACLE_RADIUS, _OBSTACLE_RADIUS)
    domain, _ = occ.cut([(2, channel)], [(2, hole)])
    occ.synchronize()

    def classify(bbox):
        xmin, ymin, _, xmax, ymax, _ = bbox
        if xmax < _TOL:
            return "inlet"
        if xmin > _CHANNEL_LENGTH - _TOL:
            return "outlet"
        if ymax < _TOL or ymin > _CHANNEL_HEIGHT - _TOL:
            return "walls"
        return "obstacle"

    tags = FACET_TAGS["obstacle"]
    pieces = _classify_boundary(2, classify, tags)
    _add_physical_groups(2, [tag for _, tag in domain], pieces, tags)
    _set_max_size(h)

    # Resolve the circle and the start of the wake, where the flow varies most.
    field = gmsh.model.mesh.field
    distance = field.add("Distance")
    field.setNumbers(distance, "CurvesList", pieces["obstacle"])
    field.setNumber(distance, "NumPointsPerCurve", 100)
    threshold = field.add("Threshold")
    field.setNumber(threshold, "InField", distance)
    field.setNumber(threshold, "SizeMin", h / 3.0)
    field.setNumber(threshold, "SizeMax", h)
    field.setNumber(threshold, "DistMin", 0.0)
    field.setNumber(threshold, "DistMax", 0.3)
    field.setAsBackgroundMesh(threshold)


def _build_box(h: float) -> None:
    occ = gmsh.model.occ
    cube = occ.addBox(0.0, 0.0, 0.0, 1.0, 1.0, 1.0)
    occ.synchronize()

    def classify(bbox):
        _, _, zmin, _, _, zmax = bbox
        if zmax < _TOL:
            return "bottom"
        if zmin > 1.0 - _TOL:
            return "top"
        return "sides"

    tags = FACET_TAGS["box"]
    pieces = _classify_boundary(3, classify, tags)
    _add_physical_groups(3, [cube], pieces, tags)
    _set_max_size(h)


_SPECS: dict[str, _MeshSpec] = {
    "lshape": _MeshSpec(dim=2, default_h=0.05, build=_build_lshape),
    "obstacle": _MeshSpec(dim=2, default_h=0.035, build=_build_obstacle),
    "box": _MeshSpec(dim=3, default_h=0.1, build=_build_box),
}

DEFAULT_H: dict[str, float] = {name: spec.default_h for name, spec in _SPECS.items()}
GEOMETRIC_DIM: dict[str, int] = {name: spec.dim for name, spec in _SPECS.items()}


def names() -> list[str]:
    """Names of the bundled meshes."""
    return list(_SPECS)


def check_h(h) -> float | None:
    """Validate a mesh size: ``None`` (use the default) or a finite float > 0.

    Raises:
        TypeError: ``h`` is not a real number.
        ValueError: ``h`` is not finite or not positive.
    """
    if h is None:
        return None
    if isinstance(h, bool) or not isinstance(h, numbers.Real):
        raise TypeError(f"h must be a positive float or None, got {type(h).__name__} {h!r}")
    if not math.isfinite(h) or h <= 0:
        raise ValueError(f"h must be a finite mesh size > 0, got {h!r}; "
                         "pass e.g. h=0.05, or h=None for the bundled default")
    return float(h)


def _spec(name) -> _MeshSpec:
    if not isinstance(name, str):
        raise TypeError(f"name must be a str, got {type(name).__name__} {name!r}")
    if name not in _SPECS:
        raise ValueError(f"name must be one of the bundled meshes {names()}, got {name!r}")
    return _SPECS[name]


@contextlib.contextmanager
def gmsh_session(active: bool = True) -> Iterator[None]:
    """Initialize the gmsh API for the duration of the block, quietly.

    The block owns the gmsh session: gmsh 4.8 cannot report whether it is
    already initialized, so a session the caller opened earlier also ends
    here. With ``active=False`` (MPI ranks that do not mesh) nothing happens.
    """
    if not active:
        yield
        return
    # gmsh sets the process-wide OpenMP thread count (to 1) when it starts; torch
    # shares that runtime, so without this every torch kernel after a mesh load
    # would run on one thread.
    openmp = _openmp_runtime()
    threads = openmp.omp_get_max_threads() if openmp is not None else None
    # gmsh >= 4.9 sets SIGINT to the OS default in initialize() and fails to
    # restore it in finalize(), so Ctrl-C would then kill the process without
    # unwinding: put back the handler in place before.
    sigint = signal.getsignal(signal.SIGINT) if threading.current_thread() is threading.main_thread() else None
    # Ignoring gmshrc / gmsh-options keeps meshes reproducible across users.
    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        yield
    finally:
        gmsh.finalize()
        if sigint is not None:
            signal.signal(signal.SIGINT, sigint)
        if threads is not None:
            openmp.omp_set_num_threads(threads)


def _openmp_runtime():
    """The OpenMP runtime gmsh uses (the process's libgomp), or None."""
    try:
        return ctypes.CDLL("libgomp.so.1")
    except OSError:
        return None


def _mesh_model(name: str, h: float | None) -> None:
    """Build and mesh bundled geometry ``name`` in a fresh gmsh model."""
    spec = _SPECS[name]
    gmsh.model.add(name)
    spec.build(spec.default_h if h is None else h)
    gmsh.model.mesh.generate(spec.dim)


def generate(name: str, h: float | None = None, comm=MPI.COMM_WORLD, rank: int = 0):
    """Mesh a bundled geometry with gmsh on ``rank`` and distribute it over ``comm``.

    Collective on ``comm``.

    Args:
        name: One of :func:`names`.
        h: Target mesh size; ``None`` uses :data:`DEFAULT_H` (the committed file's).
        comm: Communicator the mesh is distributed over.
        rank: The rank that runs gmsh.

    Returns:
        ``(mesh, cell_tags, facet_tags)`` with the tags of :data:`CELL_TAG` and
        :data:`FACET_TAGS`; 2D meshes have 2D coordinates (gdim 2).
    """
    spec = _spec(name)
    h = check_h(h)
    with gmsh_session(active=comm.rank == rank):
        if comm.rank == rank:
            _mesh_model(name, h)
        return _dolfinx.model_to_mesh(gmsh.model, comm, rank, gdim=spec.dim)


def write_msh(name: str, path, h: float | None = None) -> Path:
    """Mesh a bundled geometry and write it as a gmsh 4.1 ASCII ``.msh`` file.

    Only elements in physical groups are written, which is what DOLFINx reads.

    Returns:
        The path written.
    """
    _spec(name)
    h = check_h(h)
    path = Path(path)
    with gmsh_session():
        _mesh_model(name, h)
        gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
        gmsh.option.setNumber("Mesh.Binary", 0)
        gmsh.write(str(path))
    return path
