"""A Newton cap is a budget under implicit differentiation, exactly N steps under unrolled differentiation,
and a solve started at (or next to) its solution converges at once, whatever the scale of its residual.

Before: a capped Newton solve ran all 13 steps of PRDP's cap although its residual reached 1.7e-15 after
three, and a warm start at the solution of a problem whose residual's round-off floor lies above atol
failed with DIVERGED_MAX_IT after 50 steps. (A singular J, whose tiny steps leave a residual far above
round-off, still fails and says why: tests/test_newton_messages.py.)"""
from __future__ import annotations

import gc
import weakref

import pytest
import torch

from fempdl import NewtonOptions, NonlinearSolveLayer, forms
from fempdl.solve.newton_stop import NewtonMode, NewtonStop
from fempdl.solve.nonlinear_system import NonlinearSystem


def problem(msh, scale=1.0):
    """-div(kappa (1 + 5 u^2) grad u) = f with kappa = scale, f = 5 scale: u does not depend on the scale,
    the residual's round-off floor grows with it."""
    prob = forms.nonlinear_diffusion.problem(msh, controls=("f",), alpha=5.0, kappa=scale)
    return prob, torch.full((prob.control_size("f"),), 5.0 * scale, dtype=torch.float64)


def test_a_capped_implicit_solve_stops_at_its_tolerance(coarse_lshape):
    prob, f = problem(coarse_lshape)
    converged = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"))
    with torch.no_grad():
        reference = converged(f=f)
    needed = converged.stats.last_newton.steps
    layer = NonlinearSolveLayer(prob, NewtonOptions(max_it=needed + 8, ksp="lu"))
    f = f.clone().requires_grad_()
    u = layer(f=f)
    last = layer.stats.last_newton
    assert last.steps == needed < layer.max_it and last.reason_name.startswith("CONVERGED") and last.ok
    assert layer.stats.newton_steps == needed                     # the stats count what ran
    torch.testing.assert_close(u.detach(), reference, rtol=0, atol=1e-12)
    # At the early stop the implicit gradient is the exact one: central differences of the converged map.
    w = torch.rand(prob.output_size, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    (w * u).sum().backward()
    direction = torch.rand(prob.control_size("f"), dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    eps = 1e-5
    with torch.no_grad():
        expected = ((w * converged(f=f + eps * direction)).sum()
                    - (w * converged(f=f - eps * direction)).sum()) / (2 * eps)
    assert torch.dot(f.grad, direction).item() == pytest.approx(expected.item(), rel=1e-7)


def test_below_the_tolerance_the_cap_still_holds(coarse_lshape):
    prob, f = problem(coarse_lshape)
    layer = NonlinearSolveLayer(prob, NewtonOptions(max_it=2, ksp="lu"))
    layer(f=f)
    last = layer.stats.last_newton
    assert last.steps == 2 and last.capped and last.ok


def test_an_unrolled_solve_runs_exactly_its_cap(coarse_lshape):
    prob, f = problem(coarse_lshape)
    layer = NonlinearSolveLayer(prob, NewtonOptions(max_it=12, ksp="lu"), diff="unrolled")
    layer(f=f)
    assert layer.stats.last_newton.steps == 12 and layer.stats.last_newton.capped


@pytest.mark.parametrize("scale", [1e4, 1e8])
@pytest.mark.parametrize("max_it", [None, 10])
def test_a_warm_start_at_the_solution_converges_at_once(coarse_lshape, scale, max_it):
    prob, f = problem(coarse_lshape, scale)
    layer = NonlinearSolveLayer(prob, NewtonOptions(max_it=max_it, ksp="lu"))
    u = layer(f=f)
    u = layer(f=f, initial_guess=u)                # from rtol's stop down to the round-off floor
    floor = layer.stats.last_newton.residual_norms[-1]
    assert floor > layer.options.atol              # the round-off floor lies above atol: rtol/atol alone fail
    again = layer(f=f, initial_guess=u)
    last = layer.stats.last_newton
    assert last.steps <= 1 and last.ok and last.reason_name == "CONVERGED_SNORM_RELATIVE"
    torch.testing.assert_close(again, u, rtol=1e-13, atol=1e-13)


def test_the_stop_rule_is_one_value_chosen_from_diff(coarse_lshape):
    """``NewtonMode.for_diff`` builds the stop rule once; the system and its SNES take it as one value."""
    implicit, unrolled = NewtonMode.for_diff("implicit"), NewtonMode.for_diff("unrolled")
    assert (implicit, unrolled) == (NewtonMode(budget=True), NewtonMode(force_step=True))
    with pytest.raises(ValueError, match="diff must be one of"):
        NewtonMode.for_diff("adjoint")
    capped, uncapped = NewtonOptions(max_it=3, ksp="lu"), NewtonOptions(ksp="lu")
    assert isinstance(implicit.convergence_test(capped), NewtonStop) and unrolled.convergence_test(capped) is None
    assert unrolled.convergence_test(uncapped).force_step and not implicit.convergence_test(uncapped).force_step
    prob, _ = problem(coarse_lshape)
    assert NonlinearSolveLayer(prob, capped, diff="unrolled").system.mode == unrolled
    # The reverse pass reaches the system's transposed solve through a weak reference: no cycle.
    gc.disable()
    try:
        system = NonlinearSystem(prob, capped, mode=implicit)
        ref = weakref.ref(system)
        del system
        assert ref() is None
    finally:
        gc.enable()
