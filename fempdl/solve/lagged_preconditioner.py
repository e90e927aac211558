"""The lagged preconditioner of a Newton system's inner solves: :class:`LaggedPreconditioner`.

A lagged inner preconditioner (``KSPOptions(lag_preconditioner=True)``, the ``"lu-lagged"`` preset) is
set up on a copy P of an earlier Jacobian J and kept across Newton steps, solves, samples and the
adjoint's transposed solves: every solve still runs its Krylov method on the current J to its
tolerance, and P is refreshed from the current J after a solve that needed more than
``core.tuning.LAGGED_REFRESH_ITERATIONS`` iterations (or failed). In a time loop, where J moves a
little per step, a factorisation then serves many steps and their adjoints. PETSc sees P's values
change and sets the preconditioner up again at its next solve.
"""
from __future__ import annotations

from petsc4py import PETSc

from fempdl.core import matrices
from fempdl.core.tuning import LAGGED_REFRESH_ITERATIONS

__all__ = ["LaggedPreconditioner"]


class LaggedPreconditioner:
    """P for the Jacobian of ``problem`` (J's pattern, assembled once), and when to refresh it.

    Args:
        problem: the NonlinearProblem (its ``J_form`` and ``bcs``).
        stats: the cumulative Newton stats; each refresh counts in ``preconditioner_refreshes``.

    Attributes:
        matrix: P, the matrix the inner preconditioner is set up on.
        stale: P is copied from J at the next Jacobian evaluation (:meth:`refresh_if_stale`).
    """

    def __init__(self, problem, stats):
        self.matrix = matrices.assemble_matrix_into(matrices.create_matrix(problem.J_form), problem.J_form,
                                                    problem.bcs)
        self.stats = stats
        self.stale = True

    def note_solve(self, iterations: int, ok: bool) -> None:
        """After one Newton step's inner solve: refresh at the next Jacobian if it was slow or failed."""
        self.stale |= iterations > LAGGED_REFRESH_ITERATIONS or not ok

    def refresh_if_stale(self, J: PETSc.Mat) -> None:
        """P <- J (just assembled) if :attr:`stale`."""
        if self.stale:
            self.refresh(J)

    def note_transpose_solve(self, J: PETSc.Mat, iterations: int) -> None:
        """After a transposed solve with J: a slow one refreshes P at this J at once, so the next
        solves start from a fresh set-up."""
        if iterations > LAGGED_REFRESH_ITERATIONS:
            self.refresh(J)

    def refresh(self, J: PETSc.Mat) -> None:
        """P <- J: the preconditioner is set up again at its next solve."""
        J.copy(self.matrix, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        self.stale = False
        self.stats.preconditioner_refreshes += 1

    def destroy(self) -> None:
        self.matrix.destroy()
