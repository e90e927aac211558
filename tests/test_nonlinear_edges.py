"""NonlinearSolveLayer at the edges of its contract: where a solve starts at a solution, where the
Jacobian is singular, where a trust region rejects a step, where torch.compile and torch.func meet
the unrolled map, and where a state_dict or a problem's boundary conditions come in another shape.

Each test fails on the behaviour it guards against: a zero unrolled gradient, MUMPS's tiny finite
"solution" of a singular system marked ok, a residual history one entry too long, a DOLFINx call
traced by dynamo, a cap moved by a refused state.
"""
from __future__ import annotations

import time

from mpi4py import MPI
import dolfinx.mesh
import numpy as np
import pytest
import torch

from fempdl import NewtonOptions, NonlinearProblem, NonlinearSolveLayer, SolverFailedError, SolverWarning, forms

F64 = torch.float64
LU = NewtonOptions(rtol=1e-12, atol=1e-14, ksp="lu")


@pytest.fixture(scope="module")
def prob():
    """-div(kappa (1 + u^2) grad u) = f on a 6 x 6 square, u = 0 on the boundary; controls f and kappa."""
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 6, 6)
    prob = forms.nonlinear_diffusion.problem(msh, controls=("f", "kappa"))
    prob.positive = ()          # kappa = 0 on purpose: Newton's singular-Jacobian failure
    return prob


def inputs(prob, f: float = 10.0):
    n = prob.control_size("f")
    return torch.full((n,), f, dtype=F64), torch.ones(n, dtype=F64)


def weights(prob) -> torch.Tensor:
    return torch.linspace(-1.0, 1.0, prob.output_size, dtype=F64)


def central_difference(fn, x: torch.Tensor, direction: torch.Tensor, h: float = 1e-5) -> float:
    with torch.no_grad():
        return float((fn(x + h * direction) - fn(x - h * direction)) / (2 * h))


# ------------------------------------------------------------------ a start at the solution
@pytest.mark.parametrize("start", ["zero source", "warm start at the solution"])
def test_unrolled_gradient_from_a_solution_is_the_derivative_of_the_map(prob, start):
    """From a solution Newton's tolerance holds before any step, but the map is not the identity nearby:
    any change of f moves the solution. The unrolled layer takes one step there, whose derivative is
    the implicit one (-J^-1 dF/df at the solution), and it matches central differences."""
    f, kappa = inputs(prob, 0.0 if start == "zero source" else 10.0)
    guess = None
    if start != "zero source":
        guess = NonlinearSolveLayer(prob, LU)(f=f, kappa=kappa).detach()
    w = weights(prob)
    grads = {}
    for diff in ("unrolled", "implicit"):
        layer = NonlinearSolveLayer(prob, LU, diff=diff)
        x = f.clone().requires_grad_()
        (layer(f=x, kappa=kappa, initial_guess=guess) * w).sum().backward()
        grads[diff] = x.grad
        if diff == "unrolled":
            assert layer.stats.last_newton.steps == 1

            def loss(y, layer=layer):   # the unrolled layer, bound now: the loop rebinds `layer`
                return (layer(f=y, kappa=kappa, initial_guess=guess) * w).sum()
    assert grads["unrolled"].norm() > 1e-3
    np.testing.assert_allclose(grads["unrolled"], grads["implicit"], rtol=1e-9, atol=1e-14)
    direction = torch.sin(torch.arange(len(f), dtype=F64))
    fd = central_difference(loss, f, direction)
    assert abs(float(grads["unrolled"] @ direction) - fd) <= 1e-6 * abs(fd)


def test_an_implicit_solve_from_a_solution_takes_no_step(prob):
    f, kappa = inputs(prob)
    layer = NonlinearSolveLayer(prob, LU)
    solution = layer(f=f, kappa=kappa)
    layer(f=f, kappa=kappa, initial_guess=solution)
    assert layer.stats.last_newton.steps == 0 and layer.stats.last_newton.ok


# ------------------------------------------------------------------ a singular Jacobian
@pytest.mark.parametrize("max_it", [2, None])
def test_a_singular_jacobian_stops_newton_naming_the_control(prob, max_it):
    """kappa = 0 empties J's interior rows: MUMPS would return a tiny finite step and the capped solve
    would look fine. Newton stops there as a named failure (f is not in J, so only kappa is named),
    raised or warned like any other."""
    f, _ = inputs(prob)
    layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu", max_it=max_it))
    with pytest.raises(SolverFailedError, match=r"met a Jacobian it cannot solve with \(25 empty rows \(it is "
                                                r"singular\), controls \['kappa'\]\): SNES reason "
                                                r"DIVERGED_JACOBIAN_DOMAIN after 0 step"):
        layer(f=f, kappa=torch.zeros_like(f))
    assert layer.stats.newton_failures == 1
    # The layer still solves afterwards (PETSc >= 3.2x leaves the failed solve's vectors locked).
    assert layer(f=f, kappa=torch.ones_like(f)).abs().max() > 0.1
    warn = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu", max_it=max_it, on_failure="warn"))
    with pytest.warns(SolverWarning, match="DIVERGED_JACOBIAN_DOMAIN"):
        u = warn(f=f, kappa=torch.zeros_like(f))
    assert torch.all(u == 0)                # the iterate: the zero start, boundary values 0
    layer.close()
    warn.close()


def test_a_jacobian_singular_at_the_start_only_is_a_newton_failure_not_a_coefficient_error():
    """q(u) = u^2 from zero: J(0) has no interior entries though every coefficient is fine. The message
    names the degenerate start; a start away from zero converges."""
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 6, 6)
    prob = forms.nonlinear_diffusion.problem(msh, controls=("f",), q=lambda u: u ** 2)
    f = torch.full((prob.control_size("f"),), 1.0, dtype=F64)
    layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"))
    with pytest.raises(SolverFailedError, match=r"q\(u\) that vanishes at the initial guess"):
        layer(f=f)
    X = prob.dof_coordinates()
    guess = torch.from_numpy(0.5 + 0.0 * X[:, 0])
    u = layer(f=f, initial_guess=guess)
    assert layer.stats.last_newton.ok and torch.isfinite(u).all()
    layer.close()


def test_a_jacobian_names_only_the_controls_it_depends_on(prob):
    assert prob.jacobian_controls == {"kappa"}


# ------------------------------------------------------------------ a trust region's rejected step
def test_a_trust_regions_residual_history_has_one_entry_per_step(prob):
    f, kappa = inputs(prob)
    layer = NonlinearSolveLayer(prob, NewtonOptions(snes_type="newtontr", ksp="lu", max_it=12))
    layer(f=f, kappa=kappa)
    last = layer.stats.last_newton
    assert last.ok and len(last.residual_norms) == last.steps + 1


# ------------------------------------------------------------------ torch.compile, torch.func
def test_an_unrolled_layer_under_torch_compile_runs_eagerly_with_the_same_gradient(prob):
    f, kappa = inputs(prob)
    layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu", max_it=3), diff="unrolled")
    w = weights(prob)

    def loss(x):
        return (layer(f=x, kappa=kappa) * w).sum()
    grads = []
    for fn in (loss, torch.compile(loss)):
        x = f.clone().requires_grad_()
        fn(x).backward()
        grads.append(x.grad)
    torch.testing.assert_close(grads[0], grads[1], rtol=0, atol=0)


def test_an_unrolled_layer_refuses_torch_func_with_a_clear_error(prob):
    f, kappa = inputs(prob)
    layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu", max_it=2), diff="unrolled")
    for transform in (torch.func.grad, torch.func.jacrev):
        with pytest.raises(RuntimeError, match="does not compose with torch.func"):
            transform(lambda x: layer(f=x, kappa=kappa).sum())(f)


def test_a_hessian_through_a_newton_layer_stops_at_forward_mode(prob):
    f, kappa = inputs(prob)
    layer = NonlinearSolveLayer(prob, LU)
    with pytest.raises(NotImplementedError, match="jvp function .* forward mode AD"):
        torch.func.hessian(lambda x: (layer(f=x, kappa=kappa) ** 2).sum())(f)


# ------------------------------------------------------------------ state and inputs in other shapes
def test_a_refused_state_leaves_both_caps_as_they_were(prob):
    for ksp, refusal in (("gmres", "exact Newton step"), ("lu", "no effect with ksp_type='preonly'")):
        layer = NonlinearSolveLayer(prob, NewtonOptions(ksp=ksp, max_it=2), diff="unrolled")
        with pytest.raises(ValueError, match=refusal):
            layer.load_state_dict({"_extra_state": {"max_it": 5, "inner_max_it": 3}})
        assert layer.max_it == 2 and layer.inner_max_it is None
        layer.load_state_dict({"_extra_state": {"max_it": 5, "inner_max_it": None}})
        assert layer.max_it == 5
        layer.close()


def test_one_dirichlet_condition_may_be_given_bare(prob):
    bare = NonlinearProblem(prob.F, prob.u, prob.bcs[0], controls={"f": prob.control("f")})
    assert len(bare.bcs) == 1 and np.array_equal(bare.bc_dofs, prob.bc_dofs)
    with pytest.raises(TypeError, match="bcs must be a list of dolfinx.fem.dirichletbc, got float"):
        NonlinearProblem(prob.F, prob.u, 0.0, controls={"f": prob.control("f")})


def test_an_unrolled_forward_counts_its_time_once(prob):
    """The layer's own time is what a run's time split subtracts from a step: counted twice, the
    network's share went negative."""
    f, kappa = inputs(prob)
    layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu", max_it=4), diff="unrolled")
    layer(f=f, kappa=kappa)
    before = layer.stats.layer_time
    t0 = time.perf_counter()
    layer(f=f.expand(8, -1), kappa=kappa)
    wall = time.perf_counter() - t0
    assert 0 < layer.stats.layer_time - before <= wall


@pytest.fixture(scope="module")
def beam():
    """A neo-Hookean beam [0, 4] x [0, 1] clamped at x = 0, pulled by a traction T; controls T and E."""
    msh = dolfinx.mesh.create_rectangle(MPI.COMM_WORLD, [np.array([0.0, 0.0]), np.array([4.0, 1.0])], [12, 3])
    return forms.hyperelasticity.problem(msh, controls=("T", "E"))


def pull(beam, down: float) -> torch.Tensor:
    T = torch.zeros(beam.control_size("T"), dtype=F64)
    T[1::2] = down
    return T


@pytest.mark.parametrize("diff", ["implicit", "unrolled"])
def test_a_warned_newton_failure_returns_its_last_finite_iterate_and_the_layer_recovers(beam, diff):
    """A traction that inverts elements in Newton's first step makes F NaN there. Warned, the layer
    returns the last iterate whose residual was finite (the start), on every PETSc (3.18 returned the
    step that made F NaN); its backward names the state; and the next sane call gives what a fresh
    layer gives, forward and backward."""
    E = torch.ones(beam.control_size("E"), dtype=F64)

    def forward_backward(layer, T):
        e = E.clone().requires_grad_(True)
        u = layer(T=T, E=e)
        (u * torch.linspace(-1.0, 1.0, u.shape[-1], dtype=F64)).sum().backward()
        return u.detach(), e.grad

    options = NewtonOptions(ksp="lu", on_failure="warn", max_it=None if diff == "implicit" else 8)
    layer = NonlinearSolveLayer(beam, options, diff=diff)
    with pytest.warns(SolverWarning, match="Newton"):
        u = layer(T=pull(beam, -5.0), E=E)
    last = layer.stats.last_newton
    assert not last.ok and len(last.residual_norms) == 1 and np.isfinite(last.residual_norms[0])
    assert torch.equal(u, torch.zeros_like(u))                  # the start: its residual is the last finite one
    with pytest.warns(SolverWarning):
        bad = layer(T=pull(beam, -5.0), E=E.clone().requires_grad_(True))
    bad.sum().backward()                           # at the start F is defined: a gradient, no error
    sane = pull(beam, -0.01)
    fresh = NonlinearSolveLayer(beam, NewtonOptions(ksp="lu", max_it=options.max_it), diff=diff)
    for got, want in zip(forward_backward(layer, sane), forward_backward(fresh, sane)):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-14)
    layer.close()
    fresh.close()


def test_a_symmetric_factorisation_of_a_newton_jacobian_is_refused_with_the_preset_to_use(prob):
    with pytest.raises(ValueError, match="a NonlinearProblem's Jacobian is solved as a general matrix; use the 'lu'"):
        NonlinearSolveLayer(prob, NewtonOptions(ksp="cholesky"))
