"""When a Newton solve stops: its tolerances, the cap as a budget, and the round-off floor.

PETSc's default test, with one departure that warm starts need. A solve
started at (or near) its solution has a residual at the round-off floor of its
own scale: the tolerance relative to that start is unreachable and ``atol``
may lie below the floor (a neo-Hookean beam with E = 1e4 sits at 6e-11 against
atol = 1e-12), so the solve ran to ``converged_max_it`` and failed. Here a step
that is negligible beside the state (||du|| <= ``FLOOR_STEP`` ||u||), that did
not reduce the residual (||F_k+1|| > ``FLOOR_STALL`` ||F_k||), and a residual
within the round-off of the terms it sums (||F|| <= ``FLOOR_RESIDUAL`` eps
||J||_inf ||u||: each entry of F = J u - f rounds to about eps |J| |u|) end
the solve as converged (``CONVERGED_SNORM_RELATIVE``). Above the floor Newton's
quadratic phase shrinks the residual by far more than ``FLOOR_STALL``; and a
singular J (a missing Dirichlet condition) also gives a tiny step that leaves
the residual where it was, but far above that scale, so it still fails and
says why. The floor's J norm is computed only when the first two hold.

:class:`NewtonStop` is the SNES convergence test of every solve that stops at
its tolerances: uncapped solves, and capped ones whose cap is a budget (under
implicit differentiation, where the gradient at a converged state is exact).
A capped solve differentiated as the N-step map (``diff="unrolled"``) keeps
PETSc's test with zero tolerances: exactly N steps.
"""
from __future__ import annotations

import math

import numpy as np
from petsc4py import PETSc

__all__ = ["NewtonStop", "FLOOR_STEP", "FLOOR_STALL", "FLOOR_RESIDUAL"]

#: A Newton step this small relative to the state changes it by round-off (PETSc's default stol).
FLOOR_STEP = 1e-8
#: A step at the floor leaves the residual where it was; any step of Newton's quadratic phase above
#: the floor divides it by far more than 1 / FLOOR_STALL.
FLOOR_STALL = 0.5
#: The residual's round-off, in units of eps ||J||_inf ||u||_2: room for the sum over entries and
#: cancellation, and still orders of magnitude below a singular J's stuck residual.
FLOOR_RESIDUAL = 1e4
_EPS = float(np.finfo(np.float64).eps)

_REASON = PETSc.SNES.ConvergedReason


class NewtonStop:
    """A SNES convergence test (``snes.setConvergenceTest(NewtonStop(...))``): ``atol`` and ``rtol`` as
    PETSc's default test applies them, the round-off floor (module docstring), NaN/inf as divergence.
    The step limit is SNES's own ``max_it``."""

    def __init__(self, rtol: float, atol: float, *, force_step: bool = False):
        self.rtol, self.atol, self.force_step = rtol, atol, force_step
        self._first = self._previous = math.inf

    def __call__(self, snes, its: int, norms) -> int:
        xnorm, step_norm, fnorm = norms
        if its == 0:
            self._first = self._previous = fnorm
        if not math.isfinite(fnorm):
            return _REASON.DIVERGED_FNORM_NAN
        reason = _REASON.ITERATING
        if fnorm < self.atol and (its > 0 or not self.force_step):
            reason = _REASON.CONVERGED_FNORM_ABS
        elif its > 0 and fnorm <= self.rtol * self._first:
            reason = _REASON.CONVERGED_FNORM_RELATIVE
        elif (its > 0 and step_norm <= FLOOR_STEP * xnorm and fnorm > FLOOR_STALL * self._previous
              and fnorm <= FLOOR_RESIDUAL * _EPS * snes.getJacobian()[0].norm(PETSc.NormType.INFINITY) * xnorm):
            reason = _REASON.CONVERGED_SNORM_RELATIVE
        self._previous = fnorm
        return reason
