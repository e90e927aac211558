"""NonlinearSolveLayer: Newton solves of F(u; m) = 0 as differentiable layers (DESIGN.md, "Nonlinear problems").

What is checked, against numbers the mathematics fixes:

* forward: the layer's converged solve is DOLFINx's own Newton solve (NewtonSolver) of the same
  residual, to 1e-10; plain Newton converges quadratically (a Picard Jacobian, linearly, to the same
  solution); P1 and P2 converge at rates 2 and 3 in L2 to a manufactured solution;
* gradients: float64 gradcheck of the converged (implicit) map and of the capped plain-Newton map
  (unrolled: controls and warm start), central differences; the implicit gradient of a capped Newton
  is not the capped map's derivative, but both agree with the exact one at convergence;
* caps: exactly N Newton steps, exactly K inner iterations per step, counted per sample;
* failures name SNES's reason (or warn and return the iterate); bad inputs are refused clearly;
* batching, shared controls, state_dict, torch.func, and a 2-rank mesh (tests/mpi/newton_layer.py).

"""
from __future__ import annotations

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
from test_mpi import mpirun

from fempdl import (
    KSPOptions,
    NewtonOptions,
    NonlinearProblem,
    NonlinearSolveLayer,
    SolverFailedError,
    SolverWarning,
    forms,
)
from fempdl.core import _dolfinx

COMM = MPI.COMM_WORLD
F64 = torch.float64
# Converged plain Newton (NewtonOptions' default), to a residual 1e-12 relative: with quadratic
# convergence the last step lands far below that, so solutions are exact to ~||J^-1|| * 1e-12.
CONVERGED = NewtonOptions(rtol=1e-12, atol=1e-14, ksp="lu")
PLAIN = NewtonOptions(snes_type="newton", rtol=1e-12, atol=1e-14, ksp="lu")


def capped(n: int, snes_type: str = "newton", ksp="lu") -> NewtonOptions:
    return NewtonOptions(snes_type=snes_type, max_it=n, ksp=ksp)


# ------------------------------------------------------------------ problems and inputs
def g_bc(x):
    """Nonzero Dirichlet data: the residual's lifting and the BC rows of every solve matter."""
    return 0.3 * x[0] - 0.2 * x[1] ** 2


def kappa_fn(x):
    return 1.0 + 0.3 * np.sin(np.pi * x[0]) * np.cos(np.pi * x[1])


def build(msh, controls=("f", "alpha"), **kw):
    return forms.nonlinear_diffusion.problem(msh, controls=controls, kappa=kappa_fn, g=g_bc, **kw)


def values(prob, name: str, batch: int | None = None, seed: int = 0) -> torch.Tensor:
    """Smooth-plus-noise control values: f ~ 10 (u ~ 0.6, so q = 1 + alpha u^2 is far from 1),
    alpha in [1, 1.6], kappa in [0.8, 1.5], u0 ~ 0.3; (batch, n) or, for batch=None, (n,)."""
    X = prob.dof_coordinates(name)
    base = {"f": 10.0 + 3.0 * np.sin(2 * X[:, 0]) * np.cos(3 * X[:, 1]),
            "alpha": 1.0 + 0.4 * X[:, 0] * X[:, 1],
            "kappa": 1.0 + 0.3 * X[:, 0] - 0.2 * X[:, 1],
            "u0": 0.3 * np.sin(np.pi * X[:, 0])}[name]
    gen = torch.Generator().manual_seed(seed)
    noise = torch.rand(batch or 1, len(base), generator=gen, dtype=F64)
    scale = {"f": 2.0, "alpha": 0.2, "kappa": 0.2, "u0": 0.1}[name]
    out = torch.from_numpy(base) + scale * noise
    return out if batch is not None else out[0]


def guess_values(prob, batch: int | None = None, seed: int = 0) -> torch.Tensor:
    """A warm start near (but not at) the solution."""
    X = prob.dof_coordinates()
    gen = torch.Generator().manual_seed(seed)
    base = torch.from_numpy(0.5 * np.sin(np.pi * X[:, 0]) * np.sin(np.pi * X[:, 1]))
    out = base + 0.1 * torch.rand(batch or 1, len(base), generator=gen, dtype=F64)
    return out if batch is not None else out[0]


def rel(a, b) -> float:
    """max |a - b| / max |b|."""
    a, b = (np.asarray(x.detach() if isinstance(x, torch.Tensor) else x) for x in (a, b))
    return float(np.abs(a - b).max() / np.abs(b).max())


@pytest.fixture(scope="module")
def square4():
    """25 P1 DOFs: full float64 gradcheck stays cheap."""
    return dolfinx.mesh.create_unit_square(COMM, 4, 4)


@pytest.fixture(scope="module")
def square8():
    return dolfinx.mesh.create_unit_square(COMM, 8, 8)


@pytest.fixture(scope="module")
def prob4(square4):
    return build(square4)


@pytest.fixture(scope="module")
def prob8(square8):
    return build(square8)


# Gradient variants on the 4x4 mesh: the steady problem, alpha on DG0 (a control space other than u's),
# one time step (u0 enters only F, kappa also J).
VARIANTS = {
    "steady": ({}, ("f", "alpha")),
    "dg0-alpha": ({"alpha_space": "DG0"}, ("f", "alpha")),
    "time-step": ({"dt": 0.05}, ("f", "kappa", "u0")),
}


@pytest.fixture(scope="module")
def variants(square4, prob4):
    return {name: prob4 if name == "steady" else build(square4, controls=controls, **kw)
            for name, (kw, controls) in VARIANTS.items()}


# ------------------------------------------------------------------ 1. forward = DOLFINx's Newton
def dolfinx_newton(F, u, bcs) -> int:
    """DOLFINx's own Newton solve of F(u) = 0 into u (LU steps, to a residual 1e-12 relative).
    0.5.2: fem.petsc.NonlinearProblem + nls.petsc.NewtonSolver; 0.10+: the same solver on
    fem.petsc.NewtonSolverNonlinearProblem (NonlinearProblem became the SNES-based class)."""
    petsc = dolfinx.fem.petsc
    problem_class = getattr(petsc, "NewtonSolverNonlinearProblem", None) or petsc.NonlinearProblem
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)      # 0.10+ deprecate NewtonSolver
        problem = problem_class(F, u, bcs=list(bcs))
        solver = dolfinx.nls.petsc.NewtonSolver(u.function_space.mesh.comm, problem)
    solver.convergence_criterion = "residual"
    solver.rtol, solver.atol, solver.max_it = 1e-12, 1e-14, 30
    ksp = solver.krylov_solver
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    steps, converged = solver.solve(u)
    assert converged
    return int(steps)


FORWARD_CASES = {
    "p1": ({}, ("f", "alpha")),
    "p2": ({"degree": 2}, ("f", "alpha")),
    "time-step": ({"dt": 0.05}, ("f", "alpha", "u0")),
}


@pytest.mark.parametrize("case", sorted(FORWARD_CASES))
def test_forward_equals_dolfinx_newton(square8, case):
    kw, controls = FORWARD_CASES[case]
    prob = build(square8, controls=controls, **kw)
    inputs = {name: values(prob, name, seed=i) for i, name in enumerate(controls)}
    layer = NonlinearSolveLayer(prob, CONVERGED)
    u = layer(**inputs)
    assert layer.stats.last_newton.ok and layer.stats.last_newton.reason > 0
    # The same residual form, its controls set to the layer's inputs, on a fresh unknown.
    for name, value in inputs.items():
        fn = prob.control(name)
        fn.x.array[:prob.control_size(name)] = value.numpy()
        fn.x.scatter_forward()
    u_ref = dolfinx.fem.Function(prob.V)
    steps = dolfinx_newton(ufl.replace(prob.F, {prob.u: u_ref}), u_ref, prob.bcs)
    assert steps >= 3                                             # a genuinely nonlinear solve
    reference = u_ref.x.array[:prob.output_size]
    assert rel(u, reference) <= 1e-10
    g = prob.interpolate(g_bc)
    # The boundary values are g exactly: BC rows of J are identity rows with zeroed columns,
    # so every step leaves u = g there
    np.testing.assert_array_equal(u.numpy()[prob.bc_dofs], g[prob.bc_dofs])
    layer.close()


# ------------------------------------------------------------------ 2. quadratic convergence
def convergence_orders(norms) -> np.ndarray:
    """p_k = log(r_{k+1} / r_k) / log(r_k / r_{k-1}) over the steps in the asymptotic range
    (r_k below 5e-2 r_0) and above round-off (r_{k+1} > 1e-14 r_0)."""
    r = np.array(norms)
    return np.array([np.log(r[k + 1] / r[k]) / np.log(r[k] / r[k - 1]) for k in range(1, len(r) - 1)
                     if r[k] < 5e-2 * r[0] and r[k + 1] > 1e-14 * r[0]])


def picard_problem(prob) -> NonlinearProblem:
    """``prob``'s residual (nonlinear diffusion) with the Picard Jacobian kappa q(u) grad du . grad v
    (q(u) frozen) instead of dF/du."""
    fns = {n: prob.control(n) for n in ("f", "alpha")}
    v, du = ufl.TestFunction(prob.V), ufl.TrialFunction(prob.V)
    kappa = [c for c in prob.F.coefficients() if c.name == "kappa"][0]
    J = kappa * (1 + fns["alpha"] * prob.u ** 2) * ufl.inner(ufl.grad(du), ufl.grad(v)) * ufl.dx
    return NonlinearProblem(prob.F, prob.u, prob.bcs, controls=fns, J=J)


def test_plain_newton_converges_quadratically_and_picard_linearly_to_the_same_solution(prob8):
    f, alpha = values(prob8, "f"), values(prob8, "alpha")
    newton = NonlinearSolveLayer(prob8, PLAIN)
    u = newton(f=f, alpha=alpha)
    norms = newton.stats.last_newton.residual_norms
    assert len(norms) == newton.stats.last_newton.steps + 1
    assert norms[-1] <= 1e-12 * norms[0]
    orders = convergence_orders(norms)
    assert len(orders) >= 2 and np.all(orders > 1.8), (norms, orders)
    # r_{k+1} <= C r_k^2 with one moderate C over all steps above round-off.
    r = np.array(norms)
    above = r[1:] > 1e-14 * r[0]
    ratios = r[1:][above] / r[:-1][above] ** 2
    assert len(ratios) >= 4 and ratios.max() < 1.0, ratios

    # The same residual with a Picard Jacobian (q(u) frozen): a different iteration, linear
    # convergence, the same solution.
    layer = NonlinearSolveLayer(picard_problem(prob8), PLAIN)
    u_picard = layer(f=f, alpha=alpha)
    p_norms = layer.stats.last_newton.residual_norms
    p_orders = convergence_orders(p_norms)
    assert layer.stats.last_newton.steps > 2 * newton.stats.last_newton.steps
    assert len(p_orders) >= 3 and np.all(np.abs(p_orders - 1) < 0.2), (p_norms, p_orders)
    assert rel(u_picard, u) <= 1e-10
    newton.close()
    layer.close()


# ------------------------------------------------------------------ 3. manufactured solutions
def u_exact(x, m):
    """A smooth solution with nonzero boundary values; ``m`` is numpy or ufl."""
    return 0.5 + m.sin(np.pi * x[0]) * m.cos(0.75 * np.pi * x[1]) + 0.25 * x[0] * x[1]


def interpolate_ufl(V, expr) -> np.ndarray:
    """Owned values of the interpolant in V of a UFL expression."""
    points = V.element.interpolation_points
    fn = dolfinx.fem.Function(V)
    fn.interpolate(dolfinx.fem.Expression(expr, points() if callable(points) else points))
    return fn.x.array[:V.dofmap.index_map.size_local].copy()


def mms_errors(degree: int, sizes) -> list[float]:
    errors = []
    for n in sizes:
        msh = dolfinx.mesh.create_unit_square(COMM, n, n)
        prob = forms.nonlinear_diffusion.problem(msh, controls=("f",), degree=degree, kappa=1.0, alpha=1.0,
                                                 g=lambda x: u_exact(x, np))
        x = ufl.SpatialCoordinate(msh)
        ue = u_exact(x, ufl)
        f = -ufl.div((1 + ue ** 2) * ufl.grad(ue))              # f from u_exact, in UFL
        layer = NonlinearSolveLayer(prob, CONVERGED)
        u = layer(f=torch.from_numpy(interpolate_ufl(prob.V, f)))
        e = prob.to_function(u) - ue
        form = dolfinx.fem.form(e ** 2 * ufl.dx(metadata={"quadrature_degree": 2 * degree + 4}))
        errors.append(np.sqrt(COMM.allreduce(dolfinx.fem.assemble_scalar(form), op=MPI.SUM)))
        layer.close()
    return errors


@pytest.mark.parametrize("degree,sizes,rate", [(1, (8, 16, 32), 2.0), (2, (4, 8, 16), 3.0)])
def test_manufactured_solution_converges_at_the_element_rate(degree, sizes, rate):
    errors = mms_errors(degree, sizes)
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(np.abs(rates - rate) < 0.2), (errors, rates)
    assert errors[-1] < {1: 1e-3, 2: 1e-4}[degree], errors


# ------------------------------------------------------------------ 4. gradients
@pytest.mark.parametrize("variant,control", [(v, c) for v, (_, cs) in VARIANTS.items() for c in cs
                                               if (v, c) != ("dg0-alpha", "f")])
def test_gradcheck_implicit_at_convergence(variants, variant, control):
    """Converged Newton: the implicit gradient is the exact derivative of the discrete solution."""
    prob = variants[variant]
    layer = NonlinearSolveLayer(prob, CONVERGED)
    fixed = {name: values(prob, name, seed=5) for name in prob.control_names if name != control}
    m = values(prob, control, batch=2).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: layer(**{control: x}, **fixed), (m,), eps=1e-6, atol=1e-7, rtol=1e-5)
    assert layer.stats.backward_solves > 0 and layer.stats.newton_failures == 0
    layer.close()


@pytest.mark.parametrize("variant,steps,damping", [("steady", 2, 1.0), ("steady", 3, 1.0), ("steady", 3, 0.5),
                                                   ("time-step", 2, 1.0)])
def test_gradcheck_unrolled_capped_map(variants, variant, steps, damping):
    """The unrolled gradient is the derivative of the N-step (damped) Newton map itself, for every control
    and the warm start."""
    prob = variants[variant]
    layer = NonlinearSolveLayer(prob, NewtonOptions(snes_type="newton", max_it=steps, damping=damping, ksp="lu"),
                                diff="unrolled")
    names = prob.control_names
    inputs = [values(prob, name, batch=2, seed=i).requires_grad_() for i, name in enumerate(names)]
    inputs.append(guess_values(prob, batch=2).requires_grad_())
    assert torch.autograd.gradcheck(lambda *x: layer(**dict(zip(names, x)), initial_guess=x[-1]), tuple(inputs),
                                    eps=1e-6, atol=1e-7, rtol=1e-5)
    assert layer.stats.last_newton.steps == steps and layer.stats.last_newton.capped
    layer.close()


def test_unrolled_warm_start_gradient_is_zero_on_the_boundary_and_not_elsewhere(prob4):
    layer = NonlinearSolveLayer(prob4, capped(2), diff="unrolled")
    guess = guess_values(prob4).requires_grad_()
    w = torch.linspace(-1, 1, prob4.output_size, dtype=F64)
    (layer(f=values(prob4, "f"), alpha=values(prob4, "alpha"), initial_guess=guess) * w).sum().backward()
    assert torch.all(guess.grad[prob4.bc_dofs] == 0)
    interior = np.setdiff1d(np.arange(prob4.output_size), prob4.bc_dofs)
    assert guess.grad[interior].abs().max() > 1e-4
    layer.close()


def central_difference(fn, x, dx, h):
    with torch.no_grad():
        return (float(fn(x + h * dx)) - float(fn(x - h * dx))) / (2 * h)


def directional(layer_fn, prob, control, w, seed=3):
    """(gradient . dx, central difference) of J(m) = sum(w * u(m)) along a random direction dx."""
    m = values(prob, control, seed=seed).requires_grad_()
    (layer_fn(m) * w).sum().backward()
    dx = torch.rand(m.shape, generator=torch.Generator().manual_seed(seed + 1), dtype=F64) - 0.5
    fd = central_difference(lambda x: (layer_fn(x) * w).sum(), m.detach(), dx, 1e-4)
    return float((m.grad * dx).sum()), fd


@pytest.mark.parametrize("control", ["f", "alpha"])
def test_central_differences_on_a_finer_mesh(prob8, control):
    """Implicit (converged) and unrolled (capped) gradients along a direction equal central differences of
    their maps (step 1e-4: truncation ~1e-8, round-off ~1e-12 / 1e-4)."""
    w = torch.from_numpy(prob8.dof_coordinates()[:, 0] + 0.5)
    other = {"alpha": values(prob8, "alpha", seed=9)} if control == "f" else {"f": values(prob8, "f", seed=9)}
    for options, diff in ((CONVERGED, "implicit"), (capped(2), "unrolled")):
        layer = NonlinearSolveLayer(prob8, options, diff=diff)
        slope, fd = directional(lambda x, layer=layer: layer(**{control: x}, **other), prob8, control, w)
        assert abs(fd) > 1e-3
        assert abs(slope - fd) <= 1e-6 * abs(fd), (diff, slope, fd)
        layer.close()


def gradient(layer, prob, w, **inputs):
    f = inputs.pop("f").clone().requires_grad_()
    alpha = inputs.pop("alpha").clone().requires_grad_()
    (layer(f=f, alpha=alpha, **inputs) * w).sum().backward()
    return f.grad, alpha.grad


def test_capped_implicit_gradient_is_an_approximation_and_agrees_with_unrolled_at_convergence(prob8):
    f, alpha = values(prob8, "f"), values(prob8, "alpha")
    w = torch.from_numpy(np.cos(3 * prob8.dof_coordinates()[:, 1]))
    exact = gradient(NonlinearSolveLayer(prob8, CONVERGED), prob8, w, f=f, alpha=alpha)
    # Capped at 2 steps: the implicit gradient (evaluated at the iterate) is not the derivative of the capped
    # map, which the unrolled one is (checked by central differences of the capped map).
    implicit2 = NonlinearSolveLayer(prob8, capped(2))
    unrolled2 = NonlinearSolveLayer(prob8, capped(2), diff="unrolled")
    gi, gu = gradient(implicit2, prob8, w, f=f, alpha=alpha), gradient(unrolled2, prob8, w, f=f, alpha=alpha)
    for a, b in zip(gi, gu):
        assert rel(a, b) > 1e-3
    da = torch.rand(alpha.shape, generator=torch.Generator().manual_seed(2), dtype=F64) - 0.5
    fd = central_difference(lambda x: (unrolled2(f=f, alpha=x) * w).sum(), alpha, da, 1e-4)
    assert abs(float((gu[1] * da).sum()) - fd) <= 1e-6 * abs(fd)
    assert abs(float((gi[1] * da).sum()) - fd) > 1e-3 * abs(fd)
    # Both approximate the exact gradient, and at convergence both are it: the Newton map's derivative
    # in u vanishes at the solution, so the unrolled gradient converges with the iterates.
    errors = {}
    for steps in (2, 3, 6):
        for diff in ("implicit", "unrolled"):
            g = gradient(NonlinearSolveLayer(prob8, capped(steps), diff=diff), prob8, w, f=f, alpha=alpha)
            errors[diff, steps] = max(rel(a, b) for a, b in zip(g, exact))
    for diff in ("implicit", "unrolled"):
        assert errors[diff, 2] > 1e-4 and errors[diff, 3] < errors[diff, 2], errors
        assert errors[diff, 6] <= 1e-10, errors
    converged_unrolled = gradient(NonlinearSolveLayer(prob8, PLAIN, diff="unrolled"), prob8, w, f=f, alpha=alpha)
    for a, b in zip(converged_unrolled, exact):
        assert rel(a, b) <= 1e-10


def test_implicit_gradient_of_the_warm_start_is_zero(prob8):
    f, alpha = values(prob8, "f"), values(prob8, "alpha")
    layer = NonlinearSolveLayer(prob8, CONVERGED)
    guess = guess_values(prob8).requires_grad_()
    u = layer(f=f, alpha=alpha, initial_guess=guess)
    (u ** 2).sum().backward()
    assert torch.all(guess.grad == 0)
    assert rel(u, layer(f=f, alpha=alpha)) <= 1e-10           # the solution does not depend on the start
    layer.close()


@pytest.mark.parametrize("diff", ["unrolled", "implicit"])
def test_gradient_with_a_picard_jacobian_is_the_exact_one_at_convergence(prob8, diff):
    """A user J that is not dF/du changes the iteration, not the solution, so not the gradient at
    convergence either: the implicit function theorem needs dF/du, whatever J the iteration used.
    (The unrolled pass differentiates the Picard steps themselves, which converge to it.)"""
    picard = picard_problem(prob8)
    f, alpha = values(prob8, "f"), values(prob8, "alpha")
    w = torch.linspace(-1, 1, prob8.output_size, dtype=F64)
    exact = gradient(NonlinearSolveLayer(prob8, CONVERGED), prob8, w, f=f, alpha=alpha)
    layer = NonlinearSolveLayer(picard, PLAIN, diff=diff)
    got = gradient(layer, prob8, w, f=f, alpha=alpha)
    assert layer.stats.last_newton.steps >= 8            # the (linearly convergent) Picard iteration ran
    for a, b in zip(got, exact):
        assert rel(a, b) <= 1e-9


# ------------------------------------------------------------------ 5. caps
@pytest.mark.parametrize("snes_type", ["newton", "newtonls"])
def test_capped_newton_runs_exactly_n_steps(prob8, snes_type):
    batch = 3
    f, alpha = values(prob8, "f", batch=batch), values(prob8, "alpha")
    layer = NonlinearSolveLayer(prob8, capped(3, snes_type))
    layer(f=f, alpha=alpha)
    s = layer.stats
    assert s.newton_steps == 3 * batch and s.newton_solves == batch and s.max_newton_steps == 3
    last = s.last_newton
    assert last.steps == 3 and last.capped and last.ok and last.reason_name == "DIVERGED_MAX_IT"
    assert len(last.residual_norms) == 4 and last.residual_norms[-1] > 1e-10 * last.residual_norms[0]
    assert s.forward_solves == 3 * batch and s.forward_iterations == 3 * batch      # one LU solve per step
    # PRDP moves the cap: the next call runs the new number of steps.
    layer.max_it = 4
    layer(f=f, alpha=alpha)
    assert s.newton_steps == 3 * batch + 4 * batch and s.last_newton.steps == 4
    layer.close()


def test_a_capped_line_search_newton_past_convergence_returns_the_solution(prob8):
    """PRDP raises the Newton cap; once it exceeds what Newton needs (5-6 steps here), the capped solve must
    return the converged solution, not raise (plain Newton does: its extra steps are round-off)."""
    f, alpha = values(prob8, "f"), values(prob8, "alpha")
    solution = NonlinearSolveLayer(prob8, CONVERGED)(f=f, alpha=alpha)
    assert rel(NonlinearSolveLayer(prob8, capped(12))(f=f, alpha=alpha), solution) <= 1e-10
    layer = NonlinearSolveLayer(prob8, capped(12, "newtonls"))
    assert rel(layer(f=f, alpha=alpha), solution) <= 1e-10
    assert layer.stats.last_newton.ok


@pytest.mark.parametrize("inner", ["cg", "jacobi"])
def test_capped_inner_solves_run_exactly_k_iterations_per_step(prob8, inner):
    batch, N, K = 2, 3, 4
    f, alpha = values(prob8, "f", batch=batch), values(prob8, "alpha")
    layer = NonlinearSolveLayer(prob8, capped(N, ksp=KSPOptions.preset(inner, max_it=K)))
    layer(f=f.requires_grad_(), alpha=alpha).sum().backward()
    s = layer.stats
    assert s.newton_steps == N * batch
    assert s.forward_solves == N * batch and s.forward_iterations == N * K * batch
    assert s.last_newton.inner_iterations == N * K and s.last_newton.capped
    # The implicit adjoint is one capped transposed solve per sample, at the same cap.
    assert s.backward_solves == batch and s.backward_iterations == K * batch
    # Both caps move; the inner cap in place: the same SNES, KSP and adjoint solver, new tolerances.
    solvers = layer.system._solvers
    handles = (solvers.snes.handle, solvers.ksp.handle, solvers.adjoint.ksp.handle)
    layer.max_it, layer.inner_max_it = 2, 7
    layer(f=f.detach().requires_grad_(), alpha=alpha).sum().backward()
    assert s.newton_steps == N * batch + 2 * batch
    assert s.forward_iterations == N * K * batch + 2 * 7 * batch
    assert s.backward_iterations == K * batch + 7 * batch          # the adjoint's cap moved with it
    assert layer.options.ksp.max_it == 7 and layer.options.max_it == 2
    assert layer.system._solvers is solvers
    assert (solvers.snes.handle, solvers.ksp.handle, solvers.adjoint.ksp.handle) == handles
    assert solvers.ksp.getTolerances()[3] == 7
    # Off the cap (converged inner solves, to the preset's rtol) and back onto one, still in place.
    layer.inner_max_it = None
    converged = layer(f=f.detach(), alpha=alpha)
    assert s.last_newton.inner_iterations > 2 * 7 and solvers.ksp.getTolerances()[0] > 0
    layer.inner_max_it = 3
    layer(f=f.detach(), alpha=alpha)
    assert s.last_newton.inner_iterations == 2 * 3 and layer.system._solvers is solvers
    assert torch.isfinite(converged).all()
    layer.close()


def test_unrolled_backward_runs_one_transposed_solve_per_step(prob4):
    batch, N = 2, 3
    layer = NonlinearSolveLayer(prob4, capped(N), diff="unrolled")
    layer(f=values(prob4, "f", batch=batch).requires_grad_(), alpha=values(prob4, "alpha")).sum().backward()
    s = layer.stats
    assert s.backward_newton_steps == N * batch and s.backward_solves == N * batch
    layer.close()


# ------------------------------------------------------------------ 6. failures
def test_diverging_newton_raises_with_the_snes_reason(square8):
    # alpha < 0: q = 1 + alpha u^2 turns negative where u > 1; plain Newton wanders and never converges.
    prob = build(square8, controls=("f",), alpha=-1.0)
    layer = NonlinearSolveLayer(prob, NewtonOptions(snes_type="newton", ksp="lu"))
    with pytest.raises(SolverFailedError, match=r"Newton \(newton\) did not reach its tolerance: SNES reason "
                                                r"DIVERGED_MAX_IT after 50 step\(s\)") as info:
        layer(f=torch.full((prob.control_size("f"),), 50.0, dtype=F64))
    assert not info.value.stats.ok and info.value.stats.reason < 0
    assert layer.stats.newton_failures == 1
    # With its line search, Newton stalls instead: another reason, named as well.
    ls = NonlinearSolveLayer(prob, NewtonOptions(snes_type="newtonls", ksp="lu"))
    with pytest.raises(SolverFailedError, match=r"SNES reason DIVERGED_(LINE_SEARCH|MAX_IT)"):
        ls(f=torch.full((prob.control_size("f"),), 10.0, dtype=F64))
    layer.close()
    ls.close()


def test_a_large_load_converges_as_dolfinx_newton_does(square8):
    """Far from the solution the residual grows 10^5-fold in plain Newton's first step. PETSc's default
    divergence test (10^4) would stop there; DOLFINx's NewtonSolver goes on and converges, and so must
    the layer, uncapped; capped, it runs its N steps."""
    prob = build(square8, controls=("f",))
    f = torch.full((prob.control_size("f"),), 1e4, dtype=F64)
    layer = NonlinearSolveLayer(prob, CONVERGED)
    u = layer(f=f)
    norms = layer.stats.last_newton.residual_norms
    assert norms[1] > 1e4 * norms[0] and layer.stats.last_newton.reason > 0
    prob.control("f").x.array[:] = 1e4
    u_ref = dolfinx.fem.Function(prob.V)
    dolfinx_newton(ufl.replace(prob.F, {prob.u: u_ref}), u_ref, prob.bcs)
    assert rel(u, u_ref.x.array[:prob.output_size]) <= 1e-10
    capped_layer = NonlinearSolveLayer(prob, capped(3))
    capped_layer(f=f)
    assert capped_layer.stats.last_newton.steps == 3 and capped_layer.stats.last_newton.ok
    layer.close()
    capped_layer.close()


def test_too_few_steps_for_the_tolerance_raise_or_warn_with_the_iterate(prob8):
    f, alpha = values(prob8, "f", batch=2), values(prob8, "alpha")
    strict = NonlinearSolveLayer(prob8, NewtonOptions(snes_type="newton", ksp="lu", converged_max_it=2))
    with pytest.raises(SolverFailedError, match=r"did not reach its tolerance: SNES reason DIVERGED_MAX_IT "
                                                r"after 2 step\(s\)"):
        strict(f=f, alpha=alpha)
    lenient = NonlinearSolveLayer(prob8, NewtonOptions(snes_type="newton", ksp="lu", converged_max_it=2,
                                                       on_failure="warn"))
    with pytest.warns(SolverWarning, match="SNES reason DIVERGED_MAX_IT") as record:
        u = lenient(f=f, alpha=alpha)
    assert len(record) == 2                                        # one per failed sample
    # The iterate returned is the one two plain Newton steps give.
    two_steps = NonlinearSolveLayer(prob8, capped(2))(f=f, alpha=alpha)
    assert rel(u, two_steps) <= 1e-12
    assert rel(u, NonlinearSolveLayer(prob8, CONVERGED)(f=f, alpha=alpha)) > 1e-4


def test_nonfinite_controls_are_refused_before_newton_starts(prob4):
    for diff, options in (("implicit", CONVERGED), ("unrolled", capped(2))):
        layer = NonlinearSolveLayer(prob4, options, diff=diff)
        f = values(prob4, "f")
        f[3] = float("nan")
        with pytest.raises(ValueError, match=r"control 'f' contains 1 NaN/inf value\(s\)"):
            layer(f=f, alpha=values(prob4, "alpha"))
        assert layer.stats.newton_solves == 0
        layer.close()


# ------------------------------------------------------------------ 7. input errors
@pytest.fixture(scope="module")
def parts(square4):
    V = _dolfinx.function_space(square4, "Lagrange", 1)
    u, f, a = (dolfinx.fem.Function(V) for _ in range(3))
    v, w = ufl.TestFunction(V), ufl.TrialFunction(V)
    F = (1 + u ** 2) * ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx - f * v * ufl.dx
    return dict(V=V, u=u, f=f, a=a, v=v, w=w, F=F)


def test_problem_input_errors(parts):
    u, f, a, v, w, F = (parts[k] for k in ("u", "f", "a", "v", "w", "F"))
    with pytest.raises(ValueError, match="F is not a residual in u: u does not appear in F"):
        NonlinearProblem(f * v * ufl.dx, u)
    with pytest.raises(ValueError, match=r"controls\['a'\] does not appear in F"):
        NonlinearProblem(F, u, controls={"f": f, "a": a})
    with pytest.raises(ValueError, match=r"controls\['u'\] is the unknown u itself"):
        NonlinearProblem(F, u, controls={"u": u})
    with pytest.raises(TypeError, match="J must be a bilinear UFL form .* got a form with 1 argument"):
        NonlinearProblem(F, u, J=F)
    with pytest.raises(TypeError, match="F must be a residual: a UFL form with one argument .* 2 argument"):
        NonlinearProblem(ufl.inner(ufl.grad(w), ufl.grad(v)) * ufl.dx, u)
    with pytest.raises(TypeError, match="u must be the unknown dolfinx.fem.Function"):
        NonlinearProblem(F, ufl.TrialFunction(parts["V"]))
    with pytest.raises(ValueError, match="unknown control"):
        NonlinearSolveLayer(NonlinearProblem(F, u, controls={"f": f}), capped(1))(g=torch.zeros(25, dtype=F64))
    with pytest.raises(TypeError, match="a linear fempdl.Problem goes into a SolveLayer"):
        NonlinearSolveLayer(forms.poisson.problem(parts["V"].mesh, controls=("f",)))


@pytest.mark.parametrize("kwargs,error,message", [
    ({"max_it": 0}, ValueError, r"NewtonOptions.max_it must be >= 1"),
    ({"max_it": 2.5}, TypeError, r"NewtonOptions.max_it must be an int"),
    ({"converged_max_it": 0}, ValueError, r"converged_max_it must be >= 1"),
    ({"rtol": 1.5}, ValueError, r"NewtonOptions.rtol must be a number in \[0, 1\)"),
    ({"atol": float("nan")}, ValueError, r"NewtonOptions.atol must be a number"),
    ({"rtol": 0, "atol": 0}, ValueError, r"uncapped Newton solve \(max_it=None\) needs rtol > 0 or atol > 0"),
    ({"snes_type": "picard"}, ValueError, r"snes_type must be one of \['newtonls', 'newtontr', 'newton'\]"),
    ({"linesearch": "quadratic"}, ValueError, r"linesearch must be one of"),
    ({"snes_type": "newtontr", "linesearch": "bt"}, ValueError, r"a line search applies to snes_type='newtonls'"),
    ({"snes_type": "newton", "damping": 0.0}, ValueError, r"damping must be in \(0, 1\]"),
    ({"damping": 0.5, "snes_type": "newtonls"}, ValueError, r"damping applies to plain Newton"),
    ({"linesearch": "bt"}, ValueError, r"a line search applies to snes_type='newtonls', not 'newton'"),
    ({"ksp": 3}, TypeError, r"NewtonOptions.ksp must be KSPOptions, a preset name or None"),
    ({"ksp": "no-such-preset"}, ValueError, r"unknown preset 'no-such-preset'"),
    ({"on_failure": "ignore"}, ValueError, r"on_failure must be 'raise' or 'warn'"),
])
def test_newton_options_refuse_bad_values(kwargs, error, message):
    with pytest.raises(error, match=message):
        NewtonOptions(**kwargs)


def test_newton_options_accept_a_capped_solve_without_tolerances():
    o = NewtonOptions(max_it=3, rtol=0, atol=0, snes_type="newton", damping=0.5)
    assert o.capped and o.plain and o.step_limit == 3
    assert o.snes_tolerances() == dict(rtol=0.0, atol=0.0, stol=0.0, max_it=3)
    assert NewtonOptions(converged_max_it=7).step_limit == 7
    assert NewtonOptions().plain and not NewtonOptions(snes_type="newtonls").plain     # plain Newton is the default


def test_unrolled_refuses_what_it_cannot_differentiate(prob4):
    with pytest.raises(ValueError, match=r"diff='unrolled' differentiates plain Newton steps .* not 'newtonls'"):
        NonlinearSolveLayer(prob4, NewtonOptions(max_it=2, snes_type="newtonls", ksp="lu"), diff="unrolled")
    with pytest.raises(ValueError, match=r"not 'newtonls'"):
        NonlinearSolveLayer(prob4, NewtonOptions(max_it=2, snes_type="newtonls", linesearch="bt", ksp="lu"),
                            diff="unrolled")
    with pytest.raises(ValueError, match=r"not 'newtontr'"):
        NonlinearSolveLayer(prob4, NewtonOptions(max_it=2, snes_type="newtontr", ksp="lu"), diff="unrolled")
    with pytest.raises(ValueError, match=r"needs the exact Newton step: .* not one capped at 5 iterations"):
        NonlinearSolveLayer(prob4, capped(2, ksp=KSPOptions.preset("cg", max_it=5)), diff="unrolled")
    # Moving an unrolled layer's inner cap onto a Krylov solve is refused the same way, and changes nothing.
    layer = NonlinearSolveLayer(prob4, capped(2, ksp=KSPOptions.preset("cg", rtol=1e-13)), diff="unrolled")
    with pytest.raises(ValueError, match="needs the exact Newton step"):
        layer.inner_max_it = 5
    assert layer.inner_max_it is None
    # newtonls with the full-step line search is plain Newton: accepted, and the same map.
    basic = NonlinearSolveLayer(prob4, NewtonOptions(max_it=2, snes_type="newtonls", linesearch="basic", ksp="lu"),
                                diff="unrolled")
    f, alpha = values(prob4, "f"), values(prob4, "alpha")
    assert rel(basic(f=f, alpha=alpha), NonlinearSolveLayer(prob4, capped(2))(f=f, alpha=alpha)) <= 1e-14
    basic.close()
    with pytest.raises(ValueError, match="diff must be one of"):
        NonlinearSolveLayer(prob4, CONVERGED, diff="adjoint")
    with pytest.raises(ValueError, match="max_unrolled_values applies to diff='unrolled'"):
        NonlinearSolveLayer(prob4, CONVERGED, max_unrolled_values=10)
    layer.close()


def test_unrolled_memory_bound_is_checked_before_solving(prob4):
    n = prob4.output_size
    layer = NonlinearSolveLayer(prob4, capped(3), diff="unrolled", max_unrolled_values=4 * 2 * n)
    layer(f=values(prob4, "f", batch=2), alpha=values(prob4, "alpha"))            # (3 + 1) * 2 * n: fits
    with pytest.raises(MemoryError, match=rf"would keep {4 * 3 * n} values"):
        layer(f=values(prob4, "f", batch=3), alpha=values(prob4, "alpha"))
    assert layer.stats.newton_solves == 2
    layer.close()


def test_an_unrolled_memory_budget_in_bytes_is_checked_before_solving(prob4):
    """``memory_budget`` replaces the default budget (half the memory available): 8 bytes per kept value."""
    n = prob4.output_size
    layer = NonlinearSolveLayer(prob4, capped(3), diff="unrolled", memory_budget=8 * 4 * 2 * n)
    layer(f=values(prob4, "f", batch=2), alpha=values(prob4, "alpha"))            # (3 + 1) * 2 * n floats: fits
    with pytest.raises(MemoryError, match=r"would keep .* of iterates for backward .*more than memory_budget"):
        layer(f=values(prob4, "f", batch=3), alpha=values(prob4, "alpha"))
    assert layer.stats.newton_solves == 2 and layer.memory_budget == 8 * 4 * 2 * n
    layer.close()
    with pytest.raises(ValueError, match="memory_budget applies to diff='unrolled' layers"):
        NonlinearSolveLayer(prob4, CONVERGED, memory_budget=10 ** 9)
    with pytest.raises(ValueError, match="memory_budget must be >= 1, got 0"):
        NonlinearSolveLayer(prob4, capped(3), diff="unrolled", memory_budget=0)


@pytest.mark.parametrize("diff,options", [("implicit", CONVERGED), ("unrolled", capped(2))])
def test_second_derivatives_are_refused(prob4, diff, options):
    layer = NonlinearSolveLayer(prob4, options, diff=diff)
    f = values(prob4, "f").requires_grad_()
    alpha = values(prob4, "alpha")
    first, = torch.autograd.grad((layer(f=f, alpha=alpha) ** 2).sum(), f)
    again, = torch.autograd.grad((layer(f=f, alpha=alpha) ** 2).sum(), f, create_graph=True)
    torch.testing.assert_close(again.detach(), first, rtol=0, atol=0)          # first order is unchanged
    with pytest.raises(RuntimeError, match="second derivatives through NonlinearSolveLayer are not implemented"):
        torch.autograd.grad(again.sum(), f)
    layer.close()


# ------------------------------------------------------------------ 8. batching and state
@pytest.mark.parametrize("diff,options", [("implicit", CONVERGED), ("unrolled", capped(3))])
def test_a_batch_equals_single_calls_and_shared_controls_broadcast(prob4, diff, options):
    B = 3
    layer = NonlinearSolveLayer(prob4, options, diff=diff)
    F = values(prob4, "f", batch=B).requires_grad_()
    alpha = values(prob4, "alpha").requires_grad_()                 # (n,): shared by the batch
    w = torch.linspace(0, 1, prob4.output_size, dtype=F64)
    U = layer(f=F, alpha=alpha)
    assert U.shape == (B, prob4.output_size)
    (U * w).sum().backward()
    assert alpha.grad.shape == alpha.shape
    grad_alpha = torch.zeros_like(alpha)
    for i in range(B):
        fi, ai = F[i].detach().clone().requires_grad_(), alpha.detach().clone().requires_grad_()
        ui = layer(f=fi, alpha=ai)
        assert ui.shape == (prob4.output_size,)
        torch.testing.assert_close(ui, U[i].detach(), rtol=1e-13, atol=1e-15)
        (ui * w).sum().backward()
        torch.testing.assert_close(fi.grad, F.grad[i], rtol=1e-12, atol=1e-14)
        grad_alpha += ai.grad
    # A shared control's gradient is the sum over the samples; a broadcast (B, n) copy gives the same.
    torch.testing.assert_close(alpha.grad, grad_alpha, rtol=1e-12, atol=1e-14)
    expanded = alpha.detach().expand(B, -1).clone()
    torch.testing.assert_close(layer(f=F.detach(), alpha=expanded), U.detach(), rtol=1e-13, atol=1e-15)
    assert layer.stats.newton_solves == 3 * B
    layer.close()


def test_state_dict_carries_both_caps(prob4):
    options = capped(3, ksp=KSPOptions.preset("jacobi", max_it=5))
    trained = NonlinearSolveLayer(prob4, options)
    trained.max_it, trained.inner_max_it = 4, 6
    state = trained.state_dict()
    fresh = NonlinearSolveLayer(prob4, options)
    assert (fresh.max_it, fresh.inner_max_it) == (3, 5)
    fresh.load_state_dict(state)
    assert (fresh.max_it, fresh.inner_max_it) == (4, 6)
    fresh(f=values(prob4, "f"), alpha=values(prob4, "alpha"))
    assert fresh.stats.newton_steps == 4 and fresh.stats.forward_iterations == 4 * 6
    # A converged layer's state reloads as converged.
    converged = NonlinearSolveLayer(prob4, NewtonOptions(ksp="lu")).state_dict()
    fresh.load_state_dict(converged)
    assert fresh.max_it is None and fresh.options.capped is False
    with pytest.raises(ValueError, match="NewtonOptions.max_it must be >= 1"):
        fresh.max_it = 0
    for layer in (trained, fresh):
        layer.close()


# ------------------------------------------------------------------ 9. torch.func
def test_torch_func_grad_and_vjp_match_autograd(prob8):
    layer = NonlinearSolveLayer(prob8, CONVERGED)
    f, alpha = values(prob8, "f"), values(prob8, "alpha")
    d = torch.from_numpy(prob8.dof_coordinates()[:, 0])

    def J(f, alpha):
        return 0.5 * ((layer(f=f, alpha=alpha) - d) ** 2).sum()

    gf, ga = torch.func.grad(J, argnums=(0, 1))(f, alpha)
    fr, ar = f.clone().requires_grad_(), alpha.clone().requires_grad_()
    af, aa = torch.autograd.grad(J(fr, ar), (fr, ar))
    torch.testing.assert_close(gf, af, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(ga, aa, rtol=1e-12, atol=1e-14)
    assert gf.abs().max() > 1e-4 and ga.abs().max() > 1e-4
    u, vjp = torch.func.vjp(lambda f, a: layer(f=f, alpha=a), f, alpha)
    vf, va = vjp(u - d)
    torch.testing.assert_close(vf, af, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(va, aa, rtol=1e-12, atol=1e-14)
    layer.close()


def test_torch_compile_matches_eager(prob4):
    layer = NonlinearSolveLayer(prob4, CONVERGED)
    alpha = values(prob4, "alpha")
    torch.manual_seed(0)
    net = torch.nn.Linear(prob4.control_size("f"), prob4.control_size("f")).double()

    def model(x):
        return (layer(f=10.0 + net(x), alpha=alpha) ** 2).sum()

    x = torch.rand(2, prob4.control_size("f"), generator=torch.Generator().manual_seed(1), dtype=F64)
    xe = x.clone().requires_grad_()
    ve = model(xe)
    ge = torch.autograd.grad(ve, (xe, net.weight))
    torch._dynamo.reset()
    compiled = torch.compile(model, fullgraph=True, backend="aot_eager")
    xc = x.clone().requires_grad_()
    vc = compiled(xc)
    gc = torch.autograd.grad(vc, (xc, net.weight))
    torch.testing.assert_close(vc, ve, rtol=1e-12, atol=0)
    for a, b in zip(gc, ge):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    torch._dynamo.reset()
    layer.close()


# ------------------------------------------------------------------ 10. MPI
@pytest.fixture(scope="module")
def mpi_results(tmp_path_factory):
    path = tmp_path_factory.mktemp("mpi-newton") / "results.npz"
    done = mpirun(2, "newton_layer.py", str(path))
    assert done.returncode == 0, done.stderr[-3000:]
    return dict(np.load(path))


def test_distributed_newton_layer_equals_serial(mpi_results):
    sizes = mpi_results["owned_sizes"]
    assert len(sizes) == 2 and sizes.min() > 0.3 * sizes.sum()
    keys = sorted(k[len("serial/"):] for k in mpi_results if k.startswith("serial/"))
    assert {"implicit/u", "implicit/grad_f", "implicit/grad_alpha", "unrolled/grad_initial_guess",
            "capped-cg/grad_f"} <= set(keys)
    # Caps hold on any number of ranks: 2 samples x 3 steps x 6 CG iterations, 2 x 2 unrolled steps.
    assert int(mpi_results["split/capped-cg/newton_steps"]) == 2 * 3
    assert int(mpi_results["split/capped-cg/forward_iterations"]) == 2 * 3 * 6
    assert int(mpi_results["split/unrolled/newton_steps"]) == 2 * 2
    for key in keys:
        a, b = mpi_results["serial/" + key], mpi_results["split/" + key]
        assert a.shape == b.shape, key
        if key.endswith(("newton_steps", "forward_iterations")):
            assert int(a) == int(b), key
            continue
        assert np.abs(a).max() > 1e-6, key
        assert np.abs(a - b).max() <= 1e-10 * np.abs(a).max(), key


def test_ranks_with_different_inner_caps_are_refused_not_hung():
    # A correct refusal takes a few seconds idle, and 20 s was seen with two ranks starting up beside other busy
    # processes on 2 cores; a hang is ended by the timeout.
    done = mpirun(2, "newton_layer.py", "--inner-caps-differ", timeout=180)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "rank 0 refused" in done.stdout and "rank 1 refused" in done.stdout, done.stdout
