"""One Newton solve on SNES, for one sample: :class:`NewtonRun`.

From a start u_0 (zero or a warm start, its Dirichlet entries set to the boundary values) SNES runs
Newton's iteration u_k+1 = u_k - a J(u_k)^-1 F(u_k) until its stop rule; the run gives SNES its callbacks
(the residual F(u), the Jacobian J(u), a monitor per step that counts the inner solve), and turns what
happened into a :class:`~fempdl.solve.newton_stats.NewtonSolveStats` (steps, reason, ||F(u_k)||, inner
iterations), the returned state (after a failure, the last iterate whose residual was finite) and, when
recorded, the iterates u_0 ... u_N, each (n,) owned DOF values. A failed solve is reported with what its
message needs (:class:`~fempdl.solve.newton_stats.NewtonFailure`; J and F looked at where F went NaN).

A :class:`~fempdl.solve.nonlinear_system.NonlinearSystem` owns one run and calls it per sample with its
current SNES, options and lagged preconditioner; after a solve that stopped on an error
(:attr:`NewtonRun.stopped_on_error`) it renews the run's vectors and its solvers before the next one.
"""
from __future__ import annotations

import math
import time

from mpi4py import MPI
import numpy as np
from petsc4py import PETSc

from fempdl.core import _dolfinx, matrices
from fempdl.solve import assembly
from fempdl.solve.assembly import Timer
from fempdl.solve.capped_solver import PC_FAILED
from fempdl.solve.lagged_preconditioner import LaggedPreconditioner
from fempdl.solve.newton_options import NewtonOptions
from fempdl.solve.newton_solvers import NewtonSolvers
from fempdl.solve.newton_stats import (
    SNES_REASON_NAMES,
    NewtonFailure,
    NewtonSolveStats,
    ended_nonfinite,
    report_newton_failure,
)
from fempdl.solve.newton_stop import NewtonStop
from fempdl.solve.petsc import rejected_at_set_up
from fempdl.solve.snes import weak_callback
from fempdl.solve.stats import DIVERGED_MAX_IT, REASON_NAMES, SolveStats

__all__ = ["NewtonRun"]

_SNES_MAX_IT = PETSc.SNES.ConvergedReason.DIVERGED_MAX_IT
_INSERT, _FORWARD = PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD
# SNES's stops of a line search or trust region that cannot decrease ||F|| any further.
_STALLED = frozenset(getattr(PETSc.SNES.ConvergedReason, name)
                     for name in ("DIVERGED_LINE_SEARCH", "DIVERGED_TR_DELTA"))
_CONVERGED_EARLY = PETSc.SNES.ConvergedReason.CONVERGED_FNORM_RELATIVE
_SINGULAR_JACOBIAN = PETSc.SNES.ConvergedReason.DIVERGED_JACOBIAN_DOMAIN


class _SingularJacobian(Exception):
    """Raised from the Jacobian callback to stop SNES at a J it cannot solve with."""


class NewtonRun:
    """The vectors and callbacks of one sample's Newton solve (module docstring).

    Args:
        problem: the NonlinearProblem.
        J: the system's Jacobian, which the SNES assembles into (and a failure's diagnosis, at the state
            where F went NaN).
        stats: the system's cumulative Newton stats.
        comm: the mesh's communicator.

    Attributes:
        b, sol: the SNES's residual vector and iterate.
        stopped_on_error: the last solve stopped on an error (PETSc's or a callback's): the system renews
            the vectors (:meth:`renew_vectors`) and its solvers before the next solve.
    """

    def __init__(self, problem, J: PETSc.Mat, stats, comm):
        self.problem, self._J, self.stats, self._comm = problem, J, stats, comm
        self.b = _dolfinx.create_vector(problem.F_form)         # residual
        self.sol = _dolfinx.create_vector(problem.F_form)       # SNES's iterate
        self._accepted = self.sol.duplicate()                    # the monitor's last: a failure's result
        self._reference_state: PETSc.Vec | None = None           # u_ref, made by the first solve from a guess
        self._nonfinite_state = self.sol.duplicate()             # the last state whose residual was NaN or inf
        self._u_vec = _dolfinx.function_vector(problem.u)
        self.stopped_on_error = False
        # What run() was called with, read by the callbacks while SNES runs.
        self._solvers: NewtonSolvers | None = None
        self._options: NewtonOptions | None = None
        self._lagged: LaggedPreconditioner | None = None
        self._called: frozenset = frozenset()
        self._jacobian_defect: str | None = None
        self._recording: list | None = None
        self._residual_norms: list = []
        self._nonfinite_residual = False
        self._first_state = True            # the networks are checked strictly at a solve's first state

    def callbacks(self) -> tuple:
        """The SNES's (residual, jacobian, monitor), through weak references (no cycle with the SNES)."""
        return tuple(map(weak_callback, (self._residual, self._jacobian, self._monitor)))

    def renew_vectors(self) -> None:
        """Fresh residual and iterate vectors (a SNES made after this must take the new ``b``). An error
        inside the inner KSPSolve (Ctrl-C in its monitor) leaves the residual read-locked on PETSc >= 3.2x,
        and the next residual evaluation refuses to write it."""
        self.stopped_on_error = False
        for name in ("sol", "b"):
            getattr(self, name).destroy()
            setattr(self, name, _dolfinx.create_vector(self.problem.F_form))

    def _set_state(self, x: PETSc.Vec) -> None:
        """u <- x (owned values), ghosts updated, and the networks evaluated at it: strictly at a solve's
        first state (a network that gives NaN or a sign it must not is refused by name), as they come at
        later iterates (a step may leave a law's domain, and Newton reports it or a line search shortens it)."""
        x.copy(self._u_vec)
        self._u_vec.ghostUpdate(addv=_INSERT, mode=_FORWARD)
        self.problem.refresh_networks(strict=self._first_state)
        self._first_state = False

    def _residual(self, snes, x, b) -> None:
        with Timer(self.stats, "assembly_time"):
            self._set_state(x)
            p = self.problem
            _dolfinx.assemble_residual_into(b, p.F_form, p.J_form, p.bcs, self._u_vec)
        if not math.isfinite(b.norm(PETSc.NormType.NORM_INFINITY)):
            self._nonfinite_residual = True      # named in the failure message (PETSc's reason differs by version)
            x.copy(self._nonfinite_state)        # where J and F are looked at if Newton ends on it

    def _jacobian(self, snes, x, J, P) -> None:
        with Timer(self.stats, "assembly_time"):
            self._set_state(x)
            matrices.assemble_matrix_into(J, self.problem.J_form, self.problem.bcs)
            # A singular J (an empty row) would give MUMPS a tiny or huge finite step: a failed solve.
            self._jacobian_defect = assembly.operator_defect(J)
        if self._jacobian_defect is not None:
            raise _SingularJacobian(self._jacobian_defect)
        if P.handle != J.handle:                  # P is the lagged preconditioner's
            self._lagged.refresh_if_stale(J)

    def _monitor(self, snes, its, fnorm) -> None:
        self._residual_norms.append(float(fnorm))
        if its > 0:
            ksp = snes.getKSP()
            reason = int(ksp.getConvergedReason())
            iterations = max(int(ksp.getIterationNumber()), 1 if self._options.ksp.direct else 0)
            capped = self._options.ksp.capped and reason == DIVERGED_MAX_IT
            if self._lagged is not None:
                self._lagged.note_solve(iterations, ok=reason > 0)
            self.stats.record("forward", SolveStats(
                iterations=iterations, reason=reason, reason_name=REASON_NAMES.get(reason, str(reason)),
                residual_norm=None, time=0.0, capped=capped, ok=reason > 0 or capped))
        snes.getSolution().copy(self._accepted)
        if self._recording is not None:
            self._recording.append(snes.getSolution().getArray(readonly=True).copy())

    def run(self, solvers: NewtonSolvers, options: NewtonOptions, lagged: LaggedPreconditioner | None,
            guess: np.ndarray | None, record: bool, controls: frozenset) -> tuple[np.ndarray, np.ndarray | None]:
        """One solve with ``solvers.snes`` under ``options`` from ``guess`` (n,) (None: zero; the boundary
        values put in); returns the state (n,) and, with ``record``, the iterates (steps + 1, n). ``lagged``:
        the system's lagged preconditioner when ``options`` lag it; ``controls``: the call's control names (a
        singular J's message names those J depends on). Its stats go to ``stats``; a failure is reported
        (raised or warned, by ``options.on_failure``)."""
        p = self.problem
        self._solvers, self._options, self._lagged, self._called = solvers, options, lagged, controls
        sol = self.sol
        if guess is None:
            sol.set(0.0)
        else:
            sol.setArray(guess)
        _dolfinx.set_bc_values(sol, p.bcs)
        self._residual_norms, self._nonfinite_residual, self._jacobian_defect = [], False, None
        self._recording = [] if record else None
        s = self.stats
        inner_before, solves_before, assembly_before = s.forward_iterations, s.forward_solves, s.assembly_time
        t0 = time.perf_counter()
        self._first_state = True
        reference = self._measure_reference(from_guess=guess is not None)
        self._first_state = True
        try:
            self._solvers.snes.solve(None, sol)
        except BaseException as err:            # a callback's error comes bare or as a PETSc.Error's cause
            self.stopped_on_error = True         # renewed by the next solve (collective: not in this error path)
            cause = err.__cause__ if isinstance(err, PETSc.Error) else err
            if not isinstance(cause, _SingularJacobian):   # that one is a Newton failure, reported below
                if cause is not None and cause is not err and not isinstance(cause, PETSc.Error):
                    raise cause from None      # a callback's own error (Ctrl-C), not PETSc's
                blamed = rejected_at_set_up(self._solvers.ksp, err) if isinstance(err, PETSc.Error) else None
                if blamed is not None:         # a petsc_options value the inner solve's set-up refused
                    raise blamed from None
                raise
        elapsed = time.perf_counter() - t0
        # The inner solves' time: the SNES time less its assemblies, shared by its steps.
        steps_done = self.stats.forward_solves - solves_before
        if steps_done:
            self.stats.forward_time += elapsed - (self.stats.assembly_time - assembly_before)
        snes = self._solvers.snes
        reason = _SINGULAR_JACOBIAN if self._jacobian_defect else int(snes.getConvergedReason())
        steps = int(snes.getIterationNumber())
        del self._residual_norms[steps + 1:]       # a trust region's last, rejected step is no step
        if self._recording is not None:
            del self._recording[steps + 1:]
        capped = self._options.capped and reason == _SNES_MAX_IT and steps == self._options.max_it
        # A failure returns the last iterate the monitor accepted (its residual finite) on every PETSc:
        # 3.18 leaves the step that made F NaN in the solution, 3.25 the iterate before it.
        x = (self._accepted if reason < 0 and not capped else sol).getArray(readonly=True).copy()
        finite = bool(np.isfinite(x).all()) and all(np.isfinite(self._residual_norms))
        finite = self._comm.allreduce(finite, op=MPI.LAND) if self._comm.size > 1 else finite
        if (self._options.capped and reason in _STALLED
                and self._options.tolerances_met(self._residual_norms, reference)):
            # A capped line search or trust region cannot improve a residual at round-off and stops
            # before the cap: the iterate is the solution (plain Newton's extra steps stay there too).
            reason = _CONVERGED_EARLY
        stats = NewtonSolveStats(steps=steps, reason=reason, reason_name=SNES_REASON_NAMES.get(reason, str(reason)),
                                 residual_norms=tuple(self._residual_norms),
                                 inner_iterations=self.stats.forward_iterations - inner_before,
                                 capped=capped, ok=finite and (reason > 0 or capped), time=elapsed,
                                 nonfinite_residual=self._nonfinite_residual, reference_norm=reference)
        self.stats.record_newton(stats)
        iterates = None
        if record:
            iterates, self._recording = np.array(self._recording), None
        # PETSc keeps a failed factorisation failed (a later solve errors): fresh solvers next time.
        self.stopped_on_error |= not stats.ok and int(self._solvers.ksp.getConvergedReason()) == PC_FAILED
        if not stats.ok:
            report_newton_failure(self._options, stats, self._failure(stats))
        return x, iterates

    def _measure_reference(self, from_guess: bool) -> float | None:
        """||F(u_ref)|| (u_ref: zero with the boundary values) for the stop test of a solve from a guess, which
        takes rtol relative to min(||F(u_0)||, ||F(u_ref)||) (:mod:`fempdl.solve.newton_stop`), set as the
        test's reference; one residual assembly, collective. ``None`` (and no assembly) from zero, where
        u_0 = u_ref, and where the SNES's test does not read it (a capped solve that runs exactly max_it
        steps, or rtol = 0)."""
        test = self._solvers.snes.getConvergenceTest()
        stop = test[0] if test else None
        if not isinstance(stop, NewtonStop):
            return None
        stop.reference = None                    # not the last solve's
        if not (from_guess and stop.needs_reference):
            return None
        p = self.problem
        if self._reference_state is None:
            self._reference_state = self.sol.duplicate()
        ref = self._reference_state
        ref.set(0.0)
        _dolfinx.set_bc_values(ref, p.bcs)
        with Timer(self.stats, "assembly_time"):
            self._set_state(ref)
            _dolfinx.assemble_residual_into(self.b, p.F_form, p.J_form, p.bcs, self._u_vec)
        norm = float(self.b.norm())
        stop.reference = norm      # a NaN or inf one is no scale: rtol_scale then takes ||F(u_0)||
        return norm

    def _failure(self, stats: NewtonSolveStats) -> NewtonFailure:
        """What the failure message needs besides the stats (failed solves only; collective): values at hand
        and, after a NaN or inf residual, J and F (without J's lifting of the Dirichlet values) at that state."""
        p, ksp = self.problem, self._solvers.snes.getKSP()     # the failed step's KSP (no monitor call recorded it)
        inner, defect, alone = int(ksp.getConvergedReason()), self._jacobian_defect, None
        if defect is None and self._nonfinite_residual and ended_nonfinite(stats):
            self._set_state(self._nonfinite_state)
            F = _dolfinx.assemble_vector_into(_dolfinx.create_vector(p.F_form), p.F_form)
            alone = math.isfinite(F.norm(PETSc.NormType.NORM_INFINITY))
            F.destroy()
            defect = assembly.operator_defect(matrices.assemble_matrix_into(self._J, p.J_form, p.bcs))
        named = tuple(sorted(self._called & p.jacobian_controls))
        return NewtonFailure(inner_reason=REASON_NAMES.get(inner, str(inner)),
                             inner_iterations=ksp.getIterationNumber(), jacobian_defect=defect,
                             jacobian_controls=named, residual_alone_finite=alone, dirichlet=bool(p.bcs),
                             nullspace=len(p.nullspace) > 0, given_jacobian=p.exact_J_form is not p.J_form)

    def destroy(self) -> None:
        for vec in (self.b, self.sol, self._accepted, self._nonfinite_state, self._reference_state):
            if vec is not None:
                vec.destroy()
