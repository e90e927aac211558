"""The solvers of a Newton system for one set of options: :class:`NewtonSolvers`.

A SNES on the Jacobian J whose KSP is the inner solve, and the capped solvers of the implicit
adjoint's transposed solves (on J, and on dF/du when the problem gives another). The inner cap K is
one assignment to this owner (:attr:`NewtonSolvers.inner_max_it`): the KSP's tolerances and norm
type and the adjoint solvers' caps move in place, as a linear layer's cap does, so PRDP moving K
every few epochs keeps the SNES, its KSP and a set-up preconditioner. Any other change of the
options builds new solvers (:class:`~fempdl.solve.nonlinear_system.NonlinearSystem` does).
"""
from __future__ import annotations

from collections.abc import Callable

from petsc4py import PETSc

from fempdl.solve.capped_solver import CappedSolver, set_interrupt_checks
from fempdl.solve.newton_options import NewtonOptions
from fempdl.solve.newton_stop import NewtonMode
from fempdl.solve.petsc import create_ksp, destroy_ksp, set_norm_type, unique_prefix
from fempdl.solve.snes import create_snes, destroy_snes

__all__ = ["NewtonSolvers"]


class NewtonSolvers:
    """SNES, inner KSP and adjoint solvers of one :class:`NewtonOptions`.

    Args:
        options: the Newton options (``options.ksp`` set).
        J: the Jacobian the SNES assembles into; ``dFdu``: the matrix of the exact adjoint (``J``
            itself unless the problem's J is not dF/du); ``P``: a lagged preconditioner's matrix
            (``None``: J).
        callbacks: the SNES's (residual, jacobian, monitor); ``b`` its residual vector.
        stats: the cumulative stats the adjoint solves count in.
        mode: when the SNES stops (:class:`~fempdl.solve.newton_stop.NewtonMode`).

    Attributes:
        snes, ksp: the SNES and its inner KSP; ``adjoint``, ``exact_adjoint``: the capped solvers
        of J^T and (dF/du)^T (the same object when J is dF/du).
    """

    def __init__(self, options: NewtonOptions, *, J: PETSc.Mat, dFdu: PETSc.Mat, P: PETSc.Mat | None,
                 callbacks: tuple[Callable, Callable, Callable], b: PETSc.Vec, comm, fields, stats,
                 mode: NewtonMode):
        self._inner = options.ksp
        self.ksp = create_ksp(J, self._inner, unique_prefix("newton_ksp"), fields)
        self.snes = create_snes(comm, options, self.ksp, *callbacks, b, J, mode=mode, P=P)
        set_interrupt_checks(self.ksp, self._inner)      # Ctrl-C within a long inner solve
        self.adjoint = CappedSolver(J, self._inner, fields=fields, preconditioner_matrix=P)
        self.adjoint.stats = stats
        self.exact_adjoint = self.adjoint
        if dFdu is not J:
            self.exact_adjoint = CappedSolver(dFdu, self._inner, fields=fields)
            self.exact_adjoint.stats = stats

    @property
    def inner_max_it(self) -> int | None:
        return self._inner.max_it

    @inner_max_it.setter
    def inner_max_it(self, value: int | None) -> None:
        """Move the inner cap in place: the SNES's KSP and the adjoint solvers (a coupled adjoint)."""
        new = self._inner.with_max_it(value)
        if new.skips_residual_norm() != self._inner.skips_residual_norm():
            set_norm_type(self.ksp, new)
        self.ksp.setTolerances(**new.petsc_tolerances())
        set_interrupt_checks(self.ksp, new)
        for solver in self._adjoint_solvers():
            solver.max_it = value
        self._inner = new

    def _adjoint_solvers(self) -> list[CappedSolver]:
        return list({id(s): s for s in (self.adjoint, self.exact_adjoint)}.values())

    def destroy(self) -> None:
        destroy_snes(self.snes)
        destroy_ksp(self.ksp)
        for solver in self._adjoint_solvers():
            solver.destroy()
