"""A PETSc SNES for :class:`~fempdl.solve.newton_options.NewtonOptions`, and its destruction.

The SNES runs under a private options prefix, with the method, line search and damping the
options name, the tolerances of a capped or an uncapped solve, and two tests of PETSc's turned off:

* the divergence test (``snes_divergence_tolerance``, 1e4 by default): a residual that grows more
  than 10^4-fold in a step is what Newton does far from the solution under a large load, and
  DOLFINx's NewtonSolver goes on from there (a capped Newton must run its N steps);
* the limits on function evaluations and, for a capped inner solve, on failed linear solves
  (reaching its cap is what was asked for).

Its options go into PETSc's global database under the prefix and are removed by :func:`destroy_snes`.
"""
from __future__ import annotations

import weakref

from petsc4py import PETSc

from fempdl.solve.newton_options import NewtonOptions
from fempdl.solve.newton_stop import NewtonMode
from fempdl.solve.options import MAX_PETSC_INT
from fempdl.solve.petsc import unique_prefix

__all__ = ["create_snes", "destroy_snes", "weak_callback"]

_OPTION_KEYS = ("snes_linesearch_type", "snes_linesearch_damping", "snes_divergence_tolerance")


def create_snes(comm, options: NewtonOptions, ksp: PETSc.KSP, residual, jacobian, monitor,
                b: PETSc.Vec, J: PETSc.Mat, mode: NewtonMode,
                P: PETSc.Mat | None = None) -> PETSc.SNES:
    """A SNES solving F(u) = 0 with ``residual(snes, x, b)`` into ``b``, ``jacobian(snes, x, J, P)``
    into ``J``, each step's linear solve by ``ksp``, and ``monitor(snes, its, fnorm)`` called per
    step. ``mode`` (:class:`~fempdl.solve.newton_stop.NewtonMode`): whether to take at least one step
    even from a solution (an unrolled map needs one), and the convergence test in place of PETSc's
    (:class:`~fempdl.solve.newton_stop.NewtonStop`) of a solve that stops at its tolerances; SNES's own
    ``max_it`` still ends the solve.
    ``P``: the matrix the inner preconditioner is set up on, when not ``J`` (``jacobian`` fills both)."""
    snes = PETSc.SNES().create(comm)
    prefix = unique_prefix("snes")
    snes.setOptionsPrefix(prefix)
    snes.setType("newtonls" if options.snes_type == "newton" else options.snes_type)
    db = PETSc.Options()
    if options.snes_type != "newtontr":
        db[prefix + "snes_linesearch_type"] = "basic" if options.plain else (options.linesearch or "bt")
        db[prefix + "snes_linesearch_damping"] = options.damping
    if not hasattr(snes, "setDivergenceTolerance"):
        db[prefix + "snes_divergence_tolerance"] = -1.0       # off, in PETSc 3.18 (no setter in petsc4py)
    snes.setKSP(ksp)
    snes.setFunction(residual, b)
    snes.setJacobian(jacobian, J, P)
    snes.setFromOptions()
    snes.setTolerances(**options.snes_tolerances())
    if hasattr(snes, "setDivergenceTolerance"):
        # Off: PETSc >= 3.22 says so with PETSC_UNLIMITED (-1 became "the default" there).
        snes.setDivergenceTolerance(getattr(PETSc, "UNLIMITED", -1.0))
    snes.setMaxFunctionEvaluations(MAX_PETSC_INT)
    snes.setMaxLinearSolveFailures(MAX_PETSC_INT if options.ksp.capped else 1)
    snes.setForceIteration(mode.force_step)
    snes.setMonitor(monitor)
    stop = mode.convergence_test(options)
    if stop is not None:
        snes.setConvergenceTest(stop)
    return snes


def destroy_snes(snes: PETSc.SNES) -> None:
    """Destroy ``snes`` and remove the options :func:`create_snes` put under its prefix."""
    prefix = snes.getOptionsPrefix()
    db = PETSc.Options()
    for key in _OPTION_KEYS:
        db.delValue(prefix + key)
    snes.destroy()


def weak_callback(method):
    """A callback that calls ``method`` through a weak reference: the SNES holds its callbacks, and a
    bound method would make system and SNES a cycle that only a cyclic collection frees."""
    ref = weakref.WeakMethod(method)

    def call(*args):
        return ref()(*args)
    return call
