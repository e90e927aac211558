"""The capped PETSc solve and its transposed adjoint: :class:`CappedSolver`.

A :class:`CappedSolver` is a KSP on one operator with :meth:`~CappedSolver.solve`
(A x = b) and :meth:`~CappedSolver.solve_transpose` (A^T x = b, by
KSPSolveTranspose or on an explicitly assembled A^T), each returning a
:class:`~fempdl.solve.stats.SolveStats` and counted in its
:class:`~fempdl.solve.stats.CumulativeStats`. It knows PETSc and nothing of
UFL or torch. What a capped solve means (exactly ``max_it`` iterations from a
zero or given initial guess) is stated with :class:`~fempdl.solve.options.KSPOptions`.
The public import path is :mod:`fempdl.ksp_adjoint`.
"""
from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping

from mpi4py import MPI
import numpy as np
from petsc4py import PETSc

from fempdl.core import tuning
from fempdl.solve.options import DEFAULT_CONVERGED_MAX_IT, KSPOptions
from fempdl.solve.petsc import create_ksp, destroy_ksp, set_norm_type, set_up, unique_prefix
from fempdl.solve.scaling import row_exponents, scale_exponent, scale_vec
from fempdl.solve.stats import (
    DIVERGED_MAX_IT,
    REASON_NAMES,
    CumulativeStats,
    SolverWarning,
    SolveStats,
    report_failure,
)

__all__ = ["CappedSolver", "PC_FAILED", "set_interrupt_checks"]

_DIVERGED_BREAKDOWN = PETSc.KSP.ConvergedReason.DIVERGED_BREAKDOWN
#: A preconditioner whose set-up failed: PETSc keeps it failed (:meth:`CappedSolver._renew_failed`).
PC_FAILED = PETSc.KSP.ConvergedReason.DIVERGED_PCSETUP_FAILED
# A breakdown with the residual below this fraction of ||b|| is GMRES's happy
# breakdown under a pure cap (tolerance 0): the Krylov space holds the solution.
_HAPPY_BREAKDOWN = 1e-12


def set_interrupt_checks(ksp: PETSc.KSP, options: KSPOptions) -> None:
    """Give ``ksp`` a monitor that lets a pending KeyboardInterrupt stop a long solve (see
    :data:`fempdl.core.tuning.INTERRUPT_CHECK_MIN_WORK`), or take it away when the cap has moved below that.

    ``ksp`` may be a SNES's inner KSP: the interrupt then ends the SNES solve too."""
    cap = DEFAULT_CONVERGED_MAX_IT if options.max_it is None else options.max_it
    wanted = not options.direct and cap * ksp.getOperators()[0].getSize()[0] >= tuning.INTERRUPT_CHECK_MIN_WORK
    has = ksp.getAttr("fempdl_interruptible") is not None
    if wanted and not has:
        # Calling into Python runs the pending signal handlers: Ctrl-C raises
        # KeyboardInterrupt inside the monitor, and KSPSolve returns with it.
        ksp.setMonitor(_interrupt_point)
        ksp.setAttr("fempdl_interruptible", True)
    elif has and not wanted:
        ksp.cancelMonitor()
        ksp.setAttr("fempdl_interruptible", None)


def _interrupt_point(ksp, iteration, residual_norm) -> None:
    """A KSP monitor that does nothing: being Python, it lets signal handlers run (:func:`set_interrupt_checks`)."""


def _ldexp(value: float, e: int) -> float:
    """value * 2^e, inf where that overflows (a norm of data near float64's largest)."""
    try:
        return math.ldexp(value, e)
    except OverflowError:
        return math.inf


#: A load whose part along the declared null space exceeds this fraction of it is incompatible, not
#: round-off (an enclosed flow's lifted boundary data carry about 1e-16).
INCOMPATIBLE_LOAD = 1e-10


def _warn_incompatible(b: PETSc.Vec, nsp: PETSc.NullSpace) -> None:
    """Say so when projecting the (orthonormal) null space out of the load ``b`` removes more than round-off."""
    norm = b.norm()
    if not norm or not math.isfinite(norm):
        return
    part = math.sqrt(sum(b.dot(v) ** 2 for v in nsp.getVecs())) / norm
    if part > INCOMPATIBLE_LOAD:
        warnings.warn(f"the load has a part along the operator's declared null space ({part:.2g} of its norm; e.g. "
                      "a net source or flux in a pure-Neumann problem): the solve projects it out and returns the "
                      "solution of the compatible rest, orthogonal to the null space", SolverWarning, stacklevel=3)


class CappedSolver:
    """A PETSc KSP on one operator, with a forward and a transposed solve.

    Follows the init / compute / transpose split: build once for an operator,
    call :meth:`solve` and :meth:`solve_transpose` many times. When the operator's
    entries are reassembled in place, PETSc notices and rebuilds the
    preconditioner on the next solve.

    Args:
        A: the assembled operator (square PETSc Mat).
        options: the solver options.
        prefix: options prefix; ``options.options_prefix`` when set, else a
            unique private one.
        preconditioner_matrix: the matrix the preconditioner is set up on, when not
            ``A`` (a lagged factorisation: the Newton system refreshes it).

    Attributes:
        stats: :class:`CumulativeStats` of every solve (``solve`` counts as
            forward, ``solve_transpose`` as backward), failed ones included.

    The KSP objects are destroyed by :meth:`destroy` (or on leaving a ``with``
    block); PETSc objects are not left to the garbage collector.
    """

    def __init__(self, A: PETSc.Mat, options: KSPOptions, *, prefix: str | None = None,
                 fields: Mapping[str, np.ndarray] | None = None, preconditioner_matrix: PETSc.Mat | None = None):
        if not isinstance(options, KSPOptions):
            raise TypeError(f"options must be KSPOptions, got {type(options).__name__}")
        self._options = options
        self._A, self._P = A, preconditioner_matrix
        self._fields = fields
        self._prefix = prefix or options.options_prefix or unique_prefix("ksp")
        self._ksp = self._forward_ksp()
        # The adjoint has its own KSP when its options differ, or when it runs on
        # an assembled A^T (created at the first transposed solve: A must be assembled).
        self._ksp_adjoint = None
        self._At = None
        self._At_state = None
        if options.adjoint is not None and not options.assembled_adjoint:
            self._ksp_adjoint = create_ksp(A, options.adjoint, self._prefix + "adj_", fields)
        self.stats = CumulativeStats()
        self.reuse_preconditioner = False
        self._failed: set[str] = set()      # "forward" / "adjoint": KSPs to renew at the next solve

    @property
    def reuse_preconditioner(self) -> bool:
        """While True, solves keep the preconditioners set up for earlier matrices
        (``KSPOptions.lag_preconditioner``: the system sets it between samples)."""
        return self._reuse

    @reuse_preconditioner.setter
    def reuse_preconditioner(self, value: bool) -> None:
        self._reuse = bool(value)

    @property
    def options(self) -> KSPOptions:
        return self._options

    @property
    def max_it(self) -> int | None:
        return self._options.max_it

    @max_it.setter
    def max_it(self, value: int | None) -> None:
        """Move the cap of the forward solve (and of a coupled adjoint)."""
        new = self._options.with_max_it(value)  # validates
        # A coupled adjoint on its own KSP (the one on an assembled A^T) moves with the forward cap.
        coupled = [self._ksp] + ([self._ksp_adjoint] if new.adjoint is None and self._ksp_adjoint else [])
        for ksp in coupled:
            if new.skips_residual_norm() != self._options.skips_residual_norm():
                set_norm_type(ksp, new)
            ksp.setTolerances(**new.petsc_tolerances())
        self._options = new

    @property
    def ksp(self) -> PETSc.KSP:
        """The forward KSP (for inspection; do not change its tolerances)."""
        return self._ksp

    def solve(self, b: PETSc.Vec, x: PETSc.Vec, *, warm: bool = False) -> SolveStats:
        """Solve A x = b; ``x`` is overwritten.

        The iteration starts from zero, or from the values ``x`` holds when
        ``warm`` is True (a warm start: the K iterations then correct that
        guess; direct solves ignore it).

        Raises:
            SolverFailedError: on divergence, breakdown or NaN/inf (unless the
                options say ``on_failure="warn"``). The solve is counted in
                :attr:`stats` either way.
        """
        self._renew_failed()
        warm = warm and not self._options.direct   # PCLU under preonly refuses a nonzero guess
        if warm:
            self._ksp.setInitialGuessNonzero(True)
        try:
            return self._run(self._ksp, self._options, b, x, direction="forward")
        finally:
            if warm:
                self._ksp.setInitialGuessNonzero(False)

    def can_solve_many_transpose(self, symmetric: bool) -> bool:
        """Whether :meth:`solve_many` can solve A^T X = R: the adjoint solves with the forward's factors
        (its own direct KSP, no assembled A^T) and A = A^T (``symmetric``) or PETSc has KSPMatSolveTranspose."""
        return (self._ksp_adjoint is None and not self._options.assembled_adjoint and self._options.direct
                and (symmetric or hasattr(self._ksp, "matSolveTranspose")))

    def solve_many(self, R: np.ndarray, *, transpose: bool = False, symmetric: bool = False) -> np.ndarray:
        """A X = R for the rows of R (B, n) with one factorisation and one MatMatSolve
        (a direct solve on one process: ``options.direct``); returns X (B, n). With ``transpose``
        A^T X = R by the same factors (:meth:`can_solve_many_transpose`): one MatMatSolve where A is
        ``symmetric``, else one KSPMatSolveTranspose.

        Each sample is counted as one solve of one iteration, with its share of the time.
        """
        if not self._options.direct or self._A.getComm().getSize() > 1:
            raise ValueError("solve_many needs a direct solve (ksp_type='preonly' with a factorising pc_type) "
                             "on one process")
        direction = "backward" if transpose else "forward"
        self._renew_failed()
        batch, n = R.shape
        e = row_exponents(R)[:, None]          # rows far from 1 solved scaled (fempdl.solve.scaling)
        R = np.ldexp(R, -e)
        t0 = time.perf_counter()
        set_up(self._ksp, self._reuse)
        t1 = time.perf_counter()
        # A dense PETSc matrix is column-major: the rows of R are its columns.
        rhs = PETSc.Mat().createDense((n, batch), array=np.asfortranarray(R.T, dtype=PETSc.ScalarType),
                                      comm=PETSc.COMM_SELF)
        sol = PETSc.Mat().createDense((n, batch), comm=PETSc.COMM_SELF)
        sol.setUp()
        try:
            if transpose and not symmetric:
                self._ksp.matSolveTranspose(rhs, sol)
            else:
                self._ksp.getPC().getFactorMatrix().matSolve(rhs, sol)
            X = np.ldexp(sol.getDenseArray().T, e)
        except PETSc.Error:
            self._failed.add(direction)
            raise
        finally:
            rhs.destroy()
            sol.destroy()
        if not np.isfinite(X).all():          # petsc4py 3.18 cannot ask the PC whether its set-up failed
            self._failed.add(direction)
        elapsed = time.perf_counter() - t1
        reason = PETSc.KSP.ConvergedReason.CONVERGED_ITS
        for ok in np.isfinite(X).all(axis=1):
            self.record(direction, SolveStats(iterations=1, reason=reason, reason_name=REASON_NAMES[reason],
                                              residual_norm=None, time=elapsed / batch, capped=False,
                                              ok=bool(ok), setup_time=(t1 - t0) / batch),
                        finite=bool(ok))
        return X

    def solve_transpose(self, b: PETSc.Vec, x: PETSc.Vec) -> SolveStats:
        """Solve A^T x = b with the adjoint options (the forward ones by default),
        by KSPSolveTranspose or on an assembled A^T (``options.assembled_adjoint``)."""
        self._renew_failed()
        if self._options.assembled_adjoint:
            return self._run(self._assembled_adjoint_ksp(), self._options.adjoint_options, b, x,
                             direction="backward", transpose=False)
        if self._ksp_adjoint is None:
            return self._run(self._ksp, self._options, b, x, direction="backward")
        return self._run(self._ksp_adjoint, self._options.adjoint, b, x, direction="backward")

    def _assembled_adjoint_ksp(self) -> PETSc.KSP:
        """The KSP on A^T, with A^T refreshed if A changed since it was built."""
        state = self._A.stateGet()
        t0 = time.perf_counter()
        if self._At is None:
            # petsc4py's A.transpose() without an argument transposes A in place;
            # an empty Mat as the target asks for a new matrix.
            self._At = PETSc.Mat()
            self._A.transpose(self._At)
            self._ksp_adjoint = create_ksp(self._At, self._options.adjoint_options, self._prefix + "adj_",
                                            self._fields)
        elif state != self._At_state:
            self._A.transpose(self._At)           # same pattern: reuses A^T's storage
        if state != self._At_state:
            nsp = self._A.getTransposeNullSpace() or self._A.getNullSpace()
            if nsp is not None:
                self._At.setNullSpace(nsp)
            near = self._A.getNearNullSpace()
            if near is not None:             # elasticity's rigid-body modes: A^T = A there
                self._At.setNearNullSpace(near)
            self._At_state = state
        self.stats.adjoint_operator_time += time.perf_counter() - t0
        return self._ksp_adjoint

    def _renew_failed(self) -> None:
        """Fresh KSPs, same operator and options, for those whose preconditioner set-up failed or whose
        solve raised: PETSc keeps a failed set-up (MUMPS on a matrix with NaN entries) failed, and every
        later solve on that KSP fails or stops with PETSc error 76, however sane the matrix has become.
        Done at the next solve, which every rank calls (an exception may have been one rank's)."""
        if not self._failed:
            return
        failed, self._failed = self._failed, set()
        if "forward" in failed:
            destroy_ksp(self._ksp)
            self._ksp = self._forward_ksp()
        if "adjoint" in failed and self._ksp_adjoint is not None:
            assembled = self._options.assembled_adjoint
            operator = self._At if assembled else self._A
            options = self._options.adjoint_options if assembled else self._options.adjoint
            destroy_ksp(self._ksp_adjoint)
            self._ksp_adjoint = create_ksp(operator, options, self._prefix + "adj_", self._fields)

    def _forward_ksp(self) -> PETSc.KSP:
        ksp = create_ksp(self._A, self._options, self._prefix, self._fields)
        if self._P is not None:
            ksp.setOperators(self._A, self._P)
        return ksp

    def destroy(self) -> None:
        for ksp in (self._ksp, self._ksp_adjoint):
            if ksp is not None:
                destroy_ksp(ksp)
        if self._At is not None:
            self._At.destroy()
        self._ksp = self._ksp_adjoint = self._At = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.destroy()

    def _run(self, ksp, options: KSPOptions, b, x, *, direction: str, transpose: bool | None = None) -> SolveStats:
        transpose = direction == "backward" if transpose is None else transpose
        operator = ksp.getOperators()[0]
        # A singular operator with an attached null space (e.g. the pressure
        # constant of an enclosed flow): solve for the part of b in the range
        # and return the solution orthogonal to the null space, so the map
        # b -> x is well defined (and its transpose is the adjoint's map).
        nsp = (operator.getTransposeNullSpace() if transpose else None) or operator.getNullSpace()
        if nsp is not None:
            if nsp and direction == "forward":     # (petsc4py: a Mat without one hands out an empty handle)
                _warn_incompatible(b, nsp)
            nsp.remove(b)
        # Data far from 1 are solved scaled by a power of two (exact; fempdl.solve.scaling).
        warm = bool(ksp.getInitialGuessNonzero())
        b_max = b.norm(PETSc.NormType.NORM_INFINITY)
        e = scale_exponent(b_max, x.norm(PETSc.NormType.NORM_INFINITY) if warm else 0.0)
        self._set_interrupt_checks(ksp, options)
        t0 = time.perf_counter()
        set_up(ksp, self._reuse)      # the preconditioner's set-up, timed apart from the iterations
        t1 = time.perf_counter()
        failed_kind = "forward" if ksp is self._ksp else "adjoint"
        try:
            self._scale_data(ksp, options, b, x if warm else None, -e)
            b_norm = b.norm()
            (ksp.solveTranspose if transpose else ksp.solve)(b, x)
            overflows = bool(e) and math.isfinite(x.norm(PETSc.NormType.NORM_INFINITY))  # unless scaled back
        except PETSc.Error as err:
            self._failed.add(failed_kind)
            # petsc4py >= 3.19 wraps an exception raised in a Python monitor
            # (Ctrl-C's KeyboardInterrupt) in a PETSc.Error; 3.18 lets it through.
            if isinstance(err.__cause__, KeyboardInterrupt):
                raise err.__cause__ from None
            raise
        finally:
            self._scale_data(ksp, options, b, x, e, restore=True)
        elapsed = time.perf_counter() - t1
        if nsp is not None:
            nsp.remove(x)
        reason = int(ksp.getConvergedReason())
        iterations = int(ksp.getIterationNumber())
        norm_computed = ksp.getNormType() != PETSc.KSP.NormType.NONE
        rnorm = float(ksp.getResidualNorm()) if norm_computed else None     # of the scaled data, as b_norm
        finite = math.isfinite(x.norm(PETSc.NormType.NORM_INFINITY))
        capped = options.capped and (reason == DIVERGED_MAX_IT
                                     or (reason == PETSc.KSP.ConvergedReason.CONVERGED_ITS
                                         and iterations >= options.max_it))
        exact = (reason == _DIVERGED_BREAKDOWN and rnorm is not None and rnorm <= _HAPPY_BREAKDOWN * b_norm)
        ok = finite and (reason > 0 or capped or exact)
        rnorm = None if rnorm is None else _ldexp(rnorm, e)
        if reason == PC_FAILED:
            self._failed.add(failed_kind)
        stats = SolveStats(iterations=iterations, reason=reason,
                           reason_name=REASON_NAMES.get(reason, str(reason)),
                           residual_norm=rnorm, time=elapsed, capped=capped, ok=ok, setup_time=t1 - t0)
        upstream = ("was handed a right-hand side holding NaN or inf" if not math.isfinite(b_max) else
                    f"overflows float64 (its right-hand side reaches {b_max:.3g})" if overflows and not finite else
                    None)
        return self.record(direction, stats, finite=finite, upstream=upstream)

    @staticmethod
    def _scale_data(ksp, options: KSPOptions, b, x, e: int, *, restore: bool = False) -> None:
        """b *= 2^e and x *= 2^e (x None: b only); the user's absolute tolerance scaled alike, or put
        back when ``restore``."""
        if not e:
            return
        scale_vec(b, e)
        if x is not None:
            scale_vec(x, e)
        if options.atol:
            ksp.setTolerances(atol=options.atol if restore else math.ldexp(options.atol, e))

    # The rule NonlinearSystem applies to its inner KSP too.
    _set_interrupt_checks = staticmethod(set_interrupt_checks)

    def record(self, direction: str, stats: SolveStats, *, finite: bool = True,
               upstream: str | None = None) -> SolveStats:
        """Count a solve (also one run outside this KSP, e.g. by the batched engine) and raise or warn per
        the options if it failed; ``upstream``: a cause in the data (:func:`~fempdl.solve.stats.report_failure`)."""
        self.stats.record(direction, stats)
        if not stats.ok:
            self.report_failure(direction, stats, finite=finite, upstream=upstream)
        return stats

    def report_failure(self, direction: str, stats: SolveStats, *, finite: bool, samples: int = 1,
                       upstream: str | None = None) -> None:
        """Raise :class:`SolverFailedError` or warn (per ``on_failure``) for a failed solve."""
        options = self._options if direction == "forward" else self._options.adjoint_options
        span = None if finite or upstream or not options.direct else self._diagonal_span()
        report_failure(options, stats, finite, direction == "backward", samples, diagonal_span=span,
                       upstream=upstream)

    def _diagonal_span(self) -> tuple[float, float]:
        """The smallest and largest nonzero |a_ii| of the operator over every rank (names a badly scaled one)."""
        diagonal = self._A.getDiagonal()
        values = np.abs(diagonal.getArray(readonly=True))
        diagonal.destroy()
        values = values[values > 0]
        comm = self._A.getComm().tompi4py()
        low = comm.allreduce(float(values.min()) if len(values) else math.inf, op=MPI.MIN)
        high = comm.allreduce(float(values.max()) if len(values) else 0.0, op=MPI.MAX)
        return (low, high) if high > 0 else (1.0, 1.0)
