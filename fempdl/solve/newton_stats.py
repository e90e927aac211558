"""What Newton solves did: per-solve :class:`NewtonSolveStats`, a nonlinear layer's
:class:`NewtonCumulativeStats` (Newton steps and inner Krylov iterations counted apart), and the
failure message that names SNES's reason."""
from __future__ import annotations

import math
from dataclasses import dataclass

from petsc4py import PETSc

from fempdl.solve.stats import CumulativeStats, SolverFailedError, SolverWarning, warn_at_caller

__all__ = ["NewtonSolveStats", "NewtonCumulativeStats", "SNES_REASON_NAMES", "NONFINITE_REASONS", "report_newton_failure"]

SNES_REASON_NAMES = {
    getattr(PETSc.SNES.ConvergedReason, n): n
    for n in dir(PETSc.SNES.ConvergedReason)
    if n.isupper() and n not in ("ITERATING", "CONVERGED_ITERATING")
}


# A residual with NaN or inf entries: DIVERGED_FNORM_NAN in PETSc 3.18, DIVERGED_FUNCTION_NANORINF from 3.2x
# (the same code), and an assembly outside the function's domain.
NONFINITE_REASONS = frozenset(getattr(PETSc.SNES.ConvergedReason, name) for name in
                              ("DIVERGED_FNORM_NAN", "DIVERGED_FUNCTION_NANORINF", "DIVERGED_FUNCTION_DOMAIN")
                              if hasattr(PETSc.SNES.ConvergedReason, name))


@dataclass(frozen=True)
class NewtonSolveStats:
    """What one Newton solve (one sample) did.

    Attributes:
        steps: Newton steps taken.
        reason, reason_name: SNES's converged reason (> 0 converged, < 0 stopped), e.g.
            ``"DIVERGED_MAX_IT"`` (= the Newton cap was reached).
        residual_norms: ||F(u_k)|| for k = 0 ... steps.
        inner_iterations: Krylov iterations over all steps (1 per step for a direct solve).
        capped: True when the solve stopped because it reached ``max_it``.
        ok: False when it failed (not converged uncapped, a failed line search, NaN/inf).
        time: wall time of the solve (assembly included).
        nonfinite_residual: a residual with NaN or inf entries was assembled during the solve (a line
            search may have stepped back from it).
    """

    steps: int
    reason: int
    reason_name: str
    residual_norms: tuple
    inner_iterations: int
    capped: bool
    ok: bool
    time: float
    nonfinite_residual: bool = False


@dataclass
class NewtonCumulativeStats(CumulativeStats):
    """A nonlinear layer's counters: the inner linear solves as in :class:`CumulativeStats` (every
    Newton step's Krylov solve is one forward solve; adjoint and unrolled-step transposed solves are
    backward solves), plus Newton steps: ``newton_steps`` forward, ``backward_newton_steps`` run
    backwards by the unrolled derivative, ``newton_solves`` samples solved."""

    newton_steps: int = 0
    newton_solves: int = 0
    max_newton_steps: int = 0
    backward_newton_steps: int = 0
    newton_failures: int = 0
    last_newton: NewtonSolveStats | None = None

    def record_newton(self, stats: NewtonSolveStats) -> None:
        self.newton_steps += stats.steps
        self.newton_solves += 1
        self.max_newton_steps = max(self.max_newton_steps, stats.steps)
        self.newton_failures += not stats.ok
        self.last_newton = stats


def report_newton_failure(options, stats: NewtonSolveStats, inner_reason: str | None) -> None:
    """Raise :class:`SolverFailedError` (or warn, per ``options.on_failure``) for a failed Newton solve."""
    norms = stats.residual_norms
    history = f"residual norm {norms[-1]:.3e} from {norms[0]:.3e}" if norms else "no residual evaluated"
    if stats.reason_name == "DIVERGED_LINEAR_SOLVE":
        cause = f"its linear solve failed ({inner_reason or 'see the KSP options'})"
        fix = "use a stronger inner solve (ksp='lu'), or cap the inner solve on purpose with KSPOptions(max_it=K)"
    elif stats.reason in NONFINITE_REASONS or stats.nonfinite_residual or not math.isfinite(
            norms[-1] if norms else 0.0):
        cause = "the residual became NaN or inf"
        fix = ("the load or the controls may be beyond what the material model allows (e.g. an inverted element); "
               "reduce the load, start from a better initial_guess, or use snes_type='newtonls' with a line search")
    elif stats.reason_name == "DIVERGED_JACOBIAN_DOMAIN":
        cause = f"met a Jacobian it cannot solve with ({inner_reason})"
        fix = ("J(u) at that iterate is singular: a zero coefficient (e.g. kappa = 0 on a node's support) or a "
               "degenerate state (a conductivity q(u) that vanishes at the initial guess, such as q = u^2 from "
               "zero); check the coefficients, or start from another initial_guess")
    elif stats.reason_name == "DIVERGED_MAX_IT":
        cause = "did not reach its tolerance"
        fix = "raise converged_max_it, loosen rtol/atol, start from a better initial_guess, or load in increments"
    else:
        cause = "stopped"
        fix = ("Newton diverged: reduce the load, start from a better initial_guess, or try another snes_type "
               "('newtonls' with linesearch='bt', or 'newtontr')")
    message = (f"Newton ({options.snes_type}) {cause}: SNES reason {stats.reason_name} after {stats.steps} "
               f"step(s), {history}; {fix}. Pass NewtonOptions(on_failure='warn') to get the iterate with a "
               "warning instead.")
    if options.on_failure == "warn":
        warn_at_caller(message, SolverWarning)
    else:
        raise SolverFailedError(message, stats)
