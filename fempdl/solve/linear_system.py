"""The assembled discrete system of a Problem: batched solves and adjoints on arrays.

:class:`LinearSystem` owns the PETSc objects of one Problem for one solver
configuration (matrix, work vectors, the capped solver, control-to-RHS
matrices) and works on NumPy arrays of owned DOF values, one row per sample:

* :meth:`LinearSystem.solve` — for each sample i: set the controls, assemble
  what depends on them, solve A(m_i) u_i = b(m_i) with the capped solver.
* :meth:`LinearSystem.adjoint` — for each sample: A(m_i)^T lam_i = g_i with the
  BC entries of g_i zeroed, then dJ/dm for each requested control, either as
  C_m^T lam_i (controls that enter the RHS affinely) or by assembling the
  problem's gradient form with u = u_i and lam = lam_i.

What does not depend on the controls passed in a call is assembled once and
reused while its inputs are unchanged (a fingerprint of the coefficient and
constant values it was assembled with detects user edits). The Functions of
controls passed in a call are restored to their previous values afterwards.

Shapes: ``controls[name]`` is (B, n_m) (a broadcast view is fine); solutions,
incoming gradients and adjoints are (B, n) with n = ``problem.output_size``.
"""
from __future__ import annotations

import functools
from collections.abc import Mapping

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from fempdl.core import _dolfinx, matrices
from fempdl.core.nullspaces import constant_modes
from fempdl.core.problem import Problem
from fempdl.solve import assembly
from fempdl.solve.assembly import ControlValues, Timer
from fempdl.solve.batched_calls import BatchedCalls
from fempdl.solve.capped_solver import CappedSolver
from fempdl.solve.caps import Caps
from fempdl.solve.control_forms import ControlForms
from fempdl.solve.health import CallHealth
from fempdl.solve.options import KSPOptions
from fempdl.solve.petsc import petsc_to_scipy
from fempdl.solve.round_off import round_off_floor
from fempdl.solve.stats import CumulativeStats, record_batch

__all__ = ["LinearSystem", "INITIAL_GUESS"]

INITIAL_GUESS = "initial_guess"   # the key of the starting point's gradient in LinearSystem.adjoint


class LinearSystem:
    """Assembled matrix, vectors and capped solver of ``problem``.

    Args:
        problem: the variational problem.
        options: solver options (the cap can be moved later via ``max_it``).
        batched_engine: an engine that solves all samples of a call at once
            (:class:`fempdl.iterative.batched.BatchedEngine`), used where ``options.engine``
            and the call allow it; ``None`` runs every solve through PETSc.
    """

    def __init__(self, problem: Problem, options: KSPOptions, *, batched_engine=None):
        self._comm = problem.V.mesh.comm
        if options.engine == "batched":
            reason = ("no batched engine was given" if batched_engine is None
                      else "the operator has a null space (the engine does not project it out)"
                      if len(problem.nullspace)
                      else batched_engine.unsupported_reason(options, self._comm.size))
            if reason is not None:
                raise ValueError(f"engine='batched' cannot run these options: {reason}; "
                                 "use engine='auto' or engine='petsc'")
        assembly.check_symmetric_factor(options, problem)
        self.problem = problem
        self._batched = (None if options.engine == "petsc" or len(problem.nullspace) or batched_engine is None
                         else BatchedCalls(batched_engine))
        # A symmetric factorisation's first matrix is checked for symmetry (the flag is the user's word).
        self._symmetry_unchecked = options.pc_type in assembly.SYMMETRIC_PC_TYPES
        self._singular_unchecked = not len(problem.nullspace)     # a declared null space is projected out
        self._A = matrices.create_matrix(problem.a_form)
        self._destroyed = False
        self._b = _dolfinx.create_vector(problem.L_form)       # ghosted: assembly target
        self._x, self._rhs = self._A.createVecs()              # solution / transposed RHS
        self._work = None                                       # a residual's work vector, made when needed
        self._nullspace = assembly.attach_nullspace(self._A, problem.nullspace)
        self._near_nullspace = assembly.attach_nullspace(self._A, problem.near_nullspace, near=True)
        self._solver = CappedSolver(self._A, options, fields=problem.fields or None)
        self._A_inputs = None                                  # fingerprint of the assembled A
        self._A_version = 0                                    # bumped at every assembly of A
        # b(0), C_m and gradient vectors; timed by a Timer on the stats, not a method of self (no reference cycle:
        # the system is freed as soon as its last owner drops it)
        self._forms = ControlForms(problem, self._b, functools.partial(Timer, self._solver.stats, "assembly_time"))
        self._kept_matrices = assembly.KeptMatrices()

    # ------------------------------------------------------------ properties
    @property
    def options(self) -> KSPOptions:
        return self._solver.options

    @property
    def max_it(self) -> int | None:
        return self._solver.max_it

    @max_it.setter
    def max_it(self, value: int | None) -> None:
        self._solver.max_it = value

    @property
    def caps(self) -> Caps:
        """The solve's cap as a :class:`~fempdl.solve.caps.Caps` (a linear solve has no inner cap)."""
        return Caps(self.max_it)

    @caps.setter
    def caps(self, caps: Caps) -> None:
        if caps.inner_max_it is not None:
            raise ValueError(f"a linear solve has one cap, max_it; got {caps}")
        self.max_it = caps.max_it

    @property
    def stats(self) -> CumulativeStats:
        return self._solver.stats

    # ----------------------------------------------------------------- solve
    def solve(self, controls: Mapping[str, np.ndarray], batch: int, shared=frozenset(),
              initial_guess: np.ndarray | None = None, keep_for: int | None = None,
              health: CallHealth | None = None) -> np.ndarray:
        """Forward solves for ``batch`` samples; returns U of shape (batch, n).

        ``shared`` names controls whose rows are all equal (one tensor for the
        whole batch): a matrix that depends only on those is assembled once.
        ``initial_guess`` (batch, n) warm-starts the iterations (a broadcast view is fine).
        ``keep_for``: a call's serial number (:class:`~fempdl.solve.call_state.CallState`): keep copies of
        per-sample matrices for that call's adjoint (it then copies them instead of assembling again).
        ``health``: measure the residual ratio of each capped solve into it (:mod:`fempdl.solve.health`).
        """
        p = self.problem
        names = frozenset(controls)
        per_sample_matrix = bool((names - frozenset(shared)) & p.matrix_controls)
        # Matrix fixed and every passed control a pure RHS term: b_i = b_base + sum_m C_m m_i.
        affine = not (names & p.matrix_controls) and names <= p.affine_rhs_controls
        use_batched = self._use_batched(batch, per_sample_matrix)
        U = np.empty((batch, p.output_size))
        kept = self._kept_matrices.start(keep_for, batch) if keep_for and per_sample_matrix else None
        health = health if self.options.capped else None      # a solve to its tolerances is healthy
        with ControlValues(p, controls) as ctl:
            self._prepare_matrix(names, per_sample_matrix, ctl)
            b_base = self._forms.base_rhs(names, ctl) if affine else None
            if affine and use_batched:
                # All right-hand sides at once: b_i = b_base + sum_m C_m m_i (no per-sample PETSc calls).
                with self._assembling():
                    R = self._forms.affine_rhs_block(b_base, controls, batch)
                return self._batched_forward(R, initial_guess, health)
            rhs_mats = {name: self._forms.rhs_matrix(name) for name in sorted(names)} if affine else {}
            many = self._direct_many(batch, per_sample_matrix)
            for i in range(batch):
                if affine:
                    with self._assembling():
                        self._forms.affine_rhs_into(self._b, b_base, rhs_mats, controls, i)
                else:
                    ctl.set_sample(i)
                    if per_sample_matrix:
                        self._assemble_matrix_if_changed(names)
                        if kept is not None:
                            kept.append(self._A)
                    with self._assembling():
                        _dolfinx.assemble_vector_into(self._b, p.L_form, p.a_form, p.bcs)
                if use_batched or many:
                    U[i] = self._b.getArray(readonly=True)     # the RHS; solved below
                else:
                    if initial_guess is not None:
                        self._x.setArray(initial_guess[i])
                    start = self._residual_norm() if health is not None and initial_guess is not None else None
                    self._lag_preconditioner(per_sample_matrix and i > 0)
                    self._solver.solve(self._b, self._x, warm=initial_guess is not None)
                    U[i] = self._x.getArray(readonly=True)
                    if health is not None:      # from zero r_0 = b (its null-space part removed by the solve)
                        health.add(self._residual_norm(), self._b.norm() if start is None else start,
                                   lambda: round_off_floor(self._A, self._x.norm(), self._b.norm()))
            self._lag_preconditioner(False)
        if use_batched:
            U = self._batched_forward(U, initial_guess, health)
        elif many:
            U = self._solver.solve_many(U)
        return U

    def _residual_norm(self) -> float:
        """||b - A x|| of the current b and x (the transposed RHS vector is the work vector)."""
        self._A.mult(self._x, self._rhs)
        self._rhs.aypx(-1.0, self._b)
        return self._rhs.norm()

    def _transposed_residual_norm(self) -> float:
        """||g - A^T lam|| of the transposed RHS g and the current lam (x), in a work vector."""
        if self._work is None:
            self._work = self._rhs.duplicate()
        self._A.multTranspose(self._x, self._work)
        self._work.aypx(-1.0, self._rhs)
        return self._work.norm()

    def _batched_forward(self, R: np.ndarray, initial_guess: np.ndarray | None, health: CallHealth | None):
        """The forward solves of R's rows on the batched engine, their residual ratios measured into ``health``."""
        X = self._batched_solve(R, "forward", initial_guess)
        if health is not None:
            starts = R if initial_guess is None else R - self._batched.matmul(np.asarray(initial_guess))
            norms = [np.linalg.norm(M, axis=1) for M in (R - self._batched.matmul(X), starts, X, R)]
            health.add_rows(*norms, lambda: self._A.norm(PETSc.NormType.INFINITY))
        return X

    def _direct_many(self, batch: int, per_sample_matrix: bool) -> bool:
        """Whether a call's direct solves share one factorisation and one MatMatSolve."""
        return (self.options.direct and batch > 1 and not per_sample_matrix and self._comm.size == 1
                and not len(self.problem.nullspace))

    def adjoint(self, controls: Mapping[str, np.ndarray], U: np.ndarray, G: np.ndarray,
                wanted, shared=frozenset(), initial_guess: bool = False,
                health: CallHealth | None = None, kept_for: int | None = None) -> dict[str, np.ndarray]:
        """Control gradients dJ/dm (batch, n_m) for m in ``wanted``, given the
        forward solutions U and incoming gradients G = dJ/du, both (batch, n);
        ``health``: measure each capped adjoint's residual ratio ||G - A^T lam|| / ||G|| into it;
        ``kept_for``: the serial number of the forward call whose kept per-sample matrices to use (None:
        assemble them; the caller has put back what the forward read).

        With ``initial_guess`` the result also holds ``"initial_guess"`` (batch, n):
        the adjoint residual G - A^T lam, which is the exact derivative of the
        K-step Richardson map with respect to its starting point ((I - D^-1 A)^K
        transposed, applied to G), tends to 0 as the solve converges, and is 0
        for a direct solve (whose result does not depend on a guess)."""
        p = self.problem
        batch = G.shape[0]
        wanted = [n for n in p.input_names if n in set(wanted)]
        names = frozenset(controls)
        per_sample_matrix = bool((names - frozenset(shared)) & p.matrix_controls)
        use_batched = self._use_batched(batch, per_sample_matrix)
        by_matrix = [n for n in wanted if n in p.affine_rhs_controls]
        by_form = [n for n in wanted if n not in p.affine_rhs_controls]
        grads = {n: np.zeros((batch, p.control_size(n))) for n in wanted}
        residual = initial_guess and not self.options.adjoint_options.direct
        health = health if self.options.adjoint_options.capped else None     # a converged adjoint is healthy
        if initial_guess:
            grads[INITIAL_GUESS] = np.zeros((batch, p.output_size))
        G = assembly.without_bc_entries(G, p)
        n_owned = p.output_size
        kept = self._kept_matrices.find(kept_for, batch) if per_sample_matrix else None
        with ControlValues(p, controls) as ctl:
            self._prepare_matrix(names, per_sample_matrix, ctl)
            rhs_mats = {name: self._forms.rhs_matrix(name) for name in by_matrix}
            Lam = self._batched_solve(G, "backward") if use_batched else None
            if use_batched and (residual or health is not None):
                R = G - self._batched.matmul(Lam, transpose=True)      # the adjoint residual, for both
                if health is not None:
                    norms = [np.linalg.norm(M, axis=1) for M in (R, G, Lam, G)]
                    health.add_rows(*norms, lambda: self._A.norm(PETSc.NormType.INFINITY))
                if residual:
                    grads[INITIAL_GUESS] = R
            if (Lam is None and self._direct_many(batch, per_sample_matrix)
                    and self._solver.can_solve_many_transpose(p.symmetric)):
                # Every sample's transposed solve by the forward's factors at once (a time step's LU).
                Lam = self._solver.solve_many(G, transpose=True, symmetric=p.symmetric)
            solved = Lam is not None
            if solved and not per_sample_matrix and not by_form:
                with self._assembling():    # C_m^T lam_i, the gradient forms' values, in one product
                    for name in rhs_mats:
                        grads[name] = np.asarray((self._forms.rhs_matrix_scipy(name, transpose=True) @ Lam.T).T)
                return grads
            for i in range(batch):
                if per_sample_matrix or by_form:
                    ctl.set_sample(i)
                if solved:
                    self._x.setArray(Lam[i])
                else:
                    if per_sample_matrix and self._matrix_is_current():
                        pass                               # e.g. one sample: A still holds its matrix and factor
                    elif kept is not None:
                        kept.restore(i, self._A)
                        self._A_version += 1
                        self._A_inputs = assembly.fingerprint(p.matrix_inputs())
                    elif per_sample_matrix:
                        self._assemble_matrix(names)
                    self._lag_preconditioner(per_sample_matrix and i > 0)
                    self._rhs.setArray(G[i])
                    self._solver.solve_transpose(self._rhs, self._x)
                    if health is not None:         # G_i, its null-space part removed by the solve, against A^T lam
                        start = self._rhs.norm()
                        health.add(self._transposed_residual_norm(), start,
                                   lambda start=start: round_off_floor(self._A, self._x.norm(), start))
                    if residual:
                        self._A.multTranspose(self._x, self._rhs)
                        grads[INITIAL_GUESS][i] = G[i] - self._rhs.getArray(readonly=True)
                with self._assembling():                       # the gradient form's value for an affine control
                    for name, (C, on_control, _, _) in rhs_mats.items():
                        C.multTranspose(self._x, on_control)   # C_m^T lam lives on m's space
                        grads[name][i] = on_control.getArray(readonly=True)
                if by_form:
                    assembly.set_owned(p.lam, self._x.getArray(readonly=True), n_owned)
                    assembly.set_owned(p.u, U[i], n_owned)
                    for name in by_form:
                        grads[name][i] = self._forms.gradient(name)
            self._lag_preconditioner(False)
        return grads

    def affine_rhs(self, names: frozenset) -> tuple:
        """The pieces of b(m) = b_base + sum_m C_m m for affine right-hand-side controls ``names``
        (:meth:`~fempdl.solve.control_forms.ControlForms.affine_parts`)."""
        return self._forms.affine_parts(frozenset(names))

    def constant_matrix(self) -> sp.csr_matrix:
        """A as scipy CSR, for a problem whose matrix depends on no control passed in a call."""
        self._assemble_matrix_if_changed()
        return petsc_to_scipy(self._A)

    def matrix_with(self, name: str, values: np.ndarray, bc_diagonal: float = 1.0) -> sp.csr_matrix:
        """A assembled with control ``name`` set to ``values`` (owned DOFs) and
        ``bc_diagonal`` on the Dirichlet rows, as scipy CSR; the control keeps its value."""
        p = self.problem
        with ControlValues(p, {name: np.asarray(values)[None]}) as ctl:
            ctl.set_sample(0)
            with self._assembling():
                matrices.assemble_matrix_into(self._A, p.a_form, p.bcs, diagonal=bc_diagonal)
            self._A_version += 1
            self._A_inputs = None          # A holds these values now: reassemble when next needed
            return petsc_to_scipy(self._A)

    def record_batch(self, direction: str, options: KSPOptions, seconds: float, finite: np.ndarray,
                     engine: str, outcome=None) -> None:
        """Count one solve per sample of a batch solved outside PETSc (``finite`` (B,) bool: the
        sample's iterate is finite; ``outcome``: per-sample iterations and reasons, ``None`` for a
        pure cap, see :func:`~fempdl.solve.stats.record_batch`), then raise or warn per
        ``options`` if any failed, as the first failed sample's PETSc solve would."""
        failure = record_batch(self.stats, direction, options, seconds, finite, engine, outcome)
        if failure is not None:
            stats, finite_iterate, count = failure
            self._solver.report_failure(direction, stats, finite=finite_iterate, samples=count)

    @property
    def matrix_version(self) -> int:
        """Increases whenever the matrix is reassembled."""
        return self._A_version

    # ------------------------------------------------------------ engines
    def _use_batched(self, batch: int, per_sample_matrix: bool) -> bool:
        return self._batched is not None and self._batched.runs(self.options, batch, per_sample_matrix,
                                                                self._comm.size, self._A)

    def _batched_solve(self, R: np.ndarray, direction: str, initial_guess: np.ndarray | None = None) -> np.ndarray:
        """All rows of R at once on the batched engine (from ``initial_guess``'s rows
        if given); stats recorded per sample."""
        opts = self.options if direction == "forward" else self.options.adjoint_options
        X, seconds, outcome = self._batched.solve(self._A, self._A_version, R, opts, transpose=direction == "backward",
                                                  X0=initial_guess)
        self.record_batch(direction, opts, seconds, np.isfinite(X).all(axis=1), "batched", outcome)
        return X

    def destroy(self) -> None:
        """Free the PETSc objects (the system is unusable afterwards); a second call does nothing.
        Without it they are freed when the system itself is garbage collected, not before: a
        system still referenced (``SolveLayer(p).system``) outlives its layer."""
        if getattr(self, "_destroyed", True):
            return
        self._destroyed = True
        self._solver.destroy()
        objs = [self._A, self._b, self._x, self._rhs] + [n for n in (self._nullspace, self._near_nullspace,
                                                                       self._work) if n]
        for obj in objs:
            obj.destroy()
        self._kept_matrices.clear()
        self._forms.destroy()
        self._batched = None

    def __del__(self):
        try:
            self.destroy()
        except Exception:  # interpreter shutdown: PETSc may already be finalised
            pass

    # ------------------------------------------------------- assembly caches
    def _prepare_matrix(self, names: frozenset, per_sample: bool, ctl: ControlValues) -> None:
        """Make A right for a call: the cached constant matrix, one assembly with
        shared controls, or nothing (assembled per sample by the caller)."""
        if not names & self.problem.matrix_controls:
            self._assemble_matrix_if_changed()
            return
        if not per_sample:
            ctl.set_sample(0)
            self._assemble_matrix_if_changed(names)

    def _lag_preconditioner(self, later_sample: bool) -> None:
        """Keep the first sample's preconditioner for the later samples of a call
        (``KSPOptions.lag_preconditioner``)."""
        self._solver.reuse_preconditioner = later_sample and self.options.lag_preconditioner

    def _assembling(self) -> Timer:
        """Counts the enclosed seconds as assembly in the layer's stats."""
        return Timer(self.stats, "assembly_time")

    def _assemble_matrix(self, controls: frozenset = frozenset()) -> None:
        """Assemble A with the controls' current values; refuse a singular or non-finite one
        (:func:`~fempdl.solve.assembly.check_operator`), naming the matrix ``controls`` set for it."""
        self._A_inputs = None
        with self._assembling():
            matrices.assemble_matrix_into(self._A, self.problem.a_form, self.problem.bcs)
            assembly.check_operator(self._A, sorted(frozenset(controls) & self.problem.matrix_controls))
            if self._singular_unchecked:      # once: the null space is the forms' and bcs', not the values'
                assembly.check_not_singular(self._A, constant_modes(self.problem.V))
                self._singular_unchecked = False
            if self._symmetry_unchecked:
                assembly.check_symmetric(self._A)
                self._symmetry_unchecked = False
        self._A_version += 1
        self._A_inputs = assembly.fingerprint(self.problem.matrix_inputs())

    def _matrix_is_current(self) -> bool:
        """Whether A holds the matrix of the coefficients' and constants' current values (on every rank)."""
        return self._A_inputs is not None and assembly.fingerprint_matches(self._A_inputs, self.problem.matrix_inputs(),
                                                                  self._comm)

    def _assemble_matrix_if_changed(self, controls: frozenset = frozenset()) -> None:
        """Assemble A unless it already holds these values. An unchanged A keeps its PETSc state, so its
        factorisation (or preconditioner) is reused: the adjoint of a direct solve transposes the forward's
        factor (MatSolveTranspose) instead of factorising A again."""
        if not self._matrix_is_current():
            self._assemble_matrix(controls)
