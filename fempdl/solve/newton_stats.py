"""What Newton solves did: per-solve :class:`NewtonSolveStats`, a nonlinear layer's
:class:`NewtonCumulativeStats` (Newton steps and inner Krylov iterations counted apart), and the
failure message that names SNES's reason, the cause it points to and the fixes that apply to the options
in use (:class:`NewtonFailure` holds what the message needs besides the stats)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from petsc4py import PETSc

from fempdl.solve.stats import CumulativeStats, SolverFailedError, SolverWarning, warn_at_caller

__all__ = ["NewtonSolveStats", "NewtonCumulativeStats", "NewtonFailure", "SNES_REASON_NAMES", "NONFINITE_REASONS",
           "report_newton_failure", "explain", "ended_nonfinite", "DIVERGED_GROWTH"]

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
        reference_norm: ||F(u_ref)||, the residual at the zero state with the boundary values, measured
            for a solve from an initial guess that stops at its tolerances (``rtol`` is relative to
            min(||F(u_0)||, ||F(u_ref)||): :func:`~fempdl.solve.newton_options.rtol_scale`); ``None``
            when not measured (a start from zero is u_ref).
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
    reference_norm: float | None = None


@dataclass
class NewtonCumulativeStats(CumulativeStats):
    """A nonlinear layer's counters: the inner linear solves as in :class:`CumulativeStats` (every
    Newton step's Krylov solve is one forward solve; adjoint and unrolled-step transposed solves are
    backward solves), plus Newton steps: ``newton_steps`` forward, ``backward_newton_steps`` run
    backwards by the unrolled derivative, ``newton_solves`` samples solved, and
    ``preconditioner_refreshes``: set-ups of a lagged inner preconditioner on a new Jacobian."""

    newton_steps: int = 0
    newton_solves: int = 0
    max_newton_steps: int = 0
    backward_newton_steps: int = 0
    preconditioner_refreshes: int = 0
    newton_failures: int = 0
    last_newton: NewtonSolveStats | None = None

    def record_newton(self, stats: NewtonSolveStats) -> None:
        self.newton_steps += stats.steps
        self.newton_solves += 1
        self.max_newton_steps = max(self.max_newton_steps, stats.steps)
        self.newton_failures += not stats.ok
        self.last_newton = stats


@dataclass(frozen=True)
class NewtonFailure:
    """What a failed Newton solve's message names besides its stats: values at hand when it stopped and,
    after a NaN or inf residual, J and F assembled once more at the state that gave it (the failure path
    only: a solve that succeeds pays nothing for this).

    Attributes:
        inner_reason, inner_iterations: the last inner KSP's reason name and iterations.
        jacobian_defect: what is wrong with J(u) where Newton stopped (``"NaN or inf entries"``,
            ``"N empty rows (it is singular)"``), or None.
        jacobian_controls: the controls passed to this solve that J depends on.
        residual_alone_finite: after a NaN or inf residual, whether F(u) without the lifting of the
            Dirichlet values (which goes through J) is finite at that state; None when not looked at.
        dirichlet, nullspace: the problem has Dirichlet conditions / declares a null space.
        given_jacobian: the problem's J is not dF/du (``NonlinearProblem(..., J=...)``).
    """

    inner_reason: str = ""
    inner_iterations: int = 0
    jacobian_defect: str | None = None
    jacobian_controls: tuple = ()
    residual_alone_finite: bool | None = None
    dirichlet: bool = True
    nullspace: bool = False
    given_jacobian: bool = False


def report_newton_failure(options, stats: NewtonSolveStats, failure: NewtonFailure) -> None:
    """Raise :class:`SolverFailedError` (or warn, per ``options.on_failure``) for a failed Newton solve,
    naming its cause and the fixes that apply (:func:`explain`)."""
    cause, fix = explain(options, stats, failure)
    norms = stats.residual_norms
    history = f"residual norm {norms[-1]:.3e} from {norms[0]:.3e}" if norms else "no residual evaluated"
    message = (f"Newton ({options.snes_type}) {cause}: SNES reason {stats.reason_name} after {stats.steps} "
               f"step(s), {history}; {fix}. Pass NewtonOptions(on_failure='warn') to get the iterate with a "
               "warning instead.")
    if options.on_failure == "warn":
        warn_at_caller(message, SolverWarning)
    else:
        raise SolverFailedError(message, stats)


# ---------------------------------------------------------------- why it failed, and what to do
def explain(options, stats: NewtonSolveStats, failure: NewtonFailure) -> tuple[str, str]:
    """(cause, fix) of a failed Newton solve: the first of :data:`_EXPLANATIONS` that recognises it."""
    for explanation in _EXPLANATIONS:
        found = explanation(options, stats, failure)
        if found is not None:
            return found
    return "stopped", ("Newton diverged: reduce the load, start from a better initial_guess, or "
                       f"{_other_methods(options)}")


def ended_nonfinite(stats: NewtonSolveStats) -> bool:
    """The solve ended on a NaN or inf residual (not one a line search stepped back from)."""
    norms = stats.residual_norms
    return stats.reason in NONFINITE_REASONS or not norms or not math.isfinite(norms[-1])


def _jacobian(options, stats, failure):
    """J(u) is singular or not finite where Newton stopped: at an iterate (from the Jacobian's assembly), or at
    the state whose residual was NaN when F alone is finite there (the NaN came in through J's lifting
    of the Dirichlet values) or that state is the initial guess."""
    defect = failure.jacobian_defect
    if defect is None:
        return None
    named = list(failure.jacobian_controls)
    if stats.reason_name == "DIVERGED_JACOBIAN_DOMAIN":
        where = "at the initial guess" if stats.steps == 0 else f"at the iterate after {stats.steps} step(s)"
        if "empty row" in defect:
            return (f"met a Jacobian it cannot solve with ({defect}, controls {named})",
                    "J(u) at that iterate is singular: a zero coefficient (e.g. kappa = 0 on a node's support) or a "
                    "degenerate state (a conductivity q(u) that vanishes at the initial guess, such as q = u^2 from "
                    "zero); check the coefficients, or start from another initial_guess")
        return f"its Jacobian J(u) became NaN or inf {where} ({_depends(named)})", _singular_coefficient_fix(named)
    at_start = not stats.residual_norms
    if not ended_nonfinite(stats) or "NaN" not in defect or not (failure.residual_alone_finite or at_start):
        return None
    where = "at the initial guess" if at_start else f"in Newton step {stats.steps + 1}"
    residual = ("F(u) itself is finite there: the residual is NaN only through J, which lifts the Dirichlet values"
                if failure.residual_alone_finite else "F(u) is NaN or inf there too")
    return (f"its Jacobian J(u) became NaN or inf {where} ({_depends(named)}; {residual})",
            _singular_coefficient_fix(named))


def _depends(named: list) -> str:
    if named:
        return f"J depends on the controls {named}"
    return "J depends on none of the controls passed: a coefficient is undefined at this u"


def _singular_coefficient_fix(named: list) -> str:
    check = f", and check the controls {named} for zeros, NaN or inf" if named else ""
    return ("a coefficient of J is undefined at that state, e.g. the p-Laplacian's |grad u|^(p-2) (or its "
            "derivative) where grad u = 0; start away from the singular state with initial_guess=, or regularise "
            f"the coefficient, e.g. (eps + |grad u|^2)^((p-2)/2) with a small eps > 0{check}")


def _residual_nan(options, stats, failure):
    if not ended_nonfinite(stats):
        return None
    if not stats.residual_norms:
        return ("the residual became NaN or inf at the initial guess",
                "a coefficient of F is undefined at that state (e.g. a logarithm or a negative power of a quantity "
                "that vanishes there), or a Constant or fixed Function holds NaN or inf; start from another "
                "initial_guess, or regularise the coefficient")
    return (f"the residual became NaN or inf in Newton step {stats.steps + 1}",
            "the load or the controls may be beyond what the material model allows (e.g. an inverted element); "
            "reduce the load or apply it in increments (each solve started from the last with initial_guess=), "
            f"start from a better initial_guess, or {_nan_method(options)}")


def _nan_method(options) -> str:
    """A method that steps back from a NaN residual, other than the one in use."""
    if options.snes_type == "newton":
        return "use snes_type='newtonls' with a line search (it cuts back steps that make F NaN)"
    if options.snes_type == "newtonls" and options.linesearch == "basic":
        return "use a backtracking line search (linesearch='bt'), which cuts back steps that make F NaN"
    return "try " + " or ".join(_methods_other_than(options, "newton"))      # full steps would not avoid the NaN


def _linear_solve(options, stats, failure):
    if stats.reason_name != "DIVERGED_LINEAR_SOLVE":
        return None
    cause = f"its linear solve failed ({failure.inner_reason} after {failure.inner_iterations} iterations)"
    singular = f"J(u) may be singular: {_singular_hint(failure)}"
    if options.ksp.direct:          # a factorisation fails on a singular or non-finite J, not for want of strength
        return cause, singular
    fix = "use a stronger inner solve (ksp='lu'), or cap the inner solve on purpose with KSPOptions(max_it=K)"
    if failure.inner_reason in _SINGULAR_INNER or not failure.dirichlet:
        fix = f"{singular}; or {fix}"
    return cause, fix


def _line_search(options, stats, failure):
    if stats.reason_name != "DIVERGED_LINE_SEARCH":
        return None
    used = options.linesearch or ("bt" if options.snes_type == "newtonls" else "basic")
    cut = " (trial steps that made F NaN or inf were cut back)" if stats.nonfinite_residual else ""
    method = "" if options.snes_type == "newtonls" else "snes_type='newtonls' with "
    others = [f"{method}linesearch={name!r}{note}" for name, note in _LINE_SEARCH_NOTES.items() if name != used]
    others += _methods_other_than(options, "newtonls", "newton")      # plain Newton is linesearch="basic"
    fixes = [f"try {' or '.join(others)}", "start from a better initial_guess, or apply the load in increments "
             "(each solve started from the last with initial_guess=)", *_direction_hints(options, failure)]
    return (f"its line search ({used!r}) found no step along the Newton direction that decreases ||F||{cut}",
            "; ".join(fixes))


def _direction_hints(options, failure) -> list[str]:
    """Why a Newton direction may not decrease ||F||: an inexact step, a J that is not dF/du, a singular J."""
    hints = []
    if options.ksp.capped:
        hints.append("a capped inner solve gives an inexact step that need not decrease ||F||: converge it "
                     "(KSPOptions max_it=None)")
    if failure.given_jacobian:
        hints.append("the problem's J= is not dF/du, so its step need not decrease ||F||: check it")
    if not failure.dirichlet:
        hints.append(f"J(u) may be singular: {_singular_hint(failure)}")
    return hints


def _trust_region(options, stats, failure):
    if stats.reason_name != "DIVERGED_TR_DELTA":
        return None
    return ("its trust region shrank to nothing without a step that decreases ||F||",
            "; ".join(["start from a better initial_guess, or apply the load in increments (initial_guess=)",
                       f"or {_other_methods(options)}", *_direction_hints(options, failure)]))


def _local_minimum(options, stats, failure):
    if stats.reason_name != "DIVERGED_LOCAL_MIN":
        return None
    return ("reached a local minimum of ||F|| that is not a solution (J^T F = 0 with F != 0)",
            f"J(u) is singular there; likely cause: {_singular_hint(failure)}; or start from another initial_guess")


def _max_it(options, stats, failure):
    if stats.reason_name != "DIVERGED_MAX_IT":
        return None
    norms = stats.residual_norms
    if _stagnant(norms):
        return ("did not reach its tolerance",
                f"the residual stopped decreasing at {norms[-1]:.3e} (a Newton step no longer reduces it): J(u) is "
                f"singular there and more steps will not help; likely cause: {_singular_hint(failure)}")
    if norms[0] > 0 and norms[-1] >= DIVERGED_GROWTH * norms[0]:
        return "did not reach its tolerance", _diverged(options, stats, failure)
    far = _far_start(options, stats)
    if far is not None:
        return "did not reach its tolerance", far
    if len(norms) > 10 and norms[-1] >= 0.9 * norms[0]:
        return "did not reach its tolerance", _no_progress(options, stats, failure)
    fix = "raise converged_max_it, loosen rtol/atol, start from a better initial_guess, or load in increments"
    if failure.given_jacobian:
        fix += "; the problem's J= is not dF/du, which slows Newton down or stops it converging: check it"
    if not failure.dirichlet:
        fix += f"; J(u) may be singular: {_singular_hint(failure)}"
    return "did not reach its tolerance", fix


def _diverged(options, stats, failure) -> str:
    """The fix when the residual ended :data:`DIVERGED_GROWTH` or more times above where it started: Newton
    diverged from its start (a lid-driven cavity at Re = 1000 from zero). Not a load or a null space to
    check: nearer starts (continuation) or shorter steps."""
    norms = stats.residual_norms
    hints = [f"the residual grew {norms[-1] / norms[0]:.2g}-fold from the initial guess: Newton diverged; start "
             "closer (continuation in the parameter, e.g. solve at a lower Reynolds number or load and use that "
             f"solution as initial_guess, in steps up to this one) or {_shorter_steps(options)}",
             "if the continuation stops converging at some parameter value, there may be no solution beyond it "
             "(a fold or a limit load)"]
    if options.ksp.capped:
        hints.append(f"the inner solve, capped at {options.ksp.max_it} iterations, gives inexact steps: converge "
                     "it (max_it=None)")
    if failure.given_jacobian:
        hints.append("the problem's J= is not dF/du, which can make Newton diverge: check it")
    if not failure.dirichlet:
        hints.append(f"J(u) may be singular: {_singular_hint(failure)}")
    return "; ".join(hints)


def _shorter_steps(options) -> str:
    """How to shorten the steps of the method in use."""
    if options.snes_type == "newton":
        return (f"damp the step (damping={options.damping / 2:g}), or use snes_type='newtonls' with "
                "linesearch='bt'")
    if options.snes_type == "newtonls" and options.linesearch == "basic":
        return "use a backtracking line search (linesearch='bt')"
    return _other_methods(options)


def _far_start(options, stats) -> str | None:
    """The fix when the residual is still above that of the zero state with the boundary values (what rtol is
    relative to, :func:`~fempdl.solve.newton_options.rtol_scale`), having started above it: the initial guess
    was far from the solution and Newton had not come near it in its steps."""
    norms, reference = stats.residual_norms, stats.reference_norm
    if reference is None or not math.isfinite(reference) or not norms[-1] > reference or not norms[0] > reference:
        return None
    return (f"the residual is still {norms[-1] / reference:.2g} times that of the zero state with the boundary "
            f"values ({reference:.3e}, the scale rtol is relative to): the initial guess is far from the solution; "
            f"start closer (an initial_guess nearer the solution, or none: from zero), or raise converged_max_it "
            f"(now {options.converged_max_it})")


def _no_progress(options, stats, failure) -> str:
    """The fix when more than ten steps left ||F|| within 10% of where it started: more steps are unlikely
    to help, whatever converged_max_it says."""
    hints = [f"J(u) may be singular: {_singular_hint(failure)}"]
    if options.ksp.capped:
        hints.insert(0, f"the inner solve, capped at {options.ksp.max_it} iterations, may be too inexact to "
                        "make progress: raise its cap or converge it (max_it=None)")
    if failure.given_jacobian:
        hints.append("the problem's J= is not dF/du: check it")
    hints.append("or start from a better initial_guess")
    return f"the residual did not decrease in {stats.steps} steps, and more are unlikely to help; " + "; ".join(hints)


def _stagnant(norms) -> bool:
    """The last three steps left ||F|| unchanged to 1e-9, well above round-off of ||F(u_0)||: F is not in the
    range of J (J singular). A residual at its round-off floor wanders instead; slow convergence decreases."""
    last = norms[-4:]
    if len(last) < 4 or not all(math.isfinite(n) for n in last):
        return False
    return max(last) - min(last) <= 1e-9 * max(last) and last[-1] > 1e-8 * norms[0]


def _singular_hint(failure: NewtonFailure) -> str:
    """The likely causes of a singular J that the problem's set-up points to."""
    if failure.nullspace:
        return ("the problem declares a null space, and F(u) can vanish only for a load orthogonal to it (e.g. a "
                "zero-mean source for a pure Neumann problem): check the load, or look for a further null space "
                "(a missing Dirichlet condition)")
    if not failure.dirichlet:
        return ("the problem has no Dirichlet condition, so F may fix u only up to a constant (a pure Neumann "
                "problem): add a Dirichlet condition (bcs=), or declare the null space (nullspace=) and give a "
                "load orthogonal to it (e.g. zero mean)")
    return ("a missing Dirichlet condition (on part of the boundary, or on one field of a mixed space) or a "
            "null space to declare (nullspace=)")


def _other_methods(options) -> str:
    """The Newton methods other than the one in use, as a suggestion."""
    return "try " + " or ".join(_methods_other_than(options))


def _methods_other_than(options, *excluded: str) -> list[str]:
    methods = {"newton": "snes_type='newton' (full steps)", "newtonls": "snes_type='newtonls' with linesearch='bt'",
               "newtontr": "snes_type='newtontr' (trust region)"}
    return [text for name, text in methods.items() if name != options.snes_type and name not in excluded]


#: A failed solve whose residual ended this many times above its start diverged from it (a residual that
#: wanders at its start's scale, or shrinks too slowly, is named otherwise).
DIVERGED_GROWTH = 1e2
# Inner solves that stop this way met a singular (or indefinite) J: a breakdown, a zero pivot.
_SINGULAR_INNER = frozenset({"DIVERGED_BREAKDOWN", "DIVERGED_BREAKDOWN_BICG", "DIVERGED_INDEFINITE_PC",
                             "DIVERGED_INDEFINITE_MAT", "DIVERGED_PCSETUP_FAILED", "DIVERGED_PC_FAILED"})
_LINE_SEARCH_NOTES = {"basic": " (full steps)", "l2": " (a secant step length)", "cp": " (critical point)",
                      "bt": " (backtracking)"}      # in the order they are suggested
#: Tried in order; the J check first: a NaN residual that J caused is named as J's.
_EXPLANATIONS = (_jacobian, _residual_nan, _linear_solve, _line_search, _trust_region, _local_minimum, _max_it)
