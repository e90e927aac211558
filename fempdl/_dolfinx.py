"""The one place that touches DOLFINx names that changed after 0.5.

DOLFINx 0.6+ renamed or moved several calls used here (``FunctionSpace`` ->
``functionspace``, ``gmshio`` return values (and 0.5.2's ``read_from_msh`` is
broken in Debian's build, so .msh files are read through ``model_to_mesh``), ``create_vector`` / ``assemble_*``
signatures). Everything else in fempdl goes through this module, so a port to a
newer DOLFINx touches this file only.
"""
from __future__ import annotations

import signal
import threading

import dolfinx
import dolfinx.fem
import dolfinx.fem.petsc
import dolfinx.mesh
import numpy as np
from petsc4py import PETSc

# Importing gmsh (through gmshio) resets SIGINT to the OS default, so Ctrl-C
# would kill the process without unwinding (no cleanup, no final checkpoint).
# Put back whatever handler was in place (Python's KeyboardInterrupt by default).
_sigint = signal.getsignal(signal.SIGINT)
import dolfinx.io.gmshio  # noqa: E402

if threading.current_thread() is threading.main_thread() and _sigint is not None:
    signal.signal(signal.SIGINT, _sigint)


def function_space(msh, family: str, degree: int, shape: tuple | None = None):
    """A (scalar or vector) Lagrange/DG space on ``msh``."""
    if shape is None:
        return dolfinx.fem.FunctionSpace(msh, (family, degree))
    return dolfinx.fem.VectorFunctionSpace(msh, (family, degree), dim=shape[0])


def taylor_hood_space(msh, degree: int = 2):
    """The mixed space P_degree (vector) x P_(degree-1) of velocity and pressure."""
    import ufl

    velocity = ufl.VectorElement("Lagrange", msh.ufl_cell(), degree)
    pressure = ufl.FiniteElement("Lagrange", msh.ufl_cell(), degree - 1)
    return dolfinx.fem.FunctionSpace(msh, ufl.MixedElement([velocity, pressure]))


def collapsed_subspace(W, index: int):
    """(space, owned_dofs): subspace ``index`` of the mixed space W collapsed,
    and the owned local DOF indices in W of its owned DOFs, in its own order."""
    space, dofs = W.sub(index).collapse()
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
    cells = msh.geometry.dofmap.array.reshape(-1, msh.ufl_cell().num_vertices())[:n_cells]
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
    return dolfinx.io.gmshio.model_to_mesh(model, comm, rank, gdim=gdim)


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


def create_matrix(a_form) -> PETSc.Mat:
    return dolfinx.fem.petsc.create_matrix(a_form)


def create_vector(L_form) -> PETSc.Vec:
    """A ghosted PETSc vector laid out like the test space of ``L_form``."""
    return dolfinx.fem.petsc.create_vector(L_form)


def assemble_matrix_into(A: PETSc.Mat, a_form, bcs=(), diagonal: float = 1.0) -> PETSc.Mat:
    """Zero ``A`` and assemble ``a_form`` into it; BC rows and columns are zeroed
    and ``diagonal`` is put on BC rows (only when ``bcs`` is given)."""
    A.zeroEntries()
    dolfinx.fem.petsc.assemble_matrix(A, a_form, bcs=list(bcs), diagonal=diagonal)
    A.assemble()
    return A


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


def assemble_scalar(M_form, comm) -> float:
    """Assemble a functional and sum it over ``comm``."""
    from mpi4py import MPI

    return comm.allreduce(dolfinx.fem.assemble_scalar(M_form), op=MPI.SUM)


def bc_dofs_owned(bcs, n_owned: int) -> np.ndarray:
    """Owned local indices of all DOFs constrained by ``bcs`` (sorted, unique)."""
    if not bcs:
        return np.empty(0, dtype=np.int32)
    # dof_indices() lists owned DOFs first; the ones before first_ghost are owned.
    owned = [dofs[:first_ghost] for dofs, first_ghost in (bc.dof_indices() for bc in bcs)]
    return np.unique(np.concatenate(owned)).astype(np.int32)


def is_dirichlet_bc(obj) -> bool:
    return isinstance(obj, dolfinx.fem.DirichletBCMetaClass)


def bc_on_space(bc, V) -> bool:
    """Whether Dirichlet condition ``bc`` constrains ``V`` or one of its subspaces."""
    return V._cpp_object.contains(bc.function_space)


def cell_dofs(V) -> np.ndarray:
    """(num_cells, dofs_per_cell) local DOF indices of every cell (owned and ghost)."""
    dofs = V.dofmap.list.array
    return dofs.reshape(-1, V.dofmap.dof_layout.num_dofs)


def point_evaluator(msh, points: np.ndarray):
    """For points (N, 3): (found indices, their cells) on this process's part of ``msh``.

    A point on a facet or vertex is assigned to one of the cells containing it."""
    import dolfinx.geometry
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
