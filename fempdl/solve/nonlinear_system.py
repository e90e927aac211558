"""The discrete system of a NonlinearProblem: batched Newton solves and their adjoints on arrays.

:class:`NonlinearSystem` owns the PETSc objects of one :class:`~fempdl.core.nonlinear_problem.NonlinearProblem`
(the Jacobian J, dF/du when the problem's J is another matrix, the transposed solves' vectors) and, for one
:class:`~fempdl.solve.newton_options.NewtonOptions`, its :class:`~fempdl.solve.newton_solvers.NewtonSolvers`
(the SNES and the adjoint's capped solvers); it keeps the options and caps and composes the parts that do
the work. It works on NumPy arrays of owned DOF values, one row per sample:

* :meth:`solve` — per sample: set the controls and run one Newton solve from the initial guess (zero or
  given; a :class:`~fempdl.solve.newton_run.NewtonRun`: ``max_it`` steps, or to the tolerances);
  optionally keep every iterate u_0 ... u_N (a :class:`NewtonPath`), and measure the capped solves'
  health when handed a :class:`~fempdl.solve.health.CallHealth`;
* :meth:`adjoint` — the implicit gradient at the returned states: J(u)^T lam = g (BC entries zeroed,
  the inner solve's adjoint options), then dJ/dm = -d/dm F(u, lam; m) by assembling the problem's
  gradient forms; :meth:`unrolled_adjoint` — the exact reverse pass of the plain Newton map that was
  run (both answered by its :class:`~fempdl.solve.newton_reverse.NewtonReversePass`, which solves
  with :meth:`transpose_solve`).

A lagged inner preconditioner is a :class:`~fempdl.solve.lagged_preconditioner.LaggedPreconditioner`.
When a solve stops is the system's :class:`~fempdl.solve.newton_stop.NewtonMode`: uncapped solves, and
capped ones whose cap is a budget (implicit differentiation), stop at their tolerances or at the
round-off floor; other capped solves run exactly ``max_it`` steps.

Shapes: ``controls[name]`` is (B, n_m) (broadcast views are fine); solutions, incoming gradients and
adjoints are (B, n), n = ``problem.output_size``.
"""
from __future__ import annotations

import functools
from collections.abc import Collection, Mapping

import numpy as np

from fempdl.core import matrices
from fempdl.core.nonlinear_problem import NonlinearProblem
from fempdl.solve import assembly
from fempdl.solve.assembly import ControlValues, Timer
from fempdl.solve.caps import Caps
from fempdl.solve.control_forms import ControlForms
from fempdl.solve.health import CallHealth
from fempdl.solve.lagged_preconditioner import LaggedPreconditioner
from fempdl.solve.newton_options import NewtonOptions
from fempdl.solve.newton_reverse import NewtonPath, NewtonReversePass
from fempdl.solve.newton_run import NewtonRun
from fempdl.solve.newton_solvers import NewtonSolvers
from fempdl.solve.newton_stats import NewtonCumulativeStats
from fempdl.solve.newton_stop import NewtonMode
from fempdl.solve.round_off import round_off_floor
from fempdl.solve.snes import weak_callback

__all__ = ["NonlinearSystem", "NewtonPath", "NewtonMode"]

_AT_STATE = (", a state where F is undefined (the iterate of a failed Newton solve, returned with a warning "
             "under on_failure='warn': e.g. inverted elements)")
_EXACT_STEPS = NewtonMode()      # the default: a capped solve runs exactly max_it steps


class NonlinearSystem:
    """SNES, Jacobian and vectors of ``problem`` (see the module docstring).

    Args:
        problem: the nonlinear problem.
        options: the Newton options; ``options.ksp`` (the inner solve) must be set.
        mode: when a solve stops (:class:`~fempdl.solve.newton_stop.NewtonMode`, from the layer's diff
            by ``NewtonMode.for_diff``); the default runs a capped solve exactly ``max_it`` steps.
    """

    def __init__(self, problem: NonlinearProblem, options: NewtonOptions, mode: NewtonMode = _EXACT_STEPS):
        if not isinstance(options, NewtonOptions) or options.ksp is None:
            raise ValueError("NonlinearSystem needs NewtonOptions with the inner solve's options (ksp=...)")
        self.problem = problem
        self._comm = problem.V.mesh.comm
        self._destroyed = False
        self._J = matrices.create_matrix(problem.J_form)
        # dF/du for the implicit adjoint: the iteration's J unless the problem's J is another one.
        self._dFdu = self._J if problem.exact_J_form is problem.J_form else matrices.create_matrix(problem.exact_J_form)
        self._rhs, self._lam = self._J.createVecs()
        self._nullspaces = [nsp for A in {id(M): M for M in (self._J, self._dFdu)}.values()
                            for nsp in (assembly.attach_nullspace(A, problem.nullspace),
                                        assembly.attach_nullspace(A, problem.near_nullspace, near=True)) if nsp]
        self.stats = NewtonCumulativeStats()
        self._run = NewtonRun(problem, self._J, self.stats, self._comm)
        self._forms = ControlForms(problem, self._run.b.duplicate(),
                                   functools.partial(Timer, self.stats, "assembly_time"))
        # The reverse passes call transpose_solve through a weak reference: no cycle keeps the system alive.
        self._reverse = NewtonReversePass(problem, self.stats, self._forms, weak_callback(self.transpose_solve))
        self._mode = mode
        self._solvers: NewtonSolvers | None = None
        self._lagged: LaggedPreconditioner | None = None   # made by the first options that lag it, then kept
        self._options = options
        self._build(options)

    # ------------------------------------------------------------ options
    @property
    def mode(self) -> NewtonMode:
        """When the solves stop, fixed for the system's life (its SNES is built for it)."""
        return self._mode

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
        if self._mode.stops_at_tolerances(options) != self._mode.stops_at_tolerances(self._options):
            self.options = options                      # another convergence test: a new SNES
            return
        self._options = options
        self._solvers.snes.setTolerances(**options.snes_tolerances())

    @property
    def inner_max_it(self) -> int | None:
        return self._options.ksp.max_it

    @inner_max_it.setter
    def inner_max_it(self, value: int | None) -> None:
        self.options = self._options.with_inner_max_it(value)      # validates; moves in place

    @property
    def caps(self) -> Caps:
        """The Newton cap and the inner cap as one :class:`~fempdl.solve.caps.Caps`."""
        return Caps(self.max_it, self.inner_max_it)

    @caps.setter
    def caps(self, caps: Caps) -> None:
        # A backward puts back the caps its forward ran at (fempdl.solve.call_state); only what moved is set.
        if caps.inner_max_it != self.inner_max_it:
            self.inner_max_it = caps.inner_max_it
        if caps.max_it != self.max_it:
            self.max_it = caps.max_it

    def _build(self, options: NewtonOptions) -> None:
        p = self.problem
        assembly.check_symmetric_factor(options.ksp, p)
        lagged = self._lagged_preconditioner(options)
        if lagged is not None:
            lagged.stale = True                           # set up on the first Jacobian
        self._solvers = NewtonSolvers(
            options, J=self._J, dFdu=self._dFdu, P=None if lagged is None else lagged.matrix,
            callbacks=self._run.callbacks(), b=self._run.b,
            comm=self._comm, fields=p.fields or None, stats=self.stats, mode=self._mode)

    def _lagged_preconditioner(self, options: NewtonOptions | None = None) -> LaggedPreconditioner | None:
        """The lagged preconditioner if ``options`` (default: the current ones) lag it, made on first use."""
        if not (self._options if options is None else options).ksp.lag_preconditioner:
            return None
        if self._lagged is None:
            self._lagged = LaggedPreconditioner(self.problem, self.stats)
        return self._lagged

    # ----------------------------------------------------------------- solve
    def solve(self, controls: Mapping[str, np.ndarray], batch: int, shared=frozenset(),
              initial_guess: np.ndarray | None = None, keep_for: int | None = None,
              record: bool = False, health: CallHealth | None = None):
        """Newton solves for ``batch`` samples; returns U (batch, n), and with ``record``
        also the :class:`NewtonPath` of the iterates. ``initial_guess`` (batch, n) starts
        the iteration (its Dirichlet entries are replaced by the boundary values). ``keep_for``
        belongs to the linear system's interface (the implicit operator passes it) and is unused: the
        adjoint assembles J at the returned state, not at any iterate's. ``health``: measure
        ||F(u_N)|| / ||F(u_0)|| of each capped solve into it (:mod:`fempdl.solve.health`)."""
        p = self.problem
        n = p.output_size
        U = np.empty((batch, n))
        paths = []
        called = frozenset(controls)
        with ControlValues(p, controls, refresh=False) as ctl:
            for i in range(batch):
                ctl.set_sample(i)
                if self._run.stopped_on_error:
                    self._renew()
                U[i], iterates = self._run.run(self._solvers, self._options, self._lagged_preconditioner(),
                                               None if initial_guess is None else initial_guess[i], record, called)
                paths.append(iterates)
                last = self.stats.last_newton
                if health is not None and last.capped:     # a solve that stopped at a tolerance is healthy
                    health.add(last.residual_norms[-1], last.residual_norms[0],
                               lambda: round_off_floor(self._solvers.snes.getJacobian()[0], self._run.sol.norm()))
        return (U, NewtonPath(paths, self._options.damping)) if record else U

    def _renew(self) -> None:
        """Fresh solvers and iterate after a solve that stopped on an error: PETSc leaves the vectors a
        callback was reading locked (newer versions then refuse to write them). Collective, so it runs
        at the next solve, which every rank calls, not in the error path."""
        self._free_solvers()
        self._J.assemble()     # Ctrl-C between setting J's values and assembling them: PETSc would refuse to zero J
        self._run.renew_vectors()
        self._build(self._options)

    # --------------------------------------------------------------- adjoint
    def adjoint(self, controls: Mapping[str, np.ndarray], U: np.ndarray, G: np.ndarray,
                wanted, shared=frozenset(), initial_guess: bool = False,
                kept_for: int | None = None) -> dict[str, np.ndarray]:
        """Implicit control gradients dJ/dm (batch, n_m) at the states U (batch, n) for incoming
        G = dJ/du (batch, n) (:meth:`NewtonReversePass.adjoint`); ``kept_for`` as ``keep_for`` in
        :meth:`solve`, unused."""
        return self._reverse.adjoint(controls, U, G, wanted, shared, initial_guess=initial_guess)

    def unrolled_adjoint(self, controls: Mapping[str, np.ndarray], path: NewtonPath, G: np.ndarray,
                         wanted, initial_guess: bool = False) -> dict[str, np.ndarray]:
        """The exact vector-Jacobian product of the plain Newton map that produced ``path``
        (:meth:`NewtonReversePass.unrolled_adjoint`)."""
        return self._reverse.unrolled_adjoint(controls, path, G, wanted, initial_guess=initial_guess)

    def transpose_solve(self, u: np.ndarray, g: np.ndarray, exact: bool = False,
                        controls: Collection[str] = frozenset()) -> None:
        """Assemble J(u) (u (n,) set as the problem's state; with ``exact`` dF/du, else the iteration's J)
        and solve J^T lam = g (g (n,)) into ``problem.lam``; a singular J's message names those of
        ``controls`` (the call's control names) that J depends on."""
        p = self.problem
        assembly.set_owned(p.u, u, p.output_size)
        p.refresh_networks()
        A, form, solver = ((self._dFdu, p.exact_J_form, self._solvers.exact_adjoint) if exact
                           else (self._J, p.J_form, self._solvers.adjoint))
        with Timer(self.stats, "assembly_time"):
            matrices.assemble_matrix_into(A, form, p.bcs)
            depends = p.exact_jacobian_controls if exact else p.jacobian_controls
            assembly.check_operator(A, sorted(set(controls) & depends), _AT_STATE)
        self._rhs.setArray(g)
        solved = solver.solve_transpose(self._rhs, self._lam)
        lagged = self._lagged_preconditioner()
        if A is self._J and lagged is not None:
            lagged.note_transpose_solve(self._J, solved.iterations)
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
        objs = [self._J, self._rhs, self._lam, *self._nullspaces]
        if self._dFdu is not self._J:
            objs.append(self._dFdu)
        for obj in objs:
            obj.destroy()
        for part in (self._run, self._lagged, self._reverse, self._forms):
            if part is not None:
                part.destroy()

    def __del__(self):
        try:
            self.destroy()
        except Exception:  # interpreter shutdown: PETSc may already be finalised
            pass

