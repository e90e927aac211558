"""A Newton solve's lagged factorisation (KSPOptions.preset("lu-lagged")): every step solves its own
Jacobian to rtol by GMRES preconditioned with an earlier LU, so the iterates, the states and the implicit
gradients are those of LU Newton, with fewer factorisations."""
from mpi4py import MPI
import numpy as np
import pytest
import torch

from fempdl import KSPOptions, NewtonOptions, NonlinearSolveLayer, Rollout, forms, mesh
from fempdl.core.tuning import LAGGED_REFRESH_ITERATIONS

STEPS = 12


@pytest.fixture(scope="module")
def lshape():
    return mesh.load("lshape", MPI.COMM_SELF, h=0.2)


def rollout(msh, ksp):
    problem = forms.nonlinear_diffusion.problem(msh, controls=("u0", "f"), alpha=2.0, dt=0.02)
    step = NonlinearSolveLayer(problem, NewtonOptions(rtol=1e-11, atol=1e-13, ksp=ksp))
    return Rollout(step, "u0")


def loss_and_grads(roll, u0, f):
    u0, f = u0.clone().requires_grad_(), f.clone().requires_grad_()
    out = roll(u0, STEPS, f=f, outputs=[STEPS // 2, STEPS])
    loss = (out ** 2).sum()
    loss.backward()
    return out.detach(), u0.grad, f.grad


@pytest.mark.parametrize("batch", [1, 2])
def test_lagged_rollout_equals_lu_newton_with_fewer_factorisations(lshape, batch):
    exact, lagged = rollout(lshape, "lu"), rollout(lshape, "lu-lagged")
    n = exact.step.problem.output_size
    g = torch.Generator().manual_seed(3)
    u0 = 0.5 * torch.rand(batch, n, dtype=torch.float64, generator=g)
    f = 4 * torch.rand(batch, n, dtype=torch.float64, generator=g)
    ref, lag = loss_and_grads(exact, u0, f), loss_and_grads(lagged, u0, f)
    for a, b in zip(ref, lag):
        # Both Newton solves stop at rtol 1e-11 of a residual the inner solves reduce to 1e-12.
        assert float((a - b).abs().max()) <= 1e-8 * float(a.abs().max()), float((a - b).abs().max())
    s_exact, s_lag = exact.step.system.stats, lagged.step.system.stats
    assert s_lag.newton_steps == s_exact.newton_steps          # the same Newton iteration
    solves = s_lag.newton_steps + s_lag.backward_solves         # Newton steps and transposed solves
    assert s_lag.backward_solves == batch * STEPS
    if batch == 1:
        # An LU Newton factorises at every one of them; the lagged one only when a solve was slow.
        # (Samples taken in turn, each step, move J far: a batch refreshes about every solve.)
        assert 1 <= s_lag.preconditioner_refreshes <= solves // 2, (s_lag.preconditioner_refreshes, solves)
    assert s_lag.forward_iterations > s_lag.newton_steps       # GMRES ran on the current J
    assert s_exact.preconditioner_refreshes == 0


def test_lagged_preconditioner_is_set_up_again_when_the_jacobian_moves_far(lshape):
    """A sample whose Jacobian differs wholly (20x the source) is still solved to rtol: the slow solve
    sets the LU up again on its matrix."""
    roll = rollout(lshape, "lu-lagged")
    step = roll.step
    n = step.problem.output_size
    mild = torch.full((1, n), 0.5, dtype=torch.float64)
    with torch.no_grad():
        step(u0=torch.zeros(1, n, dtype=torch.float64), f=mild)
        before = step.system.stats.preconditioner_refreshes
        far = step(u0=torch.zeros(1, n, dtype=torch.float64), f=20 * mild)
    last = step.system.stats.last_newton
    assert last.ok and last.residual_norms[-1] <= 1e-11 * last.residual_norms[0] + 1e-13
    assert step.system.stats.preconditioner_refreshes > before
    ref = NonlinearSolveLayer(step.problem, NewtonOptions(rtol=1e-11, atol=1e-13, ksp="lu"))
    with torch.no_grad():
        exact = ref(u0=torch.zeros(1, n, dtype=torch.float64), f=20 * mild)
    assert float((far - exact).abs().max()) <= 1e-8 * float(exact.abs().max())


def test_a_lagged_direct_inner_solve_is_refused():
    with pytest.raises(ValueError, match="lu-lagged"):
        NewtonOptions(ksp=KSPOptions.preset("lu", lag_preconditioner=True))


def test_the_refresh_rule_is_a_few_iterations():
    assert 1 <= LAGGED_REFRESH_ITERATIONS <= 10
    preset = KSPOptions.preset("lu-lagged")
    assert preset.lag_preconditioner and not preset.direct and preset.rtol == 1e-12
    assert np.isclose(preset.rtol, 1e-12)
