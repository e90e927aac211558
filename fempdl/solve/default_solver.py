"""The solver a layer gets when it is given no options: chosen from what the problem is.

A layer without options (``SolveLayer(problem)``, a Newton step's inner solve, a reference twin) runs
a converged solve, never a cap. Which one follows from the problem's traits (:class:`SystemTraits`):

1. **Direct** (the ``"lu"`` preset, MUMPS) while the factorisation is cheap: up to
   :func:`direct_max_dofs` unknowns. The limit falls with the mesh's dimension (a nested-dissection
   factor's work grows like n^1.5 in 2D, n^2 in 3D, where AMG's grows like n), with the block size (a
   vector field's rows are bs times fuller: equal work at n / sqrt(bs)), and when the matrix changes
   from call to call (a matrix control, a Newton Jacobian), since a fixed matrix is factorised once
   and every later forward and adjoint solve is a pair of triangular solves.
2. **CG + algebraic multigrid** (the ``"amg"`` preset) beyond it, for a problem declared symmetric
   on one field (Poisson, heat, elasticity: symmetric positive definite). A problem that gives a
   near null space (elasticity's rigid-body modes) gets PETSc's GAMG, which builds its coarse spaces
   from it; the others hypre's BoomerAMG where PETSc has hypre. AMG's iteration count stays flat as
   the mesh is refined; Jacobi's grows like 1/h.
3. **A Schur-complement fieldsplit** (the ``"schur"`` preset) for a saddle point with fields
   ``"u"`` and ``"p"`` (Stokes, Oseen): its velocity block by LU, its Schur complement by the
   least-squares commutator.
4. **GMRES(30) + GAMG** for a problem not declared symmetric that gives a near null space (a
   hyperelastic Newton Jacobian: its rigid-body modes).
5. **GMRES(30) + ILU(0)** otherwise (a non-symmetric system, a scalar Newton Jacobian): block Jacobi
   with ILU(0) blocks, PETSc's own default, which is ILU(0) on one process and runs under MPI.

The limits are measured in ``benchmarks/bench_default_solver.py`` (``docs/benchmarks.md``). A problem
declared symmetric that is indefinite (a Helmholtz operator) fails CG with a message naming the fix;
give it ``options=KSPOptions.preset("gmres")``, or ``"lu"``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from petsc4py import PETSc

from fempdl.solve.options import KSPOptions

__all__ = ["SystemTraits", "DIRECT_MAX_DOFS", "DIRECT_MAX_DOFS_REFACTORED", "direct_max_dofs", "default_preset",
           "default_options", "explain_default"]

#: The most scalar unknowns a layer without options factorises when its matrix is fixed (no matrix
#: control): the factor is reused by every later call, forward and adjoint. Up to these sizes the
#: first call costs at most about 4x (2D) and 6-8x (3D) a CG + AMG call, and every later call is
#: 1.7-3x faster than one, which repays the factorisation within about 15 and 45 calls. At 69k 3D
#: unknowns LU's first call took 16x AMG's (23 s against 1.4 s).
DIRECT_MAX_DOFS = {1: 1_000_000, 2: 300_000, 3: 25_000}
#: The same when the matrix is factorised again at every call (a matrix control, a Newton Jacobian):
#: where LU's call costs at most about 1.5x a CG + AMG call.
DIRECT_MAX_DOFS_REFACTORED = {1: 1_000_000, 2: 100_000, 3: 3_000}


@dataclass(frozen=True)
class SystemTraits:
    """What the default solver is chosen from.

    Attributes:
        tdim: the mesh's topological dimension (1, 2 or 3).
        dofs: the number of unknowns over all processes.
        block_size: the DOF map's block size (a vector field's components; 1 for a mixed space).
        symmetric: the problem is declared symmetric (``Problem(..., symmetric=True)``); a
            NonlinearProblem's Jacobian never is.
        fields: the names of a mixed space's fields (``()`` for a single space).
        near_nullspace: the problem gives a near null space for AMG.
        matrix_fixed: the matrix depends on no control (a Problem without matrix controls; a
            Constant changed between calls refactorises it, which this does not foresee).
    """

    tdim: int
    dofs: int
    block_size: int = 1
    symmetric: bool = False
    fields: tuple = ()
    near_nullspace: bool = False
    matrix_fixed: bool = False

    @classmethod
    def of(cls, problem) -> SystemTraits:
        """The traits of a :class:`fempdl.Problem` or :class:`fempdl.NonlinearProblem`."""
        V = problem.V
        return cls(tdim=V.mesh.topology.dim, dofs=V.mesh.comm.allreduce(problem.output_size),
                   block_size=V.dofmap.index_map_bs, symmetric=bool(getattr(problem, "symmetric", False)),
                   fields=tuple(problem.fields), near_nullspace=len(problem.near_nullspace) > 0,
                   # a NonlinearProblem (no matrix_controls) assembles a new Jacobian at every Newton step
                   matrix_fixed=not getattr(problem, "matrix_controls", True))

    @property
    def spd(self) -> bool:
        """Symmetric on one field: taken as positive definite (indefinite symmetric problems are mixed)."""
        return self.symmetric and not self.fields


def direct_max_dofs(tdim: int, block_size: int = 1, matrix_fixed: bool = False) -> int:
    """The most unknowns a layer without options factorises: :data:`DIRECT_MAX_DOFS` (a fixed matrix)
    or :data:`DIRECT_MAX_DOFS_REFACTORED` of the dimension, divided by sqrt(block size)."""
    table = DIRECT_MAX_DOFS if matrix_fixed else DIRECT_MAX_DOFS_REFACTORED
    return int(table[min(max(tdim, 1), 3)] / math.sqrt(max(block_size, 1)))


def default_preset(traits: SystemTraits) -> tuple[str, KSPOptions]:
    """The default converged solver of a system with these traits: ``(name, options)``."""
    if traits.dofs <= direct_max_dofs(traits.tdim, traits.block_size, traits.matrix_fixed):
        return "lu", KSPOptions.preset("lu")
    if traits.spd:
        if traits.near_nullspace and PETSc.Sys.hasExternalPackage("hypre"):
            # BoomerAMG ignores a near null space; GAMG builds its coarse spaces from the rigid-body modes.
            return "amg", KSPOptions.preset("amg", pc_type="gamg", petsc_options={})
        return "amg", KSPOptions.preset("amg")
    if traits.near_nullspace:
        # Not symmetric, but with rigid-body modes (a hyperelastic Newton Jacobian): 5x faster than LU and
        # than ILU(0) at 11k 3D unknowns, where GMRES + ILU(0) was slower than LU.
        return "gmres-gamg", KSPOptions(ksp_type="gmres", pc_type="gamg", gmres_restart=30)
    if {"u", "p"} <= set(traits.fields):
        return "schur", KSPOptions.preset("schur")
    return "gmres-ilu", KSPOptions.preset("gmres-ilu", pc_type="bjacobi")


def default_options(problem) -> KSPOptions:
    """The options of ``SolveLayer(problem)``, of a Newton step's inner solve and of a reference twin:
    a converged solve chosen by :func:`default_preset` from the problem's traits."""
    return default_preset(SystemTraits.of(problem))[1]


def explain_default(problem) -> str:
    """One line: the solver a layer without options uses for ``problem``, and why, e.g. ``"amg: 68921
    unknowns > 25000, the direct limit in 3D for a fixed matrix (block size 1); symmetric on one field"``."""
    t = SystemTraits.of(problem)
    name, _ = default_preset(t)
    most = direct_max_dofs(t.tdim, t.block_size, t.matrix_fixed)
    limit = (f"the direct limit in {t.tdim}D for a {'fixed' if t.matrix_fixed else 'refactorised'} matrix "
             f"(block size {t.block_size})")
    if name == "lu":
        return f"lu: {t.dofs} unknowns <= {most}, {limit}"
    why = ("symmetric on one field" + (", with a near null space for GAMG" if t.near_nullspace else "") if t.spd
           else "a near null space for GAMG, not declared symmetric" if name == "gmres-gamg"
           else "fields 'u' and 'p' (a saddle point)" if name == "schur"
           else f"fields {list(t.fields)}" if t.fields else "not declared symmetric")
    return f"{name}: {t.dofs} unknowns > {most}, {limit}; {why}"
