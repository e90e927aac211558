"""Newton from a far initial guess, and Newton that diverges from its start (issue #55).

Two failures used to pass for something else:

* rtol was relative to ||F(u_0)|| alone, so a far start met it far from the solution: nonlinear
  diffusion (q = 1 + u^2) from a guess of 1e6 "converged" in 19 steps to a state 650 times off (from
  1e3: 3% off). rtol is now relative to min(||F(u_0)||, ||F(u_ref)||), u_ref the zero state with the
  boundary values (:func:`fempdl.solve.newton_options.rtol_scale`): the far start reaches the solution
  DOLFINx's Newton finds, or fails by the step limit saying the start was far;
* a lid-driven cavity at Re = 1000 from zero (plain Newton's residual grows thousands-fold) was
  reported with "check the load, or look for a further null space"; the message now says Newton
  diverged from its start and names continuation in Re (which converges) and a damped step.
"""
from __future__ import annotations

import math
import warnings

from mpi4py import MPI
import dolfinx.fem
import dolfinx.fem.petsc
import dolfinx.mesh
import dolfinx.nls.petsc
import numpy as np
import pytest
import torch
import ufl
from petsc4py import PETSc
from test_nonlinear_forms import tagged

from fempdl import NewtonOptions, NonlinearSolveLayer, SolverFailedError, forms
from fempdl.solve.newton_options import rtol_scale
from fempdl.solve.newton_stats import DIVERGED_GROWTH, SNES_REASON_NAMES, NewtonFailure, NewtonSolveStats, explain
from fempdl.solve.newton_stop import NewtonStop

F64 = torch.float64
DEFAULT = NewtonOptions(ksp="lu")          # rtol 1e-10, atol 1e-12: the tolerances of the probe
_REASON = PETSc.SNES.ConvergedReason


def g_bc(x):
    return 0.3 * x[0] - 0.2 * x[1] ** 2


@pytest.fixture(scope="module")
def diffusion():
    """-div((1 + u^2) grad u) = f on the unit square (8 x 8), u = g on the boundary; control f."""
    return forms.nonlinear_diffusion.problem(dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 8, 8),
                                             controls=("f",), g=g_bc)


def dolfinx_newton(prob, f: float, guess: float, rtol: float, atol: float) -> np.ndarray:
    """DOLFINx's own Newton (NewtonSolver, full LU steps, its residual test) on ``prob``'s residual with the
    source f, from the constant ``guess`` everywhere (boundary entries included: DOLFINx does not put the
    boundary values into its start). 0.10+ call the problem class NewtonSolverNonlinearProblem."""
    prob.control("f").x.array[:] = f
    u = dolfinx.fem.Function(prob.V)
    u.x.array[:] = guess
    Problem = getattr(dolfinx.fem.petsc, "NewtonSolverNonlinearProblem", None) or dolfinx.fem.petsc.NonlinearProblem
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)       # 0.10+ deprecate NewtonSolver
        solver = dolfinx.nls.petsc.NewtonSolver(MPI.COMM_WORLD,
                                                Problem(ufl.replace(prob.F, {prob.u: u}), u, bcs=list(prob.bcs)))
    solver.convergence_criterion = "residual"
    solver.rtol, solver.atol, solver.max_it = rtol, atol, 60
    solver.krylov_solver.setType("preonly")
    solver.krylov_solver.getPC().setType("lu")
    steps, converged = solver.solve(u)
    assert converged
    return u.x.array[:prob.output_size].copy()


def rel(a, b) -> float:
    a = a.detach().numpy() if isinstance(a, torch.Tensor) else a
    return float(np.abs(a - b).max() / np.abs(b).max())


def full(n: int, value: float) -> torch.Tensor:
    return torch.full((n,), value, dtype=F64)


# ------------------------------------------------------------------ the stop rule
def test_rtol_is_relative_to_the_smaller_of_the_start_and_the_zero_state():
    """The stop test and the helper that re-judges residual histories apply one rule."""
    stop = NewtonStop(rtol=1e-3, atol=0.0)
    stop.reference = 1.0                               # ||F(u_ref)||: the load's scale
    assert stop(None, 0, (1.0, 0.0, 1e6)) == _REASON.ITERATING
    assert stop(None, 1, (1.0, 1.0, 1e3)) == _REASON.ITERATING        # 1e-3 of the far start, not of the load
    assert stop(None, 2, (1.0, 1.0, 1e-4)) == _REASON.CONVERGED_FNORM_RELATIVE
    near = NewtonStop(rtol=1e-3, atol=0.0)
    near.reference = 1.0
    near(None, 0, (1.0, 0.0, 1e-6))                    # a warm start near its solution keeps its own rtol
    assert near(None, 1, (1.0, 1.0, 1e-8)) == _REASON.ITERATING
    assert near(None, 2, (1.0, 1.0, 1e-10)) == _REASON.CONVERGED_FNORM_RELATIVE
    options = NewtonOptions(rtol=1e-3, atol=0.0)
    assert not options.tolerances_met((1e6, 1e3), reference=1.0) and options.tolerances_met((1e6, 1e3))
    assert options.tolerances_met((1e6, 1e-4), reference=1.0)
    assert not options.tolerances_met((1e-6, 1e-8), reference=1.0)
    assert rtol_scale(1e6, None) == 1e6 and rtol_scale(1e6, math.nan) == 1e6 and rtol_scale(1e6, math.inf) == 1e6


@pytest.mark.parametrize("guess", [1e3, 1e6])
def test_a_far_guess_converges_to_the_solution_dolfinx_newton_finds(diffusion, guess):
    n = diffusion.output_size
    f = full(diffusion.control_size("f"), 10.0)
    layer = NonlinearSolveLayer(diffusion, DEFAULT)
    u = layer(f=f, initial_guess=full(n, guess))
    stats = layer.stats.last_newton
    assert stats.ok and stats.reason > 0 and stats.reference_norm is not None
    assert stats.residual_norms[0] > 1e6 * stats.reference_norm             # the start was far
    assert stats.residual_norms[-1] <= max(DEFAULT.atol, DEFAULT.rtol * stats.reference_norm)
    reference = dolfinx_newton(diffusion, 10.0, 0.0, rtol=1e-12, atol=1e-14)        # from zero, tight
    same_start = dolfinx_newton(diffusion, 10.0, guess, rtol=DEFAULT.rtol, atol=DEFAULT.atol)
    assert rel(u, reference) <= 1e-9                        # was 3e-2 (from 1e3) and 6.5e2 (from 1e6)
    assert rel(u, reference) <= max(rel(same_start, reference), 1e-12)
    # From zero no reference is measured: u_0 is u_ref.
    layer(f=f)
    assert layer.stats.last_newton.reference_norm is None and layer.stats.last_newton.ok
    layer.close()


def test_a_far_guess_beyond_the_step_limit_fails_naming_the_far_start(diffusion):
    """20 steps do not bring plain Newton from 1e6 to the solution: a failure that says the start was far
    (the rule used to accept the 19th iterate, 650 times the solution)."""
    layer = NonlinearSolveLayer(diffusion, NewtonOptions(ksp="lu", converged_max_it=20))
    with pytest.raises(SolverFailedError, match=r"did not reach its tolerance: SNES reason DIVERGED_MAX_IT after "
                                                r"20 step\(s\)") as info:
        layer(f=full(diffusion.control_size("f"), 10.0), initial_guess=full(diffusion.output_size, 1e6))
    message = str(info.value)
    assert "times that of the zero state with the boundary values" in message
    assert "the initial guess is far from the solution" in message and "raise converged_max_it (now 20)" in message
    assert "loosen rtol" not in message
    layer.close()


@pytest.mark.parametrize("diff", ["implicit", "unrolled"])
def test_a_capped_solve_from_a_far_guess_runs_its_cap(diffusion, diff):
    """A cap is still a cap: N steps from the far start (the implicit budget no longer stops early there),
    and an unrolled solve measures no reference (it has no tolerance)."""
    layer = NonlinearSolveLayer(diffusion, NewtonOptions(ksp="lu", max_it=5), diff=diff)
    layer(f=full(diffusion.control_size("f"), 10.0), initial_guess=full(diffusion.output_size, 1e6))
    stats = layer.stats.last_newton
    assert stats.steps == 5 and stats.capped and stats.ok
    assert (stats.reference_norm is None) == (diff == "unrolled")
    layer.close()


# ------------------------------------------------------------------ Newton diverging from its start
@pytest.fixture(scope="module")
def cavity():
    """A 12 x 12 unit square (1419 Taylor-Hood DOFs), facets tagged lid (y = 1) / walls: coarse, and fine
    enough that continuation in Re reaches Re = 1000 (on 8 x 8 the Galerkin solution branch ends before)."""
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 12, 12)
    return tagged(msh, {"lid": lambda x: np.isclose(x[1], 1.0), "walls": None})


@pytest.fixture(scope="module")
def lid_flow(cavity):
    """The lid-driven cavity (lid speed 1, side 1) with the viscosity as a control: Re = 1 / nu."""
    return forms.navier_stokes.problem(cavity, controls=("nu",), velocity={"lid": (1.0, 0.0), "walls": 0.0})


def reynolds(prob, re: float) -> torch.Tensor:
    return full(prob.control_size("nu"), 1.0 / re)


def test_a_cavity_at_re_1000_from_zero_is_named_divergence_not_the_load(lid_flow):
    assert lid_flow.enclosed                             # a declared null space: what the old message blamed
    layer = NonlinearSolveLayer(lid_flow, NewtonOptions())
    with pytest.raises(SolverFailedError) as info:
        layer(nu=reynolds(lid_flow, 1000.0))
    message, norms = str(info.value), info.value.stats.residual_norms
    assert norms[-1] >= DIVERGED_GROWTH * norms[0]
    assert "-fold from the initial guess: Newton diverged" in message
    assert "continuation in the parameter" in message and "initial_guess" in message and "damping=0.5" in message
    assert "null space" not in message and "check the load" not in message and "singular" not in message
    layer.close()


def test_continuation_in_re_reaches_re_1000(lid_flow):
    """What the message suggests works: Re 100 -> 400 -> 1000, each solve started from the last."""
    layer = NonlinearSolveLayer(lid_flow, NewtonOptions())
    x = None
    for re in (100.0, 400.0, 1000.0):
        x = layer(nu=reynolds(lid_flow, re), initial_guess=x)
        assert layer.stats.last_newton.ok and layer.stats.last_newton.reason > 0, re
    assert torch.isfinite(x).all()
    layer.close()


def test_a_grown_residual_is_named_divergence_for_every_method_and_keeps_the_other_causes():
    """The message of a residual that grew: no method in use suggested, damping halved from the one in use;
    a residual that stopped decreasing is still a singular J's (the null space named)."""
    reason = {name: code for code, name in SNES_REASON_NAMES.items()}["DIVERGED_MAX_IT"]

    def stats(norms):
        return NewtonSolveStats(steps=len(norms) - 1, reason=reason, reason_name="DIVERGED_MAX_IT",
                                residual_norms=tuple(norms), inner_iterations=1, capped=False, ok=False, time=0.0)

    grown, stuck = stats((1.0, 5.0, 300.0, 2e3)), stats((1.0, 0.3, 0.25, 0.25, 0.25, 0.25))
    flow = NewtonFailure(nullspace=True)
    cause, fix = explain(NewtonOptions(ksp="lu", damping=0.5), grown, flow)
    assert cause == "did not reach its tolerance" and "grew 2e+03-fold" in fix and "damping=0.25" in fix
    assert "null space" not in fix
    _, fix = explain(NewtonOptions(ksp="lu", snes_type="newtonls", linesearch="basic"), grown, flow)
    assert "linesearch='bt'" in fix and "linesearch='basic'" not in fix and "damping=" not in fix
    _, fix = explain(NewtonOptions(ksp="lu", snes_type="newtontr"), grown, flow)
    assert "snes_type='newtontr'" not in fix
    _, fix = explain(NewtonOptions(ksp="lu"), stuck, flow)
    assert "stopped decreasing" in fix and "a load orthogonal to it" in fix
