"""The hand-written petsc4py loop bench_layer.py times SolveLayer against, and the solver it is spelled with.

:class:`Solver` names one capped solver both ways (fempdl's ``KSPOptions`` and raw PETSc settings);
:class:`RawLoop` does a layer call's work for the source control f by hand, built from dolfinx and
petsc4py only; :func:`boundary_values` is the Dirichlet data both sides use.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

from mpi4py import MPI  # noqa: F401  (before DOLFINx: PyPI's DOLFINx needs the MPI library mpi4py loads)
import dolfinx.fem
import dolfinx.fem.petsc
import dolfinx.mesh
import numpy as np
import ufl
from petsc4py import PETSc

from fempdl.ksp_adjoint import KSPOptions


def boundary_values(x):
    # Non-zero Dirichlet data, so the constant part b0 of the right-hand side
    # (lifting and BC rows) is exercised by the comparison.
    return 1.0 + x[0] * x[1]


@dataclass(frozen=True)
class Solver:
    """One solver configuration, spelled both ways: fempdl options and raw PETSc settings."""

    name: str
    ksp_type: str
    pc_type: str
    gmres_restart: int | None
    norm_none: bool   # fempdl skips the residual norm for a pure cap of Richardson

    def layer_options(self, max_it: int, engine: str = "auto") -> KSPOptions:
        if self.name == "jacobi":
            return KSPOptions(max_it=max_it, engine=engine)
        return KSPOptions.preset(self.name, max_it=max_it, engine=engine)


SOLVERS = {
    "jacobi": Solver("jacobi", "richardson", "jacobi", None, norm_none=True),
    "gmres": Solver("gmres", "gmres", "jacobi", 30, norm_none=False),
}


class RawLoop:
    """The layer's work for an affine source control, written by hand.

    Built from dolfinx and petsc4py only, on the same function space (so the
    DOF order matches): A with the Dirichlet rows and columns replaced by the
    identity, the mass matrix M = dL/df with its Dirichlet rows zeroed (those
    rows of b come from the boundary data alone), and b0 = the lifted boundary
    data. Per sample: b = M f + b0, a capped KSP solve; backward: the BC
    entries of dJ/du zeroed, A^T lam = dJ/du, dJ/df = M^T lam.
    """

    def __init__(self, V, solver: Solver, max_it: int):
        msh = V.mesh
        fdim = msh.topology.dim - 1
        msh.topology.create_connectivity(fdim, msh.topology.dim)
        facets = dolfinx.mesh.exterior_facet_indices(msh.topology)
        self.bc_dofs = dolfinx.fem.locate_dofs_topological(V, fdim, facets)
        g = dolfinx.fem.Function(V)
        g.interpolate(boundary_values)
        bc = dolfinx.fem.dirichletbc(g, self.bc_dofs)

        u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
        a = dolfinx.fem.form(ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx)
        self.A = dolfinx.fem.petsc.assemble_matrix(a, bcs=[bc])
        self.A.assemble()
        self.M = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(u * v * ufl.dx))
        self.M.assemble()
        self.M.zeroRows(self.bc_dofs, diag=0.0)
        # A Constant, not 0.0 * form: UFL collapses the latter to an empty form.
        L0 = dolfinx.fem.form(dolfinx.fem.Constant(msh, 0.0) * v * ufl.dx)
        b0 = dolfinx.fem.petsc.assemble_vector(L0)
        dolfinx.fem.petsc.apply_lifting(b0, [a], bcs=[[bc]])
        b0.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        dolfinx.fem.petsc.set_bc(b0, [bc])
        self.n = V.dofmap.index_map.size_local
        self.b0 = self.A.createVecLeft()
        self.b0.setArray(b0.array_r[: self.n])
        b0.destroy()

        self.f, self.b = self.M.createVecs()
        self.x, self.rhs = self.A.createVecs()
        self.ksp = PETSc.KSP().create(msh.comm)
        self.ksp.setOperators(self.A)
        self.ksp.setType(solver.ksp_type)
        self.ksp.getPC().setType(solver.pc_type)
        if solver.gmres_restart is not None:
            self.ksp.setGMRESRestart(solver.gmres_restart)
        if solver.norm_none:
            self.ksp.setNormType(PETSc.KSP.NormType.NONE)
        self.ksp.setInitialGuessNonzero(False)
        self.set_max_it(max_it)
        self.ksp_time = 0.0

    def set_max_it(self, max_it: int) -> None:
        # rtol = atol = 0 and no divergence test: exactly max_it iterations.
        self.ksp.setTolerances(rtol=0.0, atol=0.0, divtol=1e300, max_it=max_it)

    def forward(self, F: np.ndarray) -> np.ndarray:
        U = np.empty((F.shape[0], self.n))
        for i in range(F.shape[0]):
            self.f.setArray(F[i])
            self.M.mult(self.f, self.b)
            self.b.axpy(1.0, self.b0)
            t0 = time.perf_counter()
            self.ksp.solve(self.b, self.x)
            self.ksp_time += time.perf_counter() - t0
            U[i] = self.x.getArray(readonly=True)
        return U

    def backward(self, W: np.ndarray) -> np.ndarray:
        G = W.copy()
        G[:, self.bc_dofs] = 0.0  # u = g there does not depend on f
        grads = np.empty((W.shape[0], self.M.getSize()[1]))
        for i in range(W.shape[0]):
            self.rhs.setArray(G[i])
            t0 = time.perf_counter()
            self.ksp.solveTranspose(self.rhs, self.x)
            self.ksp_time += time.perf_counter() - t0
            self.M.multTranspose(self.x, self.f)
            grads[i] = self.f.getArray(readonly=True)
        return grads

    def destroy(self) -> None:
        for obj in (self.ksp, self.A, self.M, self.b0, self.f, self.b, self.x, self.rhs):
            obj.destroy()

