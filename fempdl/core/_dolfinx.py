"""The one place that knows which DOLFINx / PETSc fempdl runs on.

Two stacks are supported: Debian bookworm's DOLFINx 0.5.2 with PETSc 3.18, and
DOLFINx >= 0.9 (tested: 0.11 with PETSc 3.25 from PyPI). Between them DOLFINx
renamed or moved several calls used here (``FunctionSpace`` ->
``functionspace``, ``ufl.MixedElement`` -> ``basix.ufl.mixed_element``,
``gmshio`` -> ``gmsh`` and its return value, ``create_vector``'s argument,
``BoundingBoxTree`` -> ``bb_tree``, adjacency lists -> 2D arrays). Each
difference is decided once here, by what the installed package offers;
everything else in fempdl calls these functions, so no other module asks for a
version.

Debian's 0.5.2 ``gmshio.read_from_msh`` is broken, so .msh files are read
through ``model_to_mesh`` on both stacks.
"""
from __future__ import annotations

import importlib
import importlib.util
import shutil
import signal
import sys
import threading
from pathlib import Path

# mpi4py's MPI first: PyPI's DOLFINx finds libmpi only once mpi4py has loaded it.
from mpi4py import MPI
import basix
import dolfinx
import dolfinx.fem
import dolfinx.fem.petsc
import dolfinx.geometry
import dolfinx.mesh
import numpy as np
import ufl
from petsc4py import PETSc

# Importing dolfinx leaves the process's dlopen flags at RTLD_GLOBAL (its line that
# restores them is commented out). torch.compile's CPU backend then loads every
# compiled kernel with global symbols, all named ``kernel``, so a graph can run
# another graph's kernel: silently wrong values and gradients. Restore the flags
# dolfinx found (its own extension modules are loaded by now).
if hasattr(dolfinx, "stored_dlopen_flags"):
    sys.setdlopenflags(dolfinx.stored_dlopen_flags)

#: (major, minor) of the DOLFINx in use, e.g. (0, 5) or (0, 11); for reports
#: and for tests that must know the stack. Code branches on the capabilities below.
DOLFINX_VERSION: tuple[int, int] = tuple(int(p) for p in dolfinx.__version__.split(".")[:2])
#: (major, minor, patch) of PETSc.
PETSC_VERSION: tuple[int, int, int] = tuple(PETSc.Sys.getVersion())
#: The stack's name: "debian" (DOLFINx 0.5) or "current" (DOLFINx >= 0.9).
STACK = "debian" if DOLFINX_VERSION < (0, 9) else "current"


def mpi_launcher() -> list[str]:
    """The command (program and flags, before ``-n N``) that starts ranks of this MPI.

    PyPI's mpi4py brings MPICH and its ``mpiexec`` beside the interpreter;
    Debian's is Open MPI's ``mpirun`` on PATH, which refuses more ranks than
    cores unless told ``--oversubscribe`` (MPICH oversubscribes by default).
    """
    beside = Path(sys.executable).parent / "mpiexec"
    if "Open MPI" in MPI.Get_library_version():
        launcher = shutil.which("mpirun")
        flags = ["--oversubscribe"]
    else:
        launcher = str(beside) if beside.exists() else shutil.which("mpiexec")
        flags = []
    if launcher is None:
        raise FileNotFoundError(f"no MPI launcher found for {MPI.Get_library_version().splitlines()[0]!r}; "
                                "install the MPI that mpi4py was built with (Debian: openmpi-bin; PyPI: mpich)")
    return [launcher, *flags]


def _import_keeping_sigint(name: str):
    """Import module ``name`` and put back the SIGINT handler that was in place (Python's KeyboardInterrupt,
    or the user's): gmsh's module sets the OS default when imported (later releases again in
    ``gmsh.initialize``: :func:`fempdl.core.meshgen.gmsh_session`), and Ctrl-C would then kill the
    process without unwinding (no KeyboardInterrupt, no ``finally``, no final checkpoint)."""
    before = signal.getsignal(signal.SIGINT)
    try:
        return importlib.import_module(name)
    finally:
        # Only the main thread may set a handler; None: one installed outside Python, not restorable.
        if before is not None and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, before)


#: The gmsh module, imported here and nowhere else in fempdl (see :func:`_import_keeping_sigint`).
gmsh = _import_keeping_sigint("gmsh")
# DOLFINx 0.10 moved gmshio to dolfinx.io.gmsh.
_gmsh_io = _import_keeping_sigint("dolfinx.io.gmsh" if importlib.util.find_spec("dolfinx.io.gmsh")
                                  else "dolfinx.io.gmshio")

_NEW_SPACES = hasattr(dolfinx.fem, "functionspace")       # 0.7+: functionspace and basix.ufl elements
if _NEW_SPACES:
    import basix.ufl


def function_space(msh, family: str, degree: int, shape: tuple | None = None):
    """A (scalar or vector) Lagrange/DG space on ``msh``."""
    if _NEW_SPACES:
        return dolfinx.fem.functionspace(msh, (family, degree) if shape is None else (family, degree, tuple(shape)))
    if shape is None:
        return dolfinx.fem.FunctionSpace(msh, (family, degree))
    return dolfinx.fem.VectorFunctionSpace(msh, (family, degree), dim=shape[0])


def taylor_hood_space(msh, degree: int = 2):
    """The mixed space P_degree (vector) x P_(degree-1) of velocity and pressure."""
    if _NEW_SPACES:
        cell = msh.basix_cell()
        velocity = basix.ufl.element("Lagrange", cell, degree, shape=(msh.geometry.dim,))
        pressure = basix.ufl.element("Lagrange", cell, degree - 1)
        return dolfinx.fem.functionspace(msh, basix.ufl.mixed_element([velocity, pressure]))
    velocity = ufl.VectorElement("Lagrange", msh.ufl_cell(), degree)
    pressure = ufl.FiniteElement("Lagrange", msh.ufl_cell(), degree - 1)
    return dolfinx.fem.FunctionSpace(msh, ufl.MixedElement([velocity, pressure]))


def collapsed_subspace(W, index: int):
    """(space, owned_dofs): subspace ``index`` of the mixed space W collapsed,
    and the owned local DOF indices in W of its owned DOFs, in its own order."""
    space, dofs = W.sub(index).collapse()
    if len(dofs) and isinstance(dofs[0], np.ndarray):   # 0.10+: one array per cell type
        dofs = dofs[0]
    n_owned = space.dofmap.index_map.size_local * space.dofmap.index_map_bs
    return space, np.asarray(dofs[:n_owned], dtype=np.int32)


def dirichlet_bc_on_subspace(W, index: int, value, facets: np.ndarray):
    """A Dirichlet condition on subspace ``index`` of W (value: a Function on
    the collapsed subspace) on the DOFs of ``facets``."""
    fdim = W.mesh.topology.dim - 1
    sub = W.sub(index)
    dofs = dolfinx.fem.locate_dofs_topological((sub, value.function_space), fdim, facets)
    return dolfinx.fem.dirichletbc(value, dofs, sub)


def cell_diameters(msh) -> np.ndarray:
    """Diameter (largest vertex distance) of every local cell of an affine mesh."""
    x = msh.geometry.x
    n_cells = msh.topology.index_map(msh.topology.dim).size_local
    cells = _geometry_dofmap(msh)[:n_cells]
    corners = x[cells]                                                    # (cells, vertices, 3)
    gaps = np.linalg.norm(corners[:, :, None, :] - corners[:, None, :, :], axis=-1)
    return gaps.reshape(n_cells, -1).max(axis=1)


def compile_form(ufl_form):
    """JIT-compile a UFL form (cached on disk by FFCx)."""
    return dolfinx.fem.form(ufl_form)


def model_to_mesh(model, comm, rank: int = 0, gdim: int = 3):
    """Convert the current gmsh model on ``rank`` into a distributed mesh.

    Returns:
        (mesh, cell_tags, facet_tags)
    """
    # 0.10+ returns a MeshData named tuple that starts with these three.
    return tuple(_gmsh_io.model_to_mesh(model, comm, rank, gdim=gdim))[:3]


def boundary_facets(msh) -> np.ndarray:
    """Local indices of all exterior facets of ``msh``."""
    tdim = msh.topology.dim
    msh.topology.create_connectivity(tdim - 1, tdim)
    return dolfinx.mesh.exterior_facet_indices(msh.topology)


def dirichlet_bc(V, value, facets: np.ndarray):
    """A Dirichlet condition ``u = value`` on the DOFs of ``facets``.

    ``value`` is a ``fem.Function`` on ``V`` or a ``fem.Constant``.
    """
    fdim = V.mesh.topology.dim - 1
    dofs = dolfinx.fem.locate_dofs_topological(V, fdim, facets)
    if isinstance(value, dolfinx.fem.Function):
        return dolfinx.fem.dirichletbc(value, dofs)
    return dolfinx.fem.dirichletbc(value, dofs, V)


def create_petsc_matrix(a_form) -> PETSc.Mat:
    return dolfinx.fem.petsc.create_matrix(a_form)


def create_csr_matrix(a_form):
    """DOLFINx's own CSR matrix (``la.MatrixCSR``) with the sparsity of ``a_form``, zeroed."""
    create = getattr(dolfinx.fem, "create_matrix", None) or dolfinx.fem.assemble.create_matrix   # 0.5: not exported
    return create(a_form)


def create_vector(L_form) -> PETSc.Vec:
    """A ghosted PETSc vector laid out like the test space of ``L_form``.

    Built from the space's index map (what DOLFINx does inside), because
    ``fem.petsc.create_vector`` takes a form up to 0.10 and a space from 0.11.
    """
    space = L_form.function_spaces[0]
    imap, bs = space.dofmap.index_map, space.dofmap.index_map_bs
    return PETSc.Vec().createGhost(np.asarray(imap.ghosts, dtype=PETSc.IntType),
                                   size=(imap.size_local * bs, imap.size_global * bs), bsize=bs,
                                   comm=space.mesh.comm)


def assemble_petsc_matrix(A: PETSc.Mat, a_form, bcs=(), diagonal: float = 1.0) -> None:
    """Add ``a_form`` into the PETSc matrix ``A`` (not assembled); with ``bcs``, BC rows and
    columns are left out and ``diagonal`` is set on BC rows."""
    # Positional: the keyword is ``diagonal`` up to 0.9 and ``diag`` from 0.10.
    dolfinx.fem.petsc.assemble_matrix(A, a_form, list(bcs), diagonal)


def assemble_csr_matrix(A, a_form, bcs=(), diagonal: float = 1.0) -> None:
    """Add ``a_form`` into DOLFINx's CSR matrix ``A``, as :func:`assemble_petsc_matrix` does."""
    dolfinx.fem.assemble_matrix(A, a_form, list(bcs), diagonal)


def assemble_vector_into(b: PETSc.Vec, L_form, a_form=None, bcs=()) -> PETSc.Vec:
    """Zero ``b``, assemble ``L_form`` into it, lift by ``a_form``'s BC columns,
    accumulate ghosts and set BC values (the standard DOLFINx RHS sequence)."""
    with b.localForm() as loc:
        loc.set(0.0)
    dolfinx.fem.petsc.assemble_vector(b, L_form)
    if bcs and a_form is not None:
        dolfinx.fem.petsc.apply_lifting(b, [a_form], bcs=[list(bcs)])
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    if bcs:
        dolfinx.fem.petsc.set_bc(b, list(bcs))
    return b


def function_vector(fn) -> PETSc.Vec:
    """The ghosted PETSc vector that shares ``fn``'s values (``fn.vector`` up to 0.9, ``fn.x.petsc_vec`` from 0.10)."""
    x = getattr(fn, "x", None)
    return x.petsc_vec if hasattr(x, "petsc_vec") else fn.vector


def assemble_residual_into(b: PETSc.Vec, F_form, J_form, bcs, x: PETSc.Vec) -> PETSc.Vec:
    """Zero ``b`` and assemble the Newton residual F(x) into it: lifted by J's BC columns at
    x - g and with x - g on BC rows, so that x - J^{-1} b takes the boundary values
    (DOLFINx's NonlinearProblem.F). ``x`` is ghosted with its ghosts up to date."""
    with b.localForm() as loc:
        loc.set(0.0)
    dolfinx.fem.petsc.assemble_vector(b, F_form)
    # Positional: the scale is ``scale`` up to 0.9 and ``alpha`` from 0.10.
    dolfinx.fem.petsc.apply_lifting(b, [J_form], [list(bcs)], [x], -1.0)
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    dolfinx.fem.petsc.set_bc(b, list(bcs), x, -1.0)
    return b


def set_bc_values(x: PETSc.Vec, bcs) -> None:
    """Put the Dirichlet values into ``x`` (owned entries)."""
    dolfinx.fem.petsc.set_bc(x, list(bcs))


def bc_dofs_owned(bcs, n_owned: int) -> np.ndarray:
    """Owned local indices of all DOFs constrained by ``bcs`` (sorted, unique)."""
    if not bcs:
        return np.empty(0, dtype=np.int32)
    # dof_indices() lists owned DOFs first; the ones before first_ghost are owned.
    owned = [dofs[:first_ghost] for dofs, first_ghost in (bc.dof_indices() for bc in bcs)]
    return np.unique(np.concatenate(owned)).astype(np.int32)


_DIRICHLET_BC = getattr(dolfinx.fem, "DirichletBC", None) or dolfinx.fem.DirichletBCMetaClass


def is_dirichlet_bc(obj) -> bool:
    return isinstance(obj, _DIRICHLET_BC)


def bc_on_space(bc, V) -> bool:
    """Whether Dirichlet condition ``bc`` constrains ``V`` or one of its subspaces."""
    return V._cpp_object.contains(bc.function_space)


def cell_dofs(V) -> np.ndarray:
    """(num_cells, dofs_per_cell) local DOF indices of every cell (owned and ghost)."""
    return _as_2d(V.dofmap.list, V.dofmap.dof_layout.num_dofs)


def element_degree(space) -> int:
    """The polynomial degree of ``space``'s element (UFL 2022: a method; basix.ufl: a property)."""
    degree = space.ufl_element().degree
    return degree() if callable(degree) else degree


def element_family(space) -> str:
    """The family name of ``space``'s element ("Lagrange" in UFL 2022, "P" in basix.ufl)."""
    element = space.ufl_element()
    return element.family() if callable(getattr(element, "family", None)) else element.family_name


def vertices_per_cell(msh) -> int:
    """Vertices of one cell of ``msh`` (3 for a triangle); a method in UFL 2022, a property in 2026."""
    count = msh.ufl_cell().num_vertices
    return count() if callable(count) else count


def entity_geometry(msh, dim: int, entities: np.ndarray) -> np.ndarray:
    """(len(entities), nodes) geometry node indices of local mesh entities of dimension ``dim``
    (the vertices first), unpermuted."""
    entities = np.asarray(entities, dtype=np.int32)
    if hasattr(dolfinx.mesh, "entities_to_geometry"):             # 0.6+
        return dolfinx.mesh.entities_to_geometry(msh, dim, entities, False)
    return dolfinx.cpp.mesh.entities_to_geometry(getattr(msh, "_mesh", msh), dim, entities, False)


def cell_name(msh) -> str:
    """The cell type's name, e.g. ``"triangle"`` (a method in UFL 2022, a property in 2026)."""
    name = msh.ufl_cell().cellname
    return name() if callable(name) else name


def coordinate_degree(msh) -> int:
    """The degree of the mesh's coordinate map (1: affine simplices, straight edges)."""
    geometry = msh.geometry
    cmap = geometry.cmaps[0] if hasattr(geometry, "cmaps") else geometry.cmap     # 0.10+: one per cell type
    return cmap.degree


def geometry_dofmap(msh) -> np.ndarray:
    """(num_cells, nodes_per_cell) geometry node indices of every cell on this process, ghosts included."""
    return _geometry_dofmap(msh)


def _geometry_dofmap(msh) -> np.ndarray:
    """(num_cells, nodes_per_cell) geometry node indices of every local cell."""
    geometry = msh.geometry
    if hasattr(geometry, "dofmaps"):                    # 0.10+: one dofmap per cell type
        dofmaps = geometry.dofmaps
        return dofmaps(0) if callable(dofmaps) else dofmaps[0]
    return _as_2d(geometry.dofmap, vertices_per_cell(msh))


def _as_2d(links, width: int) -> np.ndarray:
    """A fixed-width cell-to-DOF map as a 2D array (0.7+ store it so; 0.5 as an AdjacencyList)."""
    return links if isinstance(links, np.ndarray) else links.array.reshape(-1, width)


def point_evaluator(msh, points: np.ndarray):
    """For points (N, 3): (found indices, their cells) on this process's part of ``msh``.

    A point on a facet or vertex is assigned to one of the cells containing it."""
    if hasattr(dolfinx.geometry, "bb_tree"):
        tree = dolfinx.geometry.bb_tree(msh, msh.topology.dim)
        candidates = dolfinx.geometry.compute_collisions_points(tree, points)
    else:
        tree = dolfinx.geometry.BoundingBoxTree(msh, msh.topology.dim)
        candidates = dolfinx.geometry.compute_collisions(tree, points)
    colliding = dolfinx.geometry.compute_colliding_cells(msh, candidates, points)
    found, cells = [], []
    for i in range(len(points)):
        links = colliding.links(i)
        if len(links):
            found.append(i)
            cells.append(links[0])
    return np.asarray(found, dtype=np.int64), np.asarray(cells, dtype=np.int32)


def quadrature_space(msh, degree: int, shape: tuple = ()):
    """The space of values at the quadrature points of ``degree`` (basix's default scheme) on every cell:
    scalar, a vector (m,) or a matrix (a, b). Its DOFs are numbered cell by cell, point by point."""
    if _NEW_SPACES:
        element = basix.ufl.quadrature_element(msh.basix_cell(), value_shape=tuple(shape), degree=degree)
        return dolfinx.fem.functionspace(msh, element)
    cell = msh.ufl_cell()
    if not shape:
        element = ufl.FiniteElement("Quadrature", cell, degree, quad_scheme="default")
    elif len(shape) == 1:
        element = ufl.VectorElement("Quadrature", cell, degree, dim=shape[0], quad_scheme="default")
    else:
        element = ufl.TensorElement("Quadrature", cell, degree, shape=tuple(shape), quad_scheme="default")
    return dolfinx.fem.FunctionSpace(msh, element)


def quadrature_points(msh, degree: int) -> np.ndarray:
    """(P, tdim) reference points of basix's default quadrature of ``degree`` on ``msh``'s cell: the points of
    :func:`quadrature_space` and of an integral with that ``quadrature_degree``."""
    cell = msh.basix_cell() if hasattr(msh, "basix_cell") else basix.cell.string_to_type(cell_name(msh))
    return basix.make_quadrature(cell, degree)[0]


def quadrature_weights(msh, degree: int) -> np.ndarray:
    """(P,) reference weights of :func:`quadrature_points`."""
    cell = msh.basix_cell() if hasattr(msh, "basix_cell") else basix.cell.string_to_type(cell_name(msh))
    return basix.make_quadrature(cell, degree)[1]


def expression(expr, points: np.ndarray):
    """A compiled UFL expression to evaluate at ``points`` (reference coordinates) of cells."""
    return dolfinx.fem.Expression(expr, points)


def evaluate_expression(compiled, msh, cells: np.ndarray, value_size: int) -> np.ndarray:
    """(len(cells) * P, value_size) values of a compiled :func:`expression` at its points of ``cells``, cell by
    cell and point by point (0.5: ``eval(cells)``; 0.6+: ``eval(mesh, cells)``)."""
    values = compiled.eval(msh, cells) if _NEW_SPACES else compiled.eval(cells)
    return np.asarray(values).reshape(-1, value_size)
