"""The discrete system of a NonlinearProblem: batched Newton solves and their adjoints on arrays.

:class:`NonlinearSystem` owns the PETSc objects of one :class:`~fempdl.core.nonlinear_problem.NonlinearProblem`
(Jacobian, residual and solution vectors) and, for one :class:`~fempdl.solve.newton_options.NewtonOptions`,
its :class:`~fempdl.solve.newton_solvers.NewtonSolvers` (the SNES and the adjoint's capped solvers). It
works on NumPy arrays of owned DOF values, one row per sample:

* :meth:`solve` — per sample: set the controls, put the boundary values into the initial guess (zero or
  given) and run SNES (``max_it`` steps, or to the tolerances); optionally keep every iterate
  u_0 ... u_N (a :class:`NewtonPath`);
* :meth:`adjoint` — the implicit gradient at the returned states: J(u)^T lam = g (BC entries zeroed,
  the inner solve's adjoint options), then dJ/dm = -d/dm F(u, lam; m) by assembling the problem's
  gradient forms; :meth:`unrolled_adjoint` — the exact reverse pass of the plain Newton map that was
  run (both: :class:`~fempdl.solve.newton_reverse.NewtonReversePass`).

A lagged inner preconditioner (``KSPOptions(lag_preconditioner=True)``, the ``"lu-lagged"`` preset) is
set up on a copy P of an earlier J and kept across Newton steps, solves, samples and the adjoint's
transposed solves: every solve still runs its Krylov method on the current J to its tolerance, and P
is refreshed from the current J after a solve that needed more than
``core.tuning.LAGGED_REFRESH_ITERATIONS`` iterations. In a time loop, where J moves a little per
step, a factorisation then serves many steps and their adjoints.

When a solve stops: uncapped solves, and capped ones whose cap is a ``budget`` (implicit
differentiation), stop at their tolerances or at the round-off floor
(:class:`~fempdl.solve.newton_stop.NewtonStop`); other capped solves run exactly ``max_it`` steps.

Shapes: ``controls[name]`` is (B, n_m) (broadcast views are fine); solutions, incoming gradients and
adjoints are (B, n), n = ``problem.output_size``.
"""
from __future__ import annotations

import functools
import math
import time
from collections.abc import Mapping

from mpi4py import MPI
import numpy as np
from petsc4py import PETSc

from fempdl.core import _dolfinx, matrices
from fempdl.core.nonlinear_problem import NonlinearProblem
from fempdl.core.tuning import LAGGED_REFRESH_ITERATIONS
from fempdl.solve import assembly
from fempdl.solve.assembly import ControlValues, Timer
from fempdl.solve.capped_solver import PC_FAILED
from fempdl.solve.control_forms import ControlForms
from fempdl.solve.health import CallHealth, round_off_floor
from fempdl.solve.newton_options import NewtonOptions
from fempdl.solve.newton_reverse import NewtonPath, NewtonReversePass
from fempdl.solve.newton_solvers import NewtonSolvers
from fempdl.solve.newton_stats import (
    SNES_REASON_NAMES,
    NewtonCumulativeStats,
    NewtonFailure,
    NewtonSolveStats,
    ended_nonfinite,
    report_newton_failure,
)
from fempdl.solve.newton_stop import NewtonStop
from fempdl.solve.petsc import rejected_at_set_up
from fempdl.solve.snes import weak_callback
from fempdl.solve.stats import DIVERGED_MAX_IT, REASON_NAMES, SolveStats

__all__ = ["NonlinearSystem", "NewtonPath"]

_SNES_MAX_IT = PETSc.SNES.ConvergedReason.DIVERGED_MAX_IT
_INSERT, _FORWARD = PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD
# SNES's stops of a line search or trust region that cannot decrease ||F|| any further.
_STALLED = frozenset(getattr(PETSc.SNES.ConvergedReason, name)
                     for name in ("DIVERGED_LINE_SEARCH", "DIVERGED_TR_DELTA"))
_CONVERGED_EARLY = PETSc.SNES.ConvergedReason.CONVERGED_FNORM_RELATIVE
_SINGULAR_JACOBIAN = PETSc.SNES.ConvergedReason.DIVERGED_JACOBIAN_DOMAIN
_AT_STATE = (", a state where F is undefined (the iterate of a failed Newton solve, returned with a warning "
             "under on_failure='warn': e.g. inverted elements)")


class _SingularJacobian(Exception):
    """Raised from the Jacobian callback to stop SNES at a J it cannot solve with."""


class NonlinearSystem(NewtonReversePass):
    """SNES, Jacobian and vectors of ``problem`` (see the module docstring).

    Args:
        problem: the nonlinear problem.
        options: the Newton options; ``options.ksp`` (the inner solve) must be set.
        budget: a capped solve may stop at its tolerances before the cap (implicit gradients, exact
            at a converged state); otherwise it runs exactly ``max_it`` steps.
        force_step: take at least one Newton step even from a solution (an unrolled
            derivative needs one: the map is not the identity near a solution).
    """

    def __init__(self, problem: NonlinearProblem, options: NewtonOptions, force_step: bool = False,
                 budget: bool = False):
        if not isinstance(options, NewtonOptions) or options.ksp is None:
            raise ValueError("NonlinearSystem needs NewtonOptions with the inner solve's options (ksp=...)")
        self.problem = problem
        self._comm = problem.V.mesh.comm
        self._destroyed = False
        self._J = matrices.create_matrix(problem.J_form)
        self._b = _dolfinx.create_vector(problem.F_form)        # residual
        self._sol = _dolfinx.create_vector(problem.F_form)      # SNES's iterate
        self._accepted = self._sol.duplicate()                   # the monitor's last: a failure's result
        self._nonfinite_state = self._sol.duplicate()            # the last state whose residual was NaN or inf
        self._u_vec = _dolfinx.function_vector(problem.u)
        # dF/du for the implicit adjoint: the iteration's J unless the problem's J is another one.
        self._dFdu = self._J if problem.exact_J_form is problem.J_form else matrices.create_matrix(problem.exact_J_form)
        self._rhs, self._lam = self._J.createVecs()
        self._nullspaces = [nsp for A in {id(M): M for M in (self._J, self._dFdu)}.values()
                            for nsp in (assembly.attach_nullspace(A, problem.nullspace),
                                        assembly.attach_nullspace(A, problem.near_nullspace, near=True)) if nsp]
        self.stats = NewtonCumulativeStats()
        self._forms = ControlForms(problem, self._b.duplicate(), functools.partial(Timer, self.stats, "assembly_time"))
        self._step_vectors: dict = {}
        self._force_step, self._budget = force_step, budget
        self._stopped_on_error = False
        self._called_controls: frozenset = frozenset()     # named when an assembled Jacobian is singular
        self._jacobian_defect: str | None = None
        self._solvers: NewtonSolvers | None = None
        self._P: PETSc.Mat | None = None               # a lagged preconditioner's matrix (module docstring)
        self._refresh_P = False
        self._options = options
        self._build(options)
        self._recording: list | None = None
        self._residual_norms: list = []
        self._nonfinite_residual = False
        #: The last call's ||F(u_N)|| / ||F(u_0)|| of capped solves, measured when its limit is set (a layer's
        #: health check sets it: :mod:`fempdl.solve.health`).
        self.call_health = CallHealth()

    # ------------------------------------------------------------ options
    @property
    def options(self) -> NewtonOptions:
        return self._options

    @options.setter
    def options(self, options: NewtonOptions) -> None:
        """New options: a moved inner cap moves in place (:class:`NewtonSolvers`), others build new solvers."""
        if options.ksp is None:
            raise ValueError("NewtonOptions.ksp must be set")
        if options == self._options:
            return
        if options == self._options.with_inner_max_it(options.ksp.max_it):
            self._solvers.inner_max_it = options.ksp.max_it
            self._options = options
            return
        self._free_solvers()
        self._options = options
        self._build(options)

    @property
    def max_it(self) -> int | None:
        return self._options.max_it

    @max_it.setter
    def max_it(self, value: int | None) -> None:
        options = self._options.with_max_it(value)     # validates
        if self._stops_at_tolerances(options) != self._stops_at_tolerances(self._options):
            self.options = options                      # another convergence test: a new SNES
            return
        self._options = options
        self._solvers.snes.setTolerances(**options.snes_tolerances())

    def _stops_at_tolerances(self, options: NewtonOptions) -> bool:
        return not options.capped or self._budget

    @property
    def inner_max_it(self) -> int | None:
        return self._options.ksp.max_it

    @inner_max_it.setter
    def inner_max_it(self, value: int | None) -> None:
        # A backward puts back the inner cap its forward ran at (fempdl.solve.call_state).
        self.options = self._options.with_inner_max_it(value)      # validates; moves in place

    def _build(self, options: NewtonOptions) -> None:
        p = self.problem
        assembly.check_symmetric_factor(options.ksp, p)
        lagged = options.ksp.lag_preconditioner
        if lagged and self._P is None:      # J's pattern, assembled: refreshes copy values only
            self._P = matrices.assemble_matrix_into(matrices.create_matrix(p.J_form), p.J_form, p.bcs)
        self._refresh_P = lagged                          # set up on the first Jacobian
        stop = (NewtonStop(options.rtol, options.atol, force_step=self._force_step)
                if self._stops_at_tolerances(options) else None)
        self._solvers = NewtonSolvers(
            options, J=self._J, dFdu=self._dFdu, P=self._P if lagged else None,
            callbacks=tuple(map(weak_callback, (self._residual, self._jacobian, self._monitor))), b=self._b,
            comm=self._comm, fields=p.fields or None, stats=self.stats, force_step=self._force_step, stop=stop)

    # ----------------------------------------------------------- callbacks
    def _set_state(self, x: PETSc.Vec) -> None:
        """u <- x (owned values), ghosts updated."""
        x.copy(self._u_vec)
        self._u_vec.ghostUpdate(addv=_INSERT, mode=_FORWARD)

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
        if P.handle != J.handle and self._refresh_P:
            self._set_preconditioner_matrix()

    def _set_preconditioner_matrix(self) -> None:
        """P <- J: the lagged preconditioner is set up again at its next solve (PETSc sees P changed)."""
        self._J.copy(self._P, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        self._refresh_P = False
        self.stats.preconditioner_refreshes += 1

    def _monitor(self, snes, its, fnorm) -> None:
        self._residual_norms.append(float(fnorm))
        if its > 0:
            ksp = snes.getKSP()
            reason = int(ksp.getConvergedReason())
            iterations = max(int(ksp.getIterationNumber()), 1 if self._options.ksp.direct else 0)
            capped = self._options.ksp.capped and reason == DIVERGED_MAX_IT
            if self._P is not None and self._options.ksp.lag_preconditioner:
                self._refresh_P |= iterations > LAGGED_REFRESH_ITERATIONS or reason <= 0
            self.stats.record("forward", SolveStats(
                iterations=iterations, reason=reason, reason_name=REASON_NAMES.get(reason, str(reason)),
                residual_norm=None, time=0.0, capped=capped, ok=reason > 0 or capped))
        snes.getSolution().copy(self._accepted)
        if self._recording is not None:
            self._recording.append(snes.getSolution().getArray(readonly=True).copy())

    # ----------------------------------------------------------------- solve
    def solve(self, controls: Mapping[str, np.ndarray], batch: int, shared=frozenset(),
              initial_guess: np.ndarray | None = None, keep_matrices: bool = False,
              record: bool = False):
        """Newton solves for ``batch`` samples; returns U (batch, n), and with ``record``
        also the :class:`NewtonPath` of the iterates. ``initial_guess`` (batch, n) starts
        the iteration (its Dirichlet entries are replaced by the boundary values). ``keep_matrices``
        belongs to the linear system's interface (the implicit operator passes it) and is unused: the
        adjoint assembles J at the returned state, not at any iterate's."""
        p = self.problem
        n = p.output_size
        U = np.empty((batch, n))
        paths = [] if record else None
        self._called_controls = frozenset(controls)
        self.call_health = CallHealth(self.call_health.limit)
        with ControlValues(p, controls) as ctl:
            for i in range(batch):
                ctl.set_sample(i)
                U[i] = self._solve_one(None if initial_guess is None else initial_guess[i], paths)
                last = self.stats.last_newton
                if self.call_health.measuring and last.capped:     # a solve that stopped at a tolerance is healthy
                    self.call_health.add(last.residual_norms[-1], last.residual_norms[0],
                                         lambda: round_off_floor(self._solvers.snes.getJacobian()[0], self._sol.norm()))
        return (U, NewtonPath(paths, self._options.damping)) if record else U

    def _solve_one(self, guess: np.ndarray | None, paths: list | None) -> np.ndarray:
        p = self.problem
        if self._stopped_on_error:
            self._renew()
        sol = self._sol
        if guess is None:
            sol.set(0.0)
        else:
            sol.setArray(guess)
        _dolfinx.set_bc_values(sol, p.bcs)
        self._residual_norms, self._nonfinite_residual, self._jacobian_defect = [], False, None
        self._recording = [] if paths is not None else None
        s = self.stats
        inner_before, solves_before, assembly_before = s.forward_iterations, s.forward_solves, s.assembly_time
        t0 = time.perf_counter()
        try:
            self._solvers.snes.solve(None, sol)
        except BaseException as err:            # a callback's error comes bare or as a PETSc.Error's cause
            self._stopped_on_error = True        # renewed by the next solve (collective: not in this error path)
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
        if self._options.capped and reason in _STALLED and self._options.tolerances_met(self._residual_norms):
            # A capped line search or trust region cannot improve a residual at round-off and stops
            # before the cap: the iterate is the solution (plain Newton's extra steps stay there too).
            reason = _CONVERGED_EARLY
        stats = NewtonSolveStats(steps=steps, reason=reason, reason_name=SNES_REASON_NAMES.get(reason, str(reason)),
                                 residual_norms=tuple(self._residual_norms),
                                 inner_iterations=self.stats.forward_iterations - inner_before,
                                 capped=capped, ok=finite and (reason > 0 or capped), time=elapsed,
                                 nonfinite_residual=self._nonfinite_residual)
        self.stats.record_newton(stats)
        if paths is not None:
            paths.append(np.array(self._recording))
            self._recording = None
        # PETSc keeps a failed factorisation failed (a later solve errors): fresh solvers next time.
        self._stopped_on_error |= not stats.ok and int(self._solvers.ksp.getConvergedReason()) == PC_FAILED
        if not stats.ok:
            report_newton_failure(self._options, stats, self._failure(stats))
        return x

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
        named = tuple(sorted(self._called_controls & p.jacobian_controls))
        return NewtonFailure(inner_reason=REASON_NAMES.get(inner, str(inner)),
                             inner_iterations=ksp.getIterationNumber(), jacobian_defect=defect,
                             jacobian_controls=named, residual_alone_finite=alone, dirichlet=bool(p.bcs),
                             nullspace=len(p.nullspace) > 0, given_jacobian=p.exact_J_form is not p.J_form)

    def _renew(self) -> None:
        """Fresh solvers and iterate after a solve that stopped on an error: PETSc leaves the vectors a
        callback was reading locked (newer versions then refuse to write them). Collective, so it runs
        at the next solve, which every rank calls, not in the error path."""
        self._stopped_on_error = False
        self._free_solvers()
        self._J.assemble()     # Ctrl-C between setting J's values and assembling them: PETSc would refuse to zero J
        # An error inside the inner KSPSolve (Ctrl-C in its monitor) leaves the residual read-locked on
        # PETSc >= 3.2x, and the next residual evaluation refuses to write it: fresh vectors for both.
        for name in ("_sol", "_b"):
            getattr(self, name).destroy()
            setattr(self, name, _dolfinx.create_vector(self.problem.F_form))
        self._build(self._options)

    # --------------------------------------------------------------- adjoint
    def _transpose_solve(self, u: np.ndarray, g: np.ndarray, exact: bool = False) -> None:
        """Assemble J(u) (u set as the problem's state; with ``exact`` dF/du, else the iteration's J)
        and solve J^T lam = g into ``problem.lam``."""
        p = self.problem
        assembly.set_owned(p.u, u, p.output_size)
        A, form, solver = ((self._dFdu, p.exact_J_form, self._solvers.exact_adjoint) if exact
                           else (self._J, p.J_form, self._solvers.adjoint))
        with Timer(self.stats, "assembly_time"):
            matrices.assemble_matrix_into(A, form, p.bcs)
            assembly.check_operator(A, sorted(self._called_controls & (p.exact_jacobian_controls if exact
                                                              else p.jacobian_controls)), _AT_STATE)
        self._rhs.setArray(g)
        solved = solver.solve_transpose(self._rhs, self._lam)
        if A is self._J and self._P is not None and self._options.ksp.lag_preconditioner \
                and solved.iterations > LAGGED_REFRESH_ITERATIONS:
            self._set_preconditioner_matrix()     # at this J: the next solves start from a fresh set-up
        assembly.set_owned(p.lam, self._lam.getArray(readonly=True), p.output_size)

    # --------------------------------------------------------------- cleanup
    def _free_solvers(self) -> None:
        if self._solvers is not None:
            self._solvers.destroy()
        self._solvers = None

    def destroy(self) -> None:
        """Free the PETSc objects (the system is unusable afterwards); a second call does nothing."""
        if getattr(self, "_destroyed", True):
            return
        self._destroyed = True
        self._free_solvers()
        objs = [self._J, self._b, self._sol, self._accepted, self._nonfinite_state, self._rhs, self._lam,
                *self._step_vectors.values(), *self._nullspaces]
        if self._dFdu is not self._J:
            objs.append(self._dFdu)
        if self._P is not None:
            objs.append(self._P)
        for obj in objs:
            obj.destroy()
        self._forms.destroy()

    def __del__(self):
        try:
            self.destroy()
        except Exception:  # interpreter shutdown: PETSc may already be finalised
            pass

