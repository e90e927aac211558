"""When a Newton solve stops: its tolerances, the cap as a budget, and the round-off floor.

PETSc's default test, with two departures that warm starts need.

What ``rtol`` is relative to: min(||F(u_0)||, ||F(u_ref)||), u_ref the zero state with the boundary
values (:func:`~fempdl.solve.newton_options.rtol_scale`), not ||F(u_0)|| alone. A start far from the
solution (``initial_guess=`` of 1e6 for a conductivity 1 + u^2) has a residual many orders above the
load's, and rtol of it was met by a state still far from the solution. ||F(u_ref)|| is the load's
scale, what a solve from zero (and DOLFINx's Newton from a zero guess) measures against; a warm start
near its solution has the smaller residual and keeps its own. The run measures ||F(u_ref)|| once per
solve that starts from a guess (:attr:`NewtonStop.reference`, one residual assembly; a solve from zero
starts at u_ref). A far start then either converges to the solution or fails by the step limit, with
a message that names the far start; it is never accepted where it is.

The round-off floor. A solve
started at (or near) its solution has a residual at the round-off floor of its
own scale: the tolerance relative to that start is unreachable and ``atol``
may lie below the floor (a neo-Hookean beam with E = 1e4 sits at 6e-11 against
atol = 1e-12), so the solve ran to ``converged_max_it`` and failed. Here a step
that is negligible beside the state (||du|| <= ``FLOOR_STEP`` ||u||), that did
not reduce the residual (||F_k+1|| > ``FLOOR_STALL`` ||F_k||), and a residual
at the round-off floor (:func:`~fempdl.solve.round_off.round_off_floor` of J
and u) end the solve as converged (``CONVERGED_SNORM_RELATIVE``). Above the floor Newton's
quadratic phase shrinks the residual by far more than ``FLOOR_STALL``; and a
singular J (a missing Dirichlet condition) also gives a tiny step that leaves
the residual where it was, but far above that scale, so it still fails and
says why. The floor's J norm is computed only when the first two hold.

:class:`NewtonMode` is the stop rule of a system's solves, chosen once from how a
layer differentiates them (:meth:`NewtonMode.for_diff`): :class:`NewtonStop` is
the SNES convergence test of every solve that stops at its tolerances: uncapped
solves, and capped ones whose cap is a budget (under implicit differentiation,
where the gradient at a converged state is exact). A capped solve differentiated
as the N-step map (``diff="unrolled"``) keeps PETSc's test with zero tolerances:
exactly N steps, and at least one even from a solution.
"""
from __future__ import annotations

import dataclasses
import math

from petsc4py import PETSc

from fempdl.solve.newton_options import NewtonOptions, rtol_scale
from fempdl.solve.round_off import round_off_floor

__all__ = ["NewtonMode", "NewtonStop", "FLOOR_STEP", "FLOOR_STALL"]

#: A Newton step this small relative to the state changes it by round-off (PETSc's default stol).
FLOOR_STEP = 1e-8
#: A step at the floor leaves the residual where it was; any step of Newton's quadratic phase above
#: the floor divides it by far more than 1 / FLOOR_STALL.
FLOOR_STALL = 0.5

_REASON = PETSc.SNES.ConvergedReason


@dataclasses.dataclass(frozen=True)
class NewtonMode:
    """How a system's Newton solves stop, one value from the layer's ``diff`` (:meth:`for_diff`).

    Attributes:
        budget: a capped solve may stop at its tolerances before the cap (implicit gradients are
            exact at a converged state); otherwise it runs exactly ``max_it`` steps.
        force_step: take at least one step even from a solution (an unrolled derivative needs one:
            the N-step map is not the identity near a solution).
    """

    budget: bool = False
    force_step: bool = False

    @classmethod
    def for_diff(cls, diff: str) -> NewtonMode:
        """The mode of a layer that differentiates its solves implicitly or unrolled."""
        modes = {"implicit": cls(budget=True), "unrolled": cls(force_step=True)}
        if diff not in modes:
            raise ValueError(f"diff must be one of {list(modes)}, got {diff!r}")
        return modes[diff]

    def stops_at_tolerances(self, options: NewtonOptions) -> bool:
        """Whether a solve under ``options`` stops at its tolerances (an uncapped one, or
        one whose cap is a budget) rather than after exactly ``max_it`` steps."""
        return not options.capped or self.budget

    def convergence_test(self, options: NewtonOptions) -> NewtonStop | None:
        """The SNES convergence test of a solve under ``options``: :class:`NewtonStop`, or ``None`` (PETSc's
        test with the capped options' zero tolerances: exactly ``max_it`` steps)."""
        if not self.stops_at_tolerances(options):
            return None
        return NewtonStop(options.rtol, options.atol, force_step=self.force_step)


class NewtonStop:
    """A SNES convergence test (``snes.setConvergenceTest(NewtonStop(...))``): ``atol`` as PETSc's default
    test applies it, ``rtol`` relative to min(||F(u_0)||, :attr:`reference`), the round-off floor (module
    docstring), NaN/inf as divergence. The step limit is SNES's own ``max_it``.

    Attributes:
        reference: ||F(u_ref)|| of the solve about to run, set before each solve
            (:class:`~fempdl.solve.newton_run.NewtonRun`); ``None``: not measured (a start from zero,
            where it is ||F(u_0)||).
    """

    def __init__(self, rtol: float, atol: float, *, force_step: bool = False):
        self.rtol, self.atol, self.force_step = rtol, atol, force_step
        self.reference: float | None = None
        self._first = self._previous = math.inf

    @property
    def needs_reference(self) -> bool:
        """Whether a solve from a guess needs ||F(u_ref)|| measured (only the rtol test reads it)."""
        return self.rtol > 0

    def __call__(self, snes, its: int, norms) -> int:
        xnorm, step_norm, fnorm = norms
        if its == 0:
            self._first, self._previous = rtol_scale(fnorm, self.reference), fnorm
        if not math.isfinite(fnorm):
            return _REASON.DIVERGED_FNORM_NAN
        reason = _REASON.ITERATING
        if fnorm < self.atol and (its > 0 or not self.force_step):
            reason = _REASON.CONVERGED_FNORM_ABS
        elif its > 0 and fnorm <= self.rtol * self._first:
            reason = _REASON.CONVERGED_FNORM_RELATIVE
        elif (its > 0 and step_norm <= FLOOR_STEP * xnorm and fnorm > FLOOR_STALL * self._previous
              and fnorm <= round_off_floor(snes.getJacobian()[0], xnorm)):
            reason = _REASON.CONVERGED_SNORM_RELATIVE
        self._previous = fnorm
        return reason
