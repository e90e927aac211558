"""A layer's backward uses what its forward read: Constants, fixed Functions and caps changed between
two calls (a variable time step, PRDP moving the cap) must not reach an earlier call's adjoint.

The reference is central differences of the same two-call loss with each call's values set as the
loop sets them; before the fix, step 1's adjoint was solved with step 2's dt (84-120% off)."""
from __future__ import annotations

import dolfinx.fem
import pytest
import torch
import ufl

from fempdl import NonlinearProblem, forms
from fempdl.bridge_torch import SolveLayer
from fempdl.core import _dolfinx
from fempdl.ksp_adjoint import KSPOptions
from fempdl.layer.newton_layer import NonlinearSolveLayer
from fempdl.solve.newton_options import NewtonOptions

DTS = (0.02, 0.3)       # far apart: the wrong dt gives an O(1) relative error


def two_steps(layer, u0, f, dts):
    """u2 after two steps u0 -> u1 -> u2 with the given dt per step, set in the shared Constant."""
    dt = layer.problem.constants["dt"]
    u = u0
    for value in dts:
        dt.value = value
        u = layer(u0=u, f=f)
    return u


def loss_of(u, w):
    return (w * u).sum()


def central_difference(fn, x, direction, eps=1e-6):
    with torch.no_grad():
        return (fn(x + eps * direction) - fn(x - eps * direction)) / (2 * eps)


@pytest.mark.parametrize("options", [KSPOptions.preset("lu"), KSPOptions.preset("jacobi", max_it=6)],
                         ids=["lu", "jacobi6"])
def test_changed_dt_between_steps_gives_each_step_its_own_adjoint(coarse_lshape, options):
    prob = forms.heat.problem(coarse_lshape, controls=("u0", "f"))
    layer = SolveLayer(prob, options)
    n = prob.output_size
    gen = torch.Generator().manual_seed(0)
    u0 = torch.rand(n, dtype=torch.float64, generator=gen)
    f = torch.rand(n, dtype=torch.float64, generator=gen, requires_grad=True)
    w = torch.rand(n, dtype=torch.float64, generator=gen)
    loss_of(two_steps(layer, u0, f, DTS), w).backward()
    direction = torch.rand(n, dtype=torch.float64, generator=gen)
    expected = central_difference(lambda x: loss_of(two_steps(layer, u0, x, DTS), w), f.detach(), direction)
    # The map is linear in f: central differences are exact up to round-off.
    assert torch.dot(f.grad, direction).item() == pytest.approx(expected.item(), rel=1e-7)
    assert prob.constants["dt"].value == DTS[-1]        # the backward put back what the loop had set


def test_changed_fixed_function_between_calls(coarse_lshape):
    """A fixed (non-control) coefficient Function changed between two calls, as a loop that writes the
    previous state into a Function instead of passing it as a control."""
    prob = forms.heat.problem(coarse_lshape, controls=("f",))
    u0_fn = next(c for c in prob.L.coefficients() if c.name == "u0")
    layer = SolveLayer(prob, "lu")
    n = prob.output_size
    gen = torch.Generator().manual_seed(1)
    f = torch.rand(n, dtype=torch.float64, generator=gen, requires_grad=True)
    w = torch.rand(n, dtype=torch.float64, generator=gen)
    kappa_like = [torch.rand(n, dtype=torch.float64, generator=gen) for _ in range(2)]

    def loss(x):
        total = 0.0
        for values, dt in zip(kappa_like, DTS):
            u0_fn.x.array[:n] = values.numpy()
            prob.constants["dt"].value = dt
            total = total + loss_of(layer(f=x) ** 2, w)
        return total

    loss(f).backward()
    direction = torch.rand(n, dtype=torch.float64, generator=gen)
    expected = central_difference(loss, f.detach(), direction)
    assert torch.dot(f.grad, direction).item() == pytest.approx(expected.item(), rel=1e-6)


def test_cap_moved_between_forward_and_backward(coarse_lshape):
    """PRDP stepping between a forward and its backward: the backward keeps the forward's cap (for
    Richardson + Jacobi the implicit backward is then the exact derivative of the K-step map)."""
    prob = forms.poisson.problem(coarse_lshape, controls=("f",))
    layer = SolveLayer(prob, KSPOptions.preset("jacobi", max_it=3))
    n = prob.output_size
    gen = torch.Generator().manual_seed(2)
    f = torch.rand(n, dtype=torch.float64, generator=gen, requires_grad=True)
    w = torch.rand(n, dtype=torch.float64, generator=gen)
    out = loss_of(layer(f=f), w)
    layer.max_it = 40
    out.backward()
    assert layer.max_it == 40
    layer.max_it = 3
    direction = torch.rand(n, dtype=torch.float64, generator=gen)
    expected = central_difference(lambda x: loss_of(layer(f=x), w), f.detach(), direction)
    assert torch.dot(f.grad, direction).item() == pytest.approx(expected.item(), rel=1e-8)
    backward = layer.stats.backward_iterations
    assert backward == 3        # one adjoint solve at the forward's cap


@pytest.mark.parametrize("control", ["kappa", "f"])
def test_unrolled_operators_see_a_changed_dt(coarse_lshape, control):
    """diff='unrolled' keeps A (and, for a matrix control, A as an affine function of kappa) as torch
    operators: they must be rebuilt when dt changes."""
    prob = forms.heat.problem(coarse_lshape, controls=(control,), f=1.0, u0=0.5)
    layer = SolveLayer(prob, KSPOptions.preset("jacobi", max_it=5), diff="unrolled")
    reference = SolveLayer(prob, KSPOptions.preset("jacobi", max_it=5))
    value = torch.full((prob.control_size(control),), 1.5, dtype=torch.float64)
    for dt in DTS:
        prob.constants["dt"].value = dt
        expected = reference(**{control: value})
        assert expected.abs().max() > 0.01
        torch.testing.assert_close(layer(**{control: value}), expected, rtol=1e-12, atol=1e-14)


def _nonlinear_heat(msh):
    V = _dolfinx.function_space(msh.mesh, "Lagrange", 1)
    u, u0, f = dolfinx.fem.Function(V), dolfinx.fem.Function(V), dolfinx.fem.Function(V)
    dt = dolfinx.fem.Constant(V.mesh, 0.1)
    v = ufl.TestFunction(V)
    F = ((u - u0) * v + dt * (1 + u ** 2) * ufl.inner(ufl.grad(u), ufl.grad(v)) - dt * f * v) * ufl.dx
    return NonlinearProblem(F, u, [], controls={"u0": u0, "f": f}, constants={"dt": dt})


@pytest.mark.parametrize("diff", ["implicit", "unrolled"])
def test_newton_layer_changed_dt_between_steps(coarse_lshape, diff):
    prob = _nonlinear_heat(coarse_lshape)
    layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"), diff=diff)
    n = prob.output_size
    gen = torch.Generator().manual_seed(3)
    u0 = 0.5 * torch.rand(n, dtype=torch.float64, generator=gen)
    f = torch.rand(n, dtype=torch.float64, generator=gen, requires_grad=True)
    w = torch.rand(n, dtype=torch.float64, generator=gen)
    loss_of(two_steps(layer, u0, f, DTS), w).backward()
    direction = torch.rand(n, dtype=torch.float64, generator=gen)
    expected = central_difference(lambda x: loss_of(two_steps(layer, u0, x, DTS), w), f.detach(), direction)
    # Converged Newton solves: the implicit gradient is exact up to the solve tolerance and the
    # O(eps^2) truncation of the central difference.
    assert torch.dot(f.grad, direction).item() == pytest.approx(expected.item(), rel=1e-6)


def test_newton_inner_cap_moved_between_forward_and_backward(coarse_lshape):
    """The inner cap moved between a Newton layer's forward and backward (PRDP's health check does it
    with a scheduled Rollout): the backward runs at the forward's inner cap, as if nothing moved, and
    the moved cap is back afterwards."""
    prob = forms.nonlinear_diffusion.problem(coarse_lshape, controls=("f",))
    layer = NonlinearSolveLayer(prob, NewtonOptions(max_it=3, ksp=KSPOptions.preset("jacobi", max_it=6)))
    gen = torch.Generator().manual_seed(4)
    f = torch.rand(prob.control_size("f"), dtype=torch.float64, generator=gen, requires_grad=True)
    w = torch.rand(prob.output_size, dtype=torch.float64, generator=gen)
    loss_of(layer(f=f), w).backward()
    expected, f.grad = f.grad.clone(), None
    out = loss_of(layer(f=f), w)
    layer.inner_max_it = 50
    out.backward()
    assert layer.inner_max_it == 50
    torch.testing.assert_close(f.grad, expected, rtol=1e-12, atol=0.0)
