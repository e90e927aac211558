"""A torch network inside the weak form (fempdl.Network): exact against the same law in UFL, gradients against
central differences in linear, Newton (implicit and unrolled) and rollout layers, and its refusals."""
from __future__ import annotations

from mpi4py import MPI
import dolfinx
import numpy as np
import pytest
import torch
import ufl

import fempdl
from fempdl import Network, NewtonOptions, NonlinearProblem, NonlinearSolveLayer, Problem, Rollout, SolveLayer
from fempdl.core import _dolfinx

F64 = torch.float64


class Polynomial(torch.nn.Module):
    """kappa(u) = c0 + c1 u^2, its coefficients the parameters."""

    def __init__(self, c0=1.0, c1=4.0):
        super().__init__()
        self.c = torch.nn.Parameter(torch.tensor([c0, c1], dtype=F64))

    def forward(self, u):
        return self.c[0] + self.c[1] * u[:, 0] ** 2


def mlp(inputs=1, width=8, seed=0, dtype=F64):
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(inputs, width), torch.nn.Tanh(), torch.nn.Linear(width, 1),
                               torch.nn.Softplus()).to(dtype)


@pytest.fixture()
def square():
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 6, 6)
    V = _dolfinx.function_space(msh, "Lagrange", 1)
    bc = _dolfinx.dirichlet_bc(V, dolfinx.fem.Constant(msh, 0.0), _dolfinx.boundary_facets(msh))
    return msh, V, bc


def diffusion(square, module, name="kappa", positive=True, **kw):
    """-div(N(u) grad u) = f, N a network of u."""
    msh, V, bc = square
    u, f, v = dolfinx.fem.Function(V), dolfinx.fem.Function(V), ufl.TestFunction(V)
    N = Network(module, (u,), name=name, positive=positive, **kw)
    F = ufl.inner(N * ufl.grad(u), ufl.grad(v)) * ufl.dx - f * v * ufl.dx
    return NonlinearProblem(F, u, [bc], controls={"f": f}), N


def sources(prob, batch=2):
    X = prob.dof_coordinates()
    rows = [10 * np.sin(3 * X[:, 0]) * np.cos(2 * X[:, 1]), 6 + 4 * X[:, 0], 5 * X[:, 1]]
    return torch.tensor(np.stack(rows[:batch]), dtype=F64)


def weights_of(prob, batch=2):
    X = prob.dof_coordinates()
    return torch.tensor(np.stack([np.cos(5 * X[:, 0] + k * X[:, 1]) for k in range(batch)]), dtype=F64)


def directional_fd(loss, params, directions, h=1e-6):
    with torch.no_grad():
        for p, d in zip(params, directions):
            p += h * d
        plus = float(loss())
        for p, d in zip(params, directions):
            p -= 2 * h * d
        minus = float(loss())
        for p, d in zip(params, directions):
            p += h * d
    return (plus - minus) / (2 * h)


def check_parameter_gradient(loss, module, rtol, seed=1):
    """The parameters' gradient from backward against central differences along a random direction."""
    params = list(module.parameters())
    for p in params:
        p.grad = None
    loss().backward()
    gen = torch.Generator().manual_seed(seed)
    directions = [torch.randn(p.shape, generator=gen, dtype=p.dtype) for p in params]
    analytic = float(sum((p.grad * d).sum() for p, d in zip(params, directions)))
    fd = directional_fd(loss, params, directions)
    assert abs(analytic - fd) <= rtol * abs(fd), (analytic, fd)
    return analytic


# ----------------------------------------------------------------- exactness
def test_a_network_computing_the_law_equals_the_ufl_law_and_its_gradient_the_coefficient_controls(square):
    """torch's 1 + 4u^2 at the quadrature points solves as the UFL expression does (same points, LU), and its
    parameters' gradient is that of the law's coefficients as DG0 controls, summed over the cells."""
    prob, _ = diffusion(square, Polynomial())
    layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"))
    msh, V, bc = square
    u, f, v = dolfinx.fem.Function(V), dolfinx.fem.Function(V), ufl.TestFunction(V)
    DG0 = _dolfinx.function_space(msh, "DG", 0)
    c0, c1 = dolfinx.fem.Function(DG0), dolfinx.fem.Function(DG0)
    law = NonlinearProblem(ufl.inner((c0 + c1 * u ** 2) * ufl.grad(u), ufl.grad(v)) * ufl.dx - f * v * ufl.dx, u,
                           [bc], controls={"f": f, "c0": c0, "c1": c1})
    reference = NonlinearSolveLayer(law, NewtonOptions(ksp="lu"))
    fs, w = sources(prob), weights_of(prob)
    n_cells = law.control_size("c0")
    coefficients = [torch.full((n_cells,), value, dtype=F64, requires_grad=True) for value in (1.0, 4.0)]
    ours, theirs = layer(f=fs), reference(f=fs, c0=coefficients[0], c1=coefficients[1])
    assert (ours - theirs).abs().max() <= 1e-12 * theirs.abs().max()
    (ours * w).sum().backward()
    (theirs * w).sum().backward()
    expected = torch.stack([c.grad.sum() for c in coefficients])
    grad = layer.networks["kappa"].c.grad
    assert (grad - expected).abs().max() <= 1e-10 * expected.abs().max()


def test_newton_converges_quadratically_with_the_networks_jacobian(square):
    """The Jacobian holds dN/du from torch autograd: the residual falls quadratically to round-off."""
    prob, _ = diffusion(square, mlp())
    layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu", rtol=1e-14, atol=1e-13))
    layer(f=sources(prob, 1)[0])
    norms = layer.stats.last_newton.residual_norms
    ratios = [b / a ** 2 for a, b in zip(norms, norms[1:]) if a < 1e-2 and b > 1e-13 * norms[0]]
    assert ratios and max(ratios) < 1e3, norms          # r_{k+1} <= C r_k^2 once close
    assert len(norms) <= 8, norms


def test_an_energy_network_gives_its_derivative_as_the_residual_and_its_hessian_as_the_jacobian(square):
    """psi(g) = |g|^2 / 2 + |g|^4 / 4 of g = grad u in torch: fempdl.derivative of its energy equals UFL's
    derivative of the same energy (the residual needs dpsi/dg, the Jacobian the Hessian)."""
    msh, V, bc = square

    class Energy(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.b = torch.nn.Parameter(torch.tensor(1.0, dtype=F64))

        def forward(self, g):
            s = (g ** 2).sum(1)
            return s / 2 + self.b * s ** 2 / 4

    solutions = []
    for use_network in (True, False):
        u, f = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
        g = ufl.grad(u)
        psi = Network(Energy(), (g,), name="psi", degree=4) if use_network else (
            ufl.inner(g, g) / 2 + ufl.inner(g, g) ** 2 / 4)
        energy = psi * ufl.dx(metadata={"quadrature_degree": 4}) - f * u * ufl.dx
        F = fempdl.derivative(energy, u, ufl.TestFunction(V)) if use_network else ufl.derivative(
            energy, u, ufl.TestFunction(V))
        prob = NonlinearProblem(F, u, [bc], controls={"f": f})
        layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"))
        solutions.append(layer(f=sources(prob, 1)[0] * 3))
        assert layer.stats.last_newton.steps <= 8
    assert (solutions[0] - solutions[1]).abs().max() <= 1e-12 * solutions[1].abs().max()


# ------------------------------------------------------------------ gradients
@pytest.mark.parametrize("diff", ["implicit", "unrolled"])
def test_the_weights_and_the_sources_gradients_match_central_differences_through_newton(square, diff):
    """Implicit: the converged solve's gradient; unrolled: the 3-step Newton map's (second derivatives of
    the network through the step's Jacobian)."""
    prob, N = diffusion(square, mlp())
    options = NewtonOptions(ksp="lu") if diff == "implicit" else NewtonOptions(ksp="lu", max_it=3)
    layer = NonlinearSolveLayer(prob, options, diff=diff)
    fs, w = sources(prob).requires_grad_(), weights_of(prob)
    check_parameter_gradient(lambda: (layer(f=fs) * w).sum(), N.module, rtol=1e-7)
    direction = torch.randn(fs.shape, generator=torch.Generator().manual_seed(2), dtype=F64)
    analytic = float((fs.grad * direction).sum())
    fd = directional_fd(lambda: (layer(f=fs) * w).sum(), [fs], [direction])
    assert abs(analytic - fd) <= 1e-7 * abs(fd)


def test_a_network_of_x_and_a_control_in_a_linear_problem_has_exact_gradients(square):
    """a(w, v) = (N(x, m) grad w, grad v): the matrix depends on the weights and on the control m through the
    network; both gradients against central differences."""
    msh, V, bc = square
    w, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    f, m = dolfinx.fem.Function(V), dolfinx.fem.Function(V)

    class OfXAndM(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.net = mlp(inputs=3)

        def forward(self, x, m):
            return self.net(torch.cat([x, m], 1))[:, 0] + 0.1

    N = Network(OfXAndM(), (ufl.SpatialCoordinate(msh), m), name="kappa", positive=True)
    prob = Problem(ufl.inner(N * ufl.grad(w), ufl.grad(v)) * ufl.dx, f * v * ufl.dx, [bc],
                   controls={"f": f, "m": m})
    assert prob.matrix_controls == {"m", "kappa"} and prob.affine_rhs_controls == {"f"}
    layer = SolveLayer(prob)
    with pytest.raises(ValueError, match=r"a network in the form \(\['kappa'\]\) has none of; use diff='implicit'"):
        SolveLayer(prob, "jacobi", diff="unrolled")
    X = prob.dof_coordinates()
    fs = torch.tensor(np.sin(3 * X[:, 0]), dtype=F64)
    ms = torch.tensor(np.stack([X[:, 1], X[:, 0] ** 2]), dtype=F64, requires_grad=True)
    weights = weights_of(prob)
    loss = lambda: (layer(f=fs, m=ms) * weights).sum()  # noqa: E731
    check_parameter_gradient(loss, N.module, rtol=1e-7)
    direction = torch.randn(ms.shape, generator=torch.Generator().manual_seed(4), dtype=F64)
    analytic = float((ms.grad * direction).sum())
    assert abs(analytic - directional_fd(loss, [ms], [direction])) <= 1e-7 * abs(analytic)


@pytest.mark.parametrize("schedule", [None, "autograd", ("revolve", 2)])
def test_a_rollout_with_the_network_in_every_step_has_the_same_exact_gradient_under_every_schedule(square,
                                                                                                   schedule):
    msh, V, bc = square
    u, u0, f = (dolfinx.fem.Function(V) for _ in range(3))
    v = ufl.TestFunction(V)
    dt = dolfinx.fem.Constant(msh, 0.05)
    N = Network(mlp(), (u,), name="kappa", positive=True)
    F = (u - u0) / dt * v * ufl.dx + ufl.inner(N * ufl.grad(u), ufl.grad(v)) * ufl.dx - f * v * ufl.dx
    prob = NonlinearProblem(F, u, [bc], controls={"u0": u0, "f": f}, constants={"dt": dt})
    rollout = Rollout(NonlinearSolveLayer(prob, NewtonOptions(ksp="lu")), state="u0", schedule=schedule)
    X = prob.dof_coordinates()
    initial = torch.tensor(np.sin(np.pi * X[:, 0]) * np.sin(np.pi * X[:, 1]), dtype=F64)
    fs = torch.tensor(5 * X[:, 0], dtype=F64)
    weights = torch.tensor(np.cos(np.arange(5)[:, None] + 4 * X[None, :, 0]), dtype=F64)
    loss = lambda: (rollout(initial, 4, f=fs, constants={"dt": [0.05, 0.1, 0.05, 0.2]}) * weights).sum()  # noqa: E731
    check_parameter_gradient(loss, N.module, rtol=1e-7)


def test_the_backward_uses_the_weights_its_forward_read(square):
    """An optimiser step between forward and backward changes nothing in the gradient of that forward."""
    prob, N = diffusion(square, mlp())
    layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"))
    fs, w = sources(prob), weights_of(prob)
    params = list(N.module.parameters())
    (layer(f=fs) * w).sum().backward()
    expected = [p.grad.clone() for p in params]
    for p in params:
        p.grad = None
    out = layer(f=fs)
    with torch.no_grad():
        for p in params:
            p.mul_(1.1)
    (out * w).sum().backward()
    with torch.no_grad():
        for p in params:
            p.div_(1.1)
    for p, g in zip(params, expected):
        assert torch.allclose(p.grad, g, rtol=1e-12, atol=1e-14)


def test_a_float32_network_solves_with_float64_physics_and_gets_float32_gradients(square):
    """Its weights are cast: the solution is that of the same weights in float64, bit for bit."""
    module32 = mlp(dtype=torch.float32)
    module64 = mlp(dtype=torch.float32).double()
    results = []
    for module in (module32, module64):
        prob, _ = diffusion(square, module)
        layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"))
        out = layer(f=sources(prob))
        (out * weights_of(prob)).sum().backward()
        results.append((out, [p.grad for p in module.parameters()]))
    (u32, g32), (u64, g64) = results
    assert u32.dtype == F64 and torch.equal(u32, u64)
    assert all(a.dtype == torch.float32 for a in g32)
    assert all(torch.allclose(a.double(), b, rtol=1e-6, atol=1e-9) for a, b in zip(g32, g64))


def test_the_layer_holds_the_networks_as_submodules(square):
    prob, N = diffusion(square, mlp())
    layer = NonlinearSolveLayer(prob)
    assert {id(p) for p in layer.parameters()} == {id(p) for p in N.module.parameters()}
    assert prob.networks == {"kappa": N} and prob.control_size("kappa") == N.parameter_count == 8 + 8 + 8 + 1


# ------------------------------------------------------------------- refusals
class Returning(torch.nn.Module):
    def __init__(self, fn):
        super().__init__()
        self.fn = fn
        self.w = torch.nn.Parameter(torch.ones((), dtype=F64))

    def forward(self, u):
        return self.fn(self.w, u)


@pytest.mark.parametrize("fn,message", [
    (lambda w, u: w * torch.full_like(u[:, 0], float("nan")), "NaN/inf value"),
    (lambda w, u: w * torch.ones(u.shape[0], 3, dtype=u.dtype), r"returned shape \(\d+, 3\)"),
    (lambda w, u: w * (u[:, 0] - 1.0), r"must be > 0 \(built with positive=True\)"),
])
def test_a_network_returning_nan_a_wrong_shape_or_a_nonpositive_value_is_refused(square, fn, message):
    prob, _ = diffusion(square, Returning(fn))
    layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"))
    with pytest.raises(ValueError, match=message):
        layer(f=sources(prob, 1)[0])


def test_misplaced_networks_are_refused_with_the_fix(square):
    msh, V, bc = square
    u, f, v = dolfinx.fem.Function(V), dolfinx.fem.Function(V), ufl.TestFunction(V)
    N = Network(mlp(), (u,), name="kappa")
    with pytest.raises(ValueError, match="exterior_facet integral; a network is evaluated at the cells"):
        NonlinearProblem(N * u * v * ufl.ds + ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx, u, [bc])
    with pytest.raises(ValueError, match="quadrature_degree=5, but their values are held at the points of degree 2"):
        NonlinearProblem(ufl.inner(N * ufl.grad(u), ufl.grad(v)) * ufl.dx(metadata={"quadrature_degree": 5}), u, [bc])
    with pytest.raises(TypeError, match="module must be a torch.nn.Module"):
        Network(lambda u: u, (u,))
    with pytest.raises(ValueError, match="name of a control"):
        NonlinearProblem(ufl.inner(N * ufl.grad(u), ufl.grad(v)) * ufl.dx - f * v * ufl.dx, u, [bc],
                         controls={"kappa": f})
    prob = NonlinearProblem(ufl.inner(N * ufl.grad(u), ufl.grad(v)) * ufl.dx - f * v * ufl.dx, u, [bc],
                            controls={"f": f})
    with pytest.raises(ValueError, match="whose parameters the layer passes itself"):
        NonlinearSolveLayer(prob)(f=sources(prob, 1)[0], kappa=torch.zeros(N.parameter_count, dtype=F64))


def test_the_network_as_a_field_is_its_cell_mean_at_a_state_and_writes_to_xdmf(square, tmp_path):
    """field_at: the quadrature mean of 1 + 4u^2 over each cell, which UFL assembles as the same integral."""
    prob, N = diffusion(square, Polynomial())
    msh, V, _ = square
    X = prob.dof_coordinates()
    state = torch.tensor(X[:, 0] + 2 * X[:, 1] ** 2, dtype=F64)
    field = N.field_at(prob, state)
    u = prob.to_function(state)
    q = ufl.TestFunction(field.function_space)
    md = {"quadrature_degree": 2}
    integral = dolfinx.fem.petsc.assemble_vector(dolfinx.fem.form((1 + 4 * u ** 2) * q * ufl.dx(metadata=md)))
    volume = dolfinx.fem.petsc.assemble_vector(dolfinx.fem.form(q * ufl.dx))
    n = msh.topology.index_map(2).size_local
    expected = integral.array[:n] / volume.array[:n]
    assert np.abs(field.x.array[:n] - expected).max() <= 1e-13 * np.abs(expected).max()
    path = fempdl.io.write_xdmf(tmp_path / "kappa.xdmf", {"kappa": field})
    assert path.exists() and path.with_suffix(".h5").stat().st_size > 0


def test_a_capped_newton_layers_implicit_gradient_tends_to_the_converged_one_as_the_cap_grows(square):
    prob, N = diffusion(square, mlp())
    fs, w = sources(prob), weights_of(prob)

    def weight_gradient(options):
        layer = NonlinearSolveLayer(prob, options)
        for p in N.module.parameters():
            p.grad = None
        (layer(f=fs) * w).sum().backward()
        return torch.cat([p.grad.reshape(-1) for p in N.module.parameters()])
    exact = weight_gradient(NewtonOptions(ksp="lu"))
    errors = [float((weight_gradient(NewtonOptions(ksp="lu", max_it=k)) - exact).norm() / exact.norm())
              for k in (1, 2, 3)]
    assert errors[0] > 1e-3 and errors[1] < errors[0] / 3 and errors[2] < errors[1] / 3, errors


def test_the_adjoint_takes_each_samples_values_from_its_forward_instead_of_evaluating_again(square):
    """The network keeps its recent evaluations: a batch's backward, at each sample's solution, evaluates
    nothing, and its gradient is that of a layer that evaluates everything again."""
    prob, N = diffusion(square, mlp())
    layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"))
    fs, w = sources(prob, 3), weights_of(prob, 3)
    out = layer(f=fs)
    before = N.evaluations
    (out * w).sum().backward()
    assert N.evaluations == before
    kept = torch.cat([p.grad.reshape(-1) for p in N.module.parameters()])
    for p in N.module.parameters():
        p.grad = None
    out = layer(f=fs)
    N._recent.clear()                      # forget them: the backward evaluates at each solution again
    before = N.evaluations
    (out * w).sum().backward()
    assert N.evaluations == before + 3
    again = torch.cat([p.grad.reshape(-1) for p in N.module.parameters()])
    assert torch.allclose(kept, again, rtol=1e-13, atol=0)
