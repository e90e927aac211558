"""Load the bundled meshes, or any gmsh ``.msh`` file, as DOLFINx meshes with tags.

Bundled meshes (``meshes/*.msh``, built by :mod:`fempdl.core.meshgen`):

==========  ====  ====  ==============  =====================================
name        tdim  gdim  cells / P1 DOF  facet tags
==========  ====  ====  ==============  =====================================
"lshape"    2     2     2800 / 1481     outer = 1, reentrant = 2
"obstacle"  2     2     2555 / 1373     inlet = 1, outlet = 2, walls = 3,
                                        obstacle = 4
"box"       3     3     4923 / 1187     bottom = 1, top = 2, sides = 3
==========  ====  ====  ==============  =====================================

- ``"lshape"``: ``[-1, 1]^2`` minus ``[0, 1] x [-1, 0]``; "reentrant" is the
  two edges meeting at the reentrant corner (the origin), "outer" the rest.
- ``"obstacle"``: the DFG cylinder channel ``[0, 2.2] x [0, 0.41]`` minus the
  disk of radius 0.05 at ``(0.2, 0.2)``; inlet ``x = 0``, outlet ``x = 2.2``,
  walls ``y = 0`` and ``y = 0.41``, obstacle the circle (refined towards it).
- ``"box"``: the unit cube in tetrahedra; bottom ``z = 0``, top ``z = 1``,
  sides the four vertical faces.

Every cell carries cell tag 1; every exterior facet carries exactly one facet
tag. ``TaggedMesh.facet_tag("inlet")`` turns a boundary name into its tag::

    msh = load("obstacle")
    mesh, cell_tags, facet_tags = msh
    inlet_facets = facet_tags.find(msh.facet_tag("inlet"))

``load(name, h=0.02)`` meshes a bundled geometry at another size on the fly.
"""
from __future__ import annotations

import hashlib
import importlib.resources
import os
import stat
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, TypeVar

from mpi4py import MPI
import dolfinx.mesh
import numpy as np

from fempdl.core import _dolfinx, meshgen
from fempdl.core._dolfinx import gmsh  # imported there with Python's SIGINT handler kept
from fempdl.core.checks import is_int
from fempdl.core.resources import DEFAULT_MAX_CELLS, GEOMETRIES, bundled_meshes, estimated_cells

__all__ = ["TaggedMesh", "as_tagged", "available", "load"]

_T = TypeVar("_T")


@dataclass(frozen=True)
class TaggedMesh:
    """A DOLFINx mesh with its cell and facet tags and the names of the facet tags.

    Unpacks as ``mesh, cell_tags, facet_tags = tagged``.

    Attributes:
        mesh: The distributed ``dolfinx.mesh.Mesh``.
        cell_tags: ``MeshTags`` on cells, or ``None`` for a bare mesh.
        facet_tags: ``MeshTags`` on facets, or ``None`` for a bare mesh.
        name: The bundled name, the file path, or the mesh's own name.
        facet_labels: Boundary name -> facet tag (empty if the tags have no names).
    """

    mesh: dolfinx.mesh.Mesh
    cell_tags: Any
    facet_tags: Any
    name: str
    facet_labels: Mapping[str, int] = field(default_factory=dict, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "facet_labels", MappingProxyType(dict(self.facet_labels)))

    def __iter__(self) -> Iterator:
        return iter((self.mesh, self.cell_tags, self.facet_tags))

    @property
    def comm(self) -> MPI.Comm:
        return self.mesh.comm

    @property
    def tdim(self) -> int:
        return self.mesh.topology.dim

    @property
    def gdim(self) -> int:
        return self.mesh.geometry.dim

    def facet_tag(self, label: str) -> int:
        """The integer facet tag of the boundary piece called ``label``.

        Raises:
            TypeError: ``label`` is not a str.
            ValueError: the mesh has no tag called ``label`` (the message lists
                the names it has).
        """
        if not isinstance(label, str):
            raise TypeError(f"label must be a str naming a boundary piece, "
                            f"got {type(label).__name__} {label!r}")
        if not self.facet_labels:
            raise ValueError(
                f"label {label!r}: mesh {self.name!r} has no named facet tags (a bare mesh, or a .msh "
                "file without physical names); use the integer tags in facet_tags.values directly, "
                "or give the facet physical groups names in gmsh")
        if label not in self.facet_labels:
            raise ValueError(f"label must be one of {sorted(self.facet_labels)} for mesh {self.name!r}, "
                             f"got {label!r}")
        return self.facet_labels[label]


def available() -> list[str]:
    """Names of the bundled meshes, for :func:`load`."""
    return meshgen.names()


def as_tagged(obj) -> TaggedMesh:
    """``obj`` as a :class:`TaggedMesh`: returned as is, or a bare Mesh wrapped without tags.

    Raises:
        TypeError: ``obj`` is neither a TaggedMesh nor a ``dolfinx.mesh.Mesh``.
    """
    if isinstance(obj, TaggedMesh):
        return obj
    if isinstance(obj, dolfinx.mesh.Mesh):
        return TaggedMesh(obj, None, None, obj.name)
    raise TypeError(f"mesh must be a fempdl.core.mesh.TaggedMesh (from fempdl.core.mesh.load) or a "
                    f"dolfinx.mesh.Mesh, got {type(obj).__name__}")


def load(name_or_path, comm: MPI.Comm = MPI.COMM_WORLD, *, h: float | None = None,
         rank: int = 0, gdim: int | None = None, max_cells: int = DEFAULT_MAX_CELLS) -> TaggedMesh:
    """Load a bundled mesh by name, or a gmsh ``.msh`` file by path.

    Collective on ``comm``: gmsh runs on ``rank``, DOLFINx distributes the mesh.

    Args:
        name_or_path: One of :func:`available`, or a path to a ``.msh`` file.
        comm: Communicator the mesh is distributed over.
        h: For a bundled name only: mesh the geometry at this size instead of
            loading the committed file (sizes vs cell counts: docs/meshes.md).
        rank: The rank that reads or meshes with gmsh.
        gdim: For a path only: geometric dimension; ``None`` takes the
            smallest that holds the node coordinates (all ``z = 0`` -> 2).
        max_cells: For ``h``: refuse sizes whose estimated cell count
            (:func:`fempdl.core.resources.estimated_cells`) exceeds this, before
            gmsh runs (h = 1e-8 would take many GB and minutes).

    Returns:
        The mesh with its tags; bundled meshes have named facet tags, a file
        has them if its facet physical groups have names.

    Raises:
        TypeError: an argument has the wrong type.
        ValueError: unknown name, ``h`` with a path or ``h`` not finite and > 0,
            ``h`` larger than the geometry's shortest feature or giving more
            than ``max_cells`` cells, ``gdim`` with a bundled name or invalid,
            a path that is not a regular file (a FIFO, a device), or an unreadable file.
        FileNotFoundError: the path does not exist.
        IsADirectoryError: the path is a directory.
    """
    rank = _check_int_choice("rank", rank, range(comm.size))
    h = meshgen.check_h(h)
    if isinstance(name_or_path, str) and name_or_path in available():
        tagged = _load_bundled(name_or_path, comm, h, rank, gdim, max_cells)
    else:
        path = _as_msh_path(name_or_path)
        if h is not None:
            raise ValueError(f"h applies to bundled meshes only, got h={h!r} with the file {str(path)!r}; "
                             "mesh the file's geometry at that size with gmsh, or load a bundled name")
        if gdim is not None:
            gdim = _check_int_choice("gdim", gdim, (1, 2, 3))
        tagged = _read_msh(path, comm, rank, gdim)
    check_unfolded(tagged.mesh, str(name_or_path))
    return tagged


def check_unfolded(msh, name: str = "the mesh") -> None:
    """Raise ValueError (on every rank) when two cells sharing an interior facet lie on the same side of
    it: a folded mesh, with inverted or overlapping cells, whose integrals count the overlap twice
    (it loads and solves without complaint otherwise). A cell with no volume is refused too.
    Meshes of a lower dimension than their space (surfaces) are not checked."""
    topology, tdim, gdim = msh.topology, msh.topology.dim, msh.geometry.dim
    if tdim != gdim or tdim < 2:
        return
    topology.create_connectivity(tdim - 1, tdim)
    f2c = topology.connectivity(tdim - 1, tdim)
    facets = np.flatnonzero(np.diff(f2c.offsets) == 2).astype(np.int32)
    cells = f2c.array[f2c.offsets[facets][:, None] + np.arange(2)]                      # (facets, 2)
    x = msh.geometry.x[:, :gdim]
    corners = _dolfinx.vertices_per_cell(msh)
    centroids = x[_dolfinx.geometry_dofmap(msh)[:, :corners]].mean(axis=1)
    nodes = _dolfinx.entity_geometry(msh, tdim - 1, facets)[:, :tdim]
    base = x[nodes[:, 0]]
    edges = [x[nodes[:, k]] - base for k in range(1, tdim)]
    normal = np.stack([-edges[0][:, 1], edges[0][:, 0]], axis=1) if tdim == 2 else np.cross(edges[0], edges[1])
    side = np.einsum("fj,fcj->fc", normal, centroids[cells] - base[:, None, :])
    folded = side[:, 0] * side[:, 1] >= 0.0
    count = msh.comm.allreduce(int(np.count_nonzero(folded)))
    if count:
        where = base[folded][0] if folded.any() else None
        near = "" if where is None else f", e.g. near {np.round(where, 6).tolist()}"
        raise ValueError(f"{name}: {count} interior facet(s) have both their cells on the same side{near}: the "
                         "mesh is folded (inverted, overlapping or flat cells), and integrals over it would count "
                         "the overlap twice; repair or regenerate it (e.g. gmsh's mesh optimisation)")


def source_digest(name_or_path, h: float | None = None) -> str | None:
    """The SHA-256 of the ``.msh`` file :func:`load` reads for these arguments (the committed file of a
    bundled name without ``h``, or the path), or None when the mesh is generated (a bundled name at
    ``h``) or the file does not exist. A run's fingerprint holds it, so that a resume notices a mesh
    file that changed at the same path."""
    if isinstance(name_or_path, str) and name_or_path in available():
        if h is not None:
            return None
        path = bundled_meshes() / f"{name_or_path}.msh"
    else:
        path = Path(name_or_path)
    try:
        # Non-blocking: opening a FIFO for reading would otherwise wait for a writer.
        with open(os.open(path, os.O_RDONLY | os.O_NONBLOCK), "rb") as file:
            if not stat.S_ISREG(os.fstat(file.fileno()).st_mode):
                return None           # a directory, a FIFO, a device: load refuses it
            return hashlib.sha256(file.read()).hexdigest()
    except OSError:
        return None


def _load_bundled(name: str, comm, h, rank, gdim, max_cells: int = DEFAULT_MAX_CELLS) -> TaggedMesh:
    bundled_gdim = meshgen.GEOMETRIC_DIM[name]
    if gdim is not None and gdim != bundled_gdim:
        raise ValueError(f"gdim applies to .msh files only; bundled mesh {name!r} has gdim "
                         f"{bundled_gdim}, got gdim={gdim!r}; leave gdim=None")
    if h is not None:
        check_size(name, h, max_cells)
        mesh, cell_tags, facet_tags = meshgen.generate(name, h, comm, rank)
    else:
        resource = bundled_meshes() / f"{name}.msh"
        # as_file gives a real path even when the package is imported from a zip.
        with importlib.resources.as_file(resource) as path:
            if not path.is_file():
                raise FileNotFoundError(f"bundled mesh file {str(path)!r} is missing; regenerate it "
                                        "with `python tools/regenerate_meshes.py` or reinstall fempdl")
            mesh, cell_tags, facet_tags = _read_msh(path, comm, rank, bundled_gdim)
    return TaggedMesh(mesh, cell_tags, facet_tags, name, meshgen.FACET_TAGS[name])


def check_size(name: str, h: float, max_cells: int = DEFAULT_MAX_CELLS) -> float:
    """The estimated cell count of bundled mesh ``name`` at size ``h``; ValueError when ``h`` exceeds the
    geometry's shortest feature or the estimate exceeds ``max_cells``."""
    if not is_int(max_cells) or max_cells < 1:
        raise ValueError(f"max_cells must be an int >= 1, got {max_cells!r}")
    geometry = GEOMETRIES[name]
    if h > geometry.max_h:
        raise ValueError(f"h={h!r} is larger than the shortest feature of {name!r} ({geometry.max_h}), which it "
                         f"would no longer resolve; pass h <= {geometry.max_h}")
    cells = estimated_cells(name, h)
    if cells > max_cells:
        smallest = (geometry.cell_density / max_cells) ** (1.0 / geometry.dim)
        raise ValueError(f"h={h!r} would mesh {name!r} into about {cells:.3g} cells, more than max_cells="
                         f"{max_cells:,}; pass h >= {smallest:.3g}, or a larger max_cells if the machine "
                         "has the memory and time for it")
    return cells


def _as_msh_path(name_or_path) -> Path:
    """Validate ``name_or_path`` as a path to an existing ``.msh`` file."""
    if not isinstance(name_or_path, (str, os.PathLike)):
        raise TypeError(f"name_or_path must be a str or os.PathLike, got {type(name_or_path).__name__} "
                        f"{name_or_path!r}")
    path = Path(name_or_path)
    looks_like_path = isinstance(name_or_path, os.PathLike) or bool(path.suffix) or len(path.parts) > 1
    if not looks_like_path:
        raise ValueError(f"name_or_path must be a bundled mesh name {available()} or a path to a "
                         f".msh file, got {name_or_path!r}")
    if path.suffix != ".msh":
        raise ValueError(f"name_or_path must be a gmsh .msh file, got {str(path)!r}; convert other "
                         "formats with gmsh (gmsh FILE -save -format msh4)")
    try:
        mode = path.stat().st_mode        # stat, not open: opening a FIFO blocks until someone writes to it
    except (FileNotFoundError, NotADirectoryError):
        raise FileNotFoundError(f"name_or_path: no such .msh file {str(path)!r}; bundled meshes are "
                                f"{available()}") from None
    if stat.S_ISDIR(mode):
        raise IsADirectoryError(f"name_or_path: {str(path)!r} is a directory, not a .msh file; give the path of a "
                                ".msh file")
    if not stat.S_ISREG(mode):
        kind = next((name for test, name in _SPECIAL_FILES if test(mode)), "a special file")
        raise ValueError(f"name_or_path: {str(path)!r} is not a regular file ({kind}); save the mesh to a .msh "
                         "file and give its path")
    return path


_SPECIAL_FILES = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
                  (stat.S_ISBLK, "a block device"))


def _check_int_choice(arg: str, value, allowed) -> int:
    """``value`` as a python int (MPI and gmsh are handed it), TypeError or ValueError unless one of ``allowed``."""
    if not is_int(value):
        raise TypeError(f"{arg} must be an int, got {type(value).__name__} {value!r}")
    if value not in allowed:
        raise ValueError(f"{arg} must be one of {list(allowed)}, got {value!r}")
    return int(value)


def _read_msh(path: Path, comm, rank: int, gdim: int | None) -> TaggedMesh:
    # Built on model_to_mesh: Debian's DOLFINx 0.5.2 gmshio.read_from_msh
    # fails with a NameError before returning.
    with meshgen.gmsh_session(active=comm.rank == rank):
        found_gdim, labels = _run_on_rank(lambda: _open_msh(path, gdim), comm, rank)
        mesh, cell_tags, facet_tags = _dolfinx.model_to_mesh(gmsh.model, comm, rank, gdim=found_gdim)
    return TaggedMesh(mesh, cell_tags, facet_tags, str(path), labels)


def _open_msh(path: Path, gdim: int | None) -> tuple[int, dict[str, int]]:
    """Merge ``path`` into the gmsh session; return (gdim, facet tag names)."""
    try:
        gmsh.merge(str(path))
    except Exception as exc:  # gmsh raises a bare Exception
        raise ValueError(f"name_or_path: gmsh cannot read {str(path)!r}: {exc}") from None
    groups = gmsh.model.getPhysicalGroups()
    if not groups:
        raise ValueError(f"name_or_path: {str(path)!r} has no physical groups; DOLFINx reads only "
                         "elements in physical groups, so add one for the cells (and the boundary)")
    tdim = max(dim for dim, _ in groups)
    if gdim is None:
        gdim = _smallest_gdim(tdim)
    elif gdim < tdim:
        raise ValueError(f"gdim must be >= the mesh's topological dimension {tdim}, got {gdim}")
    labels = {gmsh.model.getPhysicalName(dim, tag): tag for dim, tag in groups if dim == tdim - 1}
    labels.pop("", None)
    return gdim, labels


def _smallest_gdim(tdim: int) -> int:
    """The fewest coordinates that hold the current gmsh mesh's nodes (at least tdim)."""
    _, coords, _ = gmsh.model.mesh.getNodes()
    used = np.flatnonzero(np.any(coords.reshape(-1, 3) != 0.0, axis=0))
    return max(tdim, int(used[-1]) + 1 if used.size else 1)


def _run_on_rank(fn: Callable[[], _T], comm, rank: int) -> _T:
    """Call ``fn`` on ``rank``; every rank returns its result or raises its error.

    Sharing the error keeps the other ranks from waiting forever in the
    collective mesh creation that follows.
    """
    result, error = None, None
    if comm.rank == rank:
        try:
            result = fn()
        except Exception as exc:
            error = exc
    shared_result, shared_error = comm.bcast((result, error), root=rank)
    if error is not None:
        raise error
    if shared_error is not None:
        raise shared_error
    return shared_result
