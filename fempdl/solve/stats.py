"""What solves did and how they failed: per-solve :class:`SolveStats`, a layer's :class:`CumulativeStats`
(the iteration counts PRDP savings are quoted in), and :class:`SolverFailedError` with a message that names the fix."""
from __future__ import annotations

import dataclasses
import sys
import warnings
from dataclasses import dataclass, field

import numpy as np
from petsc4py import PETSc

from fempdl.solve.options import KSPOptions

__all__ = ["SolveStats", "CumulativeStats", "SolverFailedError", "SolverWarning", "REASON_NAMES", "DIVERGED_MAX_IT",
           "report_failure", "warn_at_caller", "capped_solve_stats", "record_batch"]

REASON_NAMES = {
    getattr(PETSc.KSP.ConvergedReason, n): n
    for n in dir(PETSc.KSP.ConvergedReason)
    if n.isupper() and not n.startswith("CONVERGED_ITERATING")
}
DIVERGED_MAX_IT = PETSc.KSP.ConvergedReason.DIVERGED_MAX_IT


class SolverFailedError(RuntimeError):
    """A solve ended in anything other than convergence or reaching its cap.

    Attributes:
        stats: the :class:`SolveStats` of the failed solve.
    """

    def __init__(self, message: str, stats: SolveStats):
        super().__init__(message)
        self.stats = stats


@dataclass(frozen=True)
class SolveStats:
    """What one linear solve did.

    Attributes:
        iterations: Krylov iterations run (1 for a direct solve).
        reason: PETSc's converged reason (> 0 converged, < 0 diverged/stopped).
        reason_name: its name, e.g. ``"DIVERGED_MAX_IT"`` (= the cap was reached).
        residual_norm: final residual norm, or ``None`` when not computed (NORM_NONE).
        time: wall time of the iterations in seconds (the KSP solve after its set-up).
        capped: True when the solve stopped because it reached ``max_it``.
        ok: False when the solve diverged, broke down or produced NaN/inf.
        engine: ``"petsc"`` (a KSP solve) or ``"batched"`` (one column of a
            batched iteration; ``time`` is its share of the batch).
        setup_time: seconds in KSPSetUp before the iterations (the
            preconditioner's set-up or factorisation; about 0 while A is unchanged).
    """

    iterations: int
    reason: int
    reason_name: str
    residual_norm: float | None
    time: float
    capped: bool
    ok: bool
    engine: str = "petsc"
    setup_time: float = 0.0


@dataclass
class CumulativeStats:
    """Cumulative iteration and time counters of a layer (summed over samples).

    ``forward_iterations + backward_iterations`` is the cost metric PRDP savings
    are quoted in. Seconds, split by what they bought: ``solve_time`` the
    iterations (forward + backward), ``setup_time`` preconditioner set-up and
    factorisations, ``assembly_time`` matrices, right-hand sides and gradient
    forms, ``adjoint_operator_time`` forming an explicit A^T; ``layer_time`` is
    the whole forward and backward of the layer (those and the conversions).
    """

    forward_iterations: int = 0
    backward_iterations: int = 0
    forward_solves: int = 0
    backward_solves: int = 0
    forward_time: float = 0.0
    backward_time: float = 0.0
    layer_time: float = 0.0
    setup_time: float = 0.0
    assembly_time: float = 0.0
    adjoint_operator_time: float = 0.0
    max_forward_iterations: int = 0
    failures: int = 0
    solves_by_engine: dict = field(default_factory=dict)
    last: SolveStats | None = None

    def record(self, direction: str, stats: SolveStats, solves: int = 1) -> None:
        """Add ``solves`` solves, each with ``stats``; ``direction`` is ``"forward"`` or ``"backward"``."""
        if direction == "forward":
            self.max_forward_iterations = max(self.max_forward_iterations, stats.iterations)
            self.forward_iterations += solves * stats.iterations
            self.forward_solves += solves
            self.forward_time += solves * stats.time
        elif direction == "backward":
            self.backward_iterations += solves * stats.iterations
            self.backward_solves += solves
            self.backward_time += solves * stats.time
        else:
            raise ValueError(f"direction must be 'forward' or 'backward', got {direction!r}")
        self.setup_time += solves * stats.setup_time
        self.failures += solves * (not stats.ok)
        self.solves_by_engine[stats.engine] = self.solves_by_engine.get(stats.engine, 0) + solves
        self.last = stats

    @property
    def total_iterations(self) -> int:
        return self.forward_iterations + self.backward_iterations

    @property
    def solve_time(self) -> float:
        return self.forward_time + self.backward_time

    def reset(self) -> None:
        fresh = type(self)()
        for f in dataclasses.fields(self):
            setattr(self, f.name, getattr(fresh, f.name))


def capped_solve_stats(options: KSPOptions, seconds: float, finite: bool, engine: str) -> SolveStats:
    """Stats of a pure-cap solve that ran ``options.max_it`` iterations outside PETSc."""
    reason = PETSc.KSP.ConvergedReason.CONVERGED_ITS
    return SolveStats(iterations=options.max_it, reason=reason, reason_name=REASON_NAMES[reason],
                      residual_norm=None, time=seconds, capped=True, ok=finite, engine=engine)


def record_batch(cumulative, direction: str, options: KSPOptions, seconds: float, finite, engine: str,
                 outcome=None):
    """Record a batch solved outside PETSc in ``cumulative`` (:class:`CumulativeStats`), one solve per
    sample, each with its share of ``seconds``; ``finite`` (B,) bool. ``outcome`` is ``None`` for a
    pure cap (``options.max_it`` iterations each: two kinds of record, finite or not, each recorded
    once with its count, the last sample's kind last), else (iterations (B,), reason names (B,),
    final residual norms (B,)) per sample; a sample is ok as a PETSc solve would be: finite, and
    converged or stopped by the cap. Returns (the first failed sample's stats, whether its iterate
    is finite, how many failed), or ``None`` when none did."""
    share = seconds / len(finite)
    if outcome is None:
        bad = int(np.count_nonzero(~finite))
        kinds = {ok: capped_solve_stats(options, share, ok, engine) for ok in (False, True)}
        for ok, count in sorted({False: bad, True: len(finite) - bad}.items(), key=lambda kv: kv[0] == finite[-1]):
            if count:
                cumulative.record(direction, kinds[ok], solves=count)
        return (kinds[False], False, bad) if bad else None
    failed = []
    for ok, its, name, norm in zip(finite, *outcome):
        reason = int(getattr(PETSc.KSP.ConvergedReason, name))
        capped = options.capped and reason == DIVERGED_MAX_IT
        stats = SolveStats(iterations=int(its), reason=reason, reason_name=REASON_NAMES.get(reason, name),
                           residual_norm=float(norm), time=share, capped=capped,
                           ok=bool(ok) and (reason > 0 or capped), engine=engine)
        cumulative.record(direction, stats)
        if not stats.ok:
            failed.append((stats, bool(ok)))
    return (failed[0][0], failed[0][1], len(failed)) if failed else None


class SolverWarning(RuntimeWarning):
    """A solve failed and ``on_failure="warn"`` asked for the iterate anyway."""


#: A matrix whose nonzero diagonal entries span more than this factor is named as badly scaled where its
#: factorisation fails (a viscosity of 1e-6 beside a saddle point's O(1) coupling spans 1e6).
BADLY_SCALED_SPAN = 1e4


def report_failure(options: KSPOptions, stats: SolveStats, finite: bool, transpose: bool,
                    samples: int = 1, diagonal_span: tuple[float, float] | None = None,
                    upstream: str | None = None) -> None:
    """Raise :class:`SolverFailedError` or warn (per ``options.on_failure``) with the cause and the fix;
    ``diagonal_span``: the smallest and largest nonzero |a_ii| of the operator, for a factorisation's failure;
    ``upstream``: a cause in the data rather than the solver (a right-hand side holding NaN or inf, a
    solution beyond float64's range), which then leads the message."""
    what = "transposed solve" if transpose else "solve"
    if samples > 1:
        what += f" of {samples} samples"
    if upstream:
        cause = upstream
        fix = ("what it was assembled from overflowed or was not finite: a state grown without bound over a time "
               "loop (an unstable step for this dt, e.g. explicit Euler beyond its stability limit), or a control "
               "or gradient holding NaN or inf")
    elif not finite:
        cause = "produced NaN or inf"
        if options.direct:
            low, high = diagonal_span or (1.0, 1.0)
            fix = ("the factorisation met a zero pivot: the matrix is singular (a zero coefficient, e.g. kappa = 0, "
                   "or a missing Dirichlet condition) or badly scaled")
            if low > 0 and high / low > BADLY_SCALED_SPAN:
                fix += (f"; its diagonal spans {high / low:.1e} (|a_ii| from {low:.2e} to {high:.2e}), e.g. a "
                        "viscosity of 1e-6 beside a saddle point's O(1) coupling: nondimensionalise the "
                        "equations, or use an iterative preset ('schur' for a (u, p) flow, 'amg' or 'gmres' "
                        "otherwise)")
        else:
            fix = ("check the inputs and the operator (e.g. a zero or negative coefficient, or an "
                   "unstable damping), or use a more robust solver such as KSPOptions.preset('lu')")
    elif stats.reason == DIVERGED_MAX_IT:
        cause = f"did not reach rtol={options.petsc_tolerances()['rtol']:g} in {stats.iterations} iterations"
        fix = "try a stronger pc_type or ksp_type, a larger rtol, or cap the solve on purpose with max_it=K"
    else:
        cause = f"stopped with {stats.reason_name} after {stats.iterations} iterations"
        fix = ("the operator may be singular or indefinite for this method; try ksp_type='gmres', "
               "KSPOptions.preset('lu'), or a larger divtol")
    message = (f"{options.ksp_type}+{options.pc_type} {what} {cause}"
               + (f" (residual norm {stats.residual_norm:.3e})" if stats.residual_norm is not None else "")
               + f"; {fix}. Pass on_failure='warn' to get the iterate with a warning instead.")
    if options.on_failure == "warn":
        warn_at_caller(message, SolverWarning)
    else:
        raise SolverFailedError(message, stats)


def warn_at_caller(message: str, category: type[Warning]) -> None:
    """Warn with the location of the first frame outside fempdl and torch, so the
    warning points at the user's line (the call stack runs through autograd)."""
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_globals.get("__name__", "").split(".")[0] in ("fempdl", "torch"):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level + 1)

