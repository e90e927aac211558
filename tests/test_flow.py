"""Stokes, Oseen and Burgers layers: rates, exactness, adjoints, caps and stability."""
from __future__ import annotations

import warnings

from mpi4py import MPI
import dolfinx.fem
import dolfinx.mesh
import numpy as np
import pytest
import sympy
import torch
import ufl

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.core import _dolfinx
from fempdl.core.mesh import TaggedMesh
from fempdl.ksp_adjoint import KSPOptions

from helpers import integral

CONVERGED_SCHUR = KSPOptions.preset("schur", rtol=1e-12)
X, Y = sympy.symbols("x y")


def unit_square(n: int) -> TaggedMesh:
    """The unit square with facets tagged left=1, right=2, walls=3 (y = 0 and y = 1)."""
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, n, n)
    fdim = msh.topology.dim - 1
    pieces = [(1, lambda x: np.isclose(x[0], 0.0)), (2, lambda x: np.isclose(x[0], 1.0)),
              (3, lambda x: np.isclose(x[1], 0.0) | np.isclose(x[1], 1.0))]
    facets, values = [], []
    for tag, where in pieces:
        found = dolfinx.mesh.locate_entities_boundary(msh, fdim, where)
        facets.append(found)
        values.append(np.full(len(found), tag, dtype=np.int32))
    facets, values = np.concatenate(facets), np.concatenate(values)
    facets, first = np.unique(facets, return_index=True)
    tags = dolfinx.mesh.meshtags(msh, fdim, facets, values[first])
    return TaggedMesh(msh, None, tags, "unit-square", {"left": 1, "right": 2, "walls": 3})


def field_function(prob, name: str, values: np.ndarray):
    fn = dolfinx.fem.Function(prob.field_space(name))
    fn.x.array[: len(values)] = values
    fn.x.scatter_forward()
    return fn


def norm(expr, comm) -> float:
    return float(np.sqrt(integral(_dolfinx.compile_form(expr * ufl.dx(degree=8)), comm)))


# ------------------------------------------------------------------ Stokes
PSI = sympy.sin(sympy.pi * X) ** 2 * sympy.sin(sympy.pi * Y) ** 2 / sympy.pi
U_EXACT = (sympy.diff(PSI, Y), -sympy.diff(PSI, X))            # divergence-free
P_EXACT = sympy.cos(sympy.pi * X) * sympy.sin(sympy.pi * Y / 2)
NU = 0.5
F_EXACT = tuple(-NU * (sympy.diff(c, X, 2) + sympy.diff(c, Y, 2)) + sympy.diff(P_EXACT, v)
                for c, v in zip(U_EXACT, (X, Y)))


def vector_callable(exprs):
    fns = [sympy.lambdify((X, Y), e, "numpy") for e in exprs]
    return lambda x: np.stack([f(x[0], x[1]) + 0.0 * x[0] for f in fns])


def stokes_errors(h: float):
    """Enclosed flow on the unstructured L-shape (pressure null space), Dirichlet data from the exact u."""
    msh = mesh.load("lshape", MPI.COMM_WORLD, h=h)
    prob = forms.stokes.problem(msh, nu=NU, velocity={None: vector_callable(U_EXACT)})
    assert prob.enclosed and prob.nullspace.shape == (1, prob.output_size)
    f = torch.as_tensor(prob.interpolate(vector_callable(F_EXACT), "f"))
    parts = prob.split(SolveLayer(prob, CONVERGED_SCHUR)(f=f).numpy())
    uh, ph = field_function(prob, "u", parts["u"]), field_function(prob, "p", parts["p"])
    x = ufl.SpatialCoordinate(prob.V.mesh)
    u_ex = ufl.as_vector([_ufl(c, x) for c in U_EXACT])
    p_ex = _ufl(P_EXACT, x)
    comm = prob.V.mesh.comm
    area = integral(_dolfinx.compile_form(1.0 * ufl.dx(domain=prob.V.mesh)), comm)
    p_mean = integral(_dolfinx.compile_form((ph - p_ex) * ufl.dx), comm) / area
    e = uh - u_ex
    return (comm.allreduce(prob.output_size), norm(ufl.inner(e, e), comm),
            norm(ufl.inner(ufl.grad(e), ufl.grad(e)), comm), norm((ph - p_ex - p_mean) ** 2, comm))


def _ufl(expr, x):
    return sympy.lambdify((X, Y), expr, modules=[{"sin": ufl.sin, "cos": ufl.cos, "pi": ufl.pi}, "math"])(x[0], x[1])


def test_stokes_taylor_hood_rates_with_the_pressure_null_space():
    results = np.array([stokes_errors(h) for h in (0.2, 0.1, 0.05)])
    dofs, errors = results[:, 0], results[:, 1:]
    rates = -2.0 * np.log(errors[1:] / errors[:-1]) / np.log(dofs[1:, None] / dofs[:-1, None])
    expected = np.array([3.0, 2.0, 2.0])                      # velocity L2, velocity H1, pressure L2
    assert np.all(rates[-1] > expected - 0.25), (dofs, errors, rates)
    assert np.all(rates[-1] < expected + 0.6), rates


def test_poiseuille_flow_is_reproduced_to_round_off():
    """u = (4y(1-y), 0), p = 8 nu (1 - x): in P2 x P1, with do-nothing outflow at x = 1."""
    nu = 0.3
    profile = lambda x: np.stack([4 * x[1] * (1 - x[1]), 0 * x[0]])  # noqa: E731
    prob = forms.stokes.problem(unit_square(6), controls=(), nu=nu,
                                velocity={"left": profile, "walls": 0.0})
    assert not prob.enclosed and len(prob.nullspace) == 0
    for opts in (KSPOptions.preset("lu"), CONVERGED_SCHUR):
        parts = prob.split(SolveLayer(prob, opts)().numpy())
        V, Q = prob.field_space("u"), prob.field_space("p")
        ue, pe = dolfinx.fem.Function(V), dolfinx.fem.Function(Q)
        ue.interpolate(profile)
        pe.interpolate(lambda x: 8 * nu * (1 - x[0]))
        np.testing.assert_allclose(parts["u"], ue.x.array[: len(parts["u"])], atol=1e-10)
        np.testing.assert_allclose(parts["p"], pe.x.array[: len(parts["p"])], atol=1e-9)


# ------------------------------------------------------------------ Oseen
def rotation(x):
    return np.stack([-x[1], x[0]])


@pytest.fixture(scope="module")
def coarse_lshape_mesh():
    return mesh.load("lshape", MPI.COMM_WORLD, h=0.5)


@pytest.fixture(scope="module")
def oseen_open(coarse_lshape_mesh):
    """Oseen step with no-slip on the outer boundary and a do-nothing reentrant corner (no null space)."""
    return forms.oseen.problem(coarse_lshape_mesh, controls=("w", "u_prev", "f"), nu=0.05, dt=0.2,
                               velocity={"outer": 0.0})


@pytest.fixture(scope="module")
def oseen_enclosed(coarse_lshape_mesh):
    return forms.oseen.problem(coarse_lshape_mesh, controls=("w", "u_prev", "f"), nu=0.05, dt=0.2)


def velocity_batch(prob, name, batch, seed):
    gen = torch.Generator().manual_seed(seed)
    base = torch.as_tensor(prob.interpolate(rotation, name))
    return base + 0.3 * torch.rand(batch, prob.control_size(name), generator=gen, dtype=torch.float64)


@pytest.mark.parametrize("which", ["oseen_open", "oseen_enclosed"])
def test_oseen_adjoint_solve_passes_the_dot_product_test(which, request):
    """<S b, g> = <b, S^T g> for the converged solution map S of u_prev (linear: zero Dirichlet data),
    S^T applied by the layer's backward pass (adjoint solve on the assembled A^T, null space projected)."""
    prob = request.getfixturevalue(which)
    layer = SolveLayer(prob, CONVERGED_SCHUR)
    w = velocity_batch(prob, "w", 1, 0)[0]
    b = velocity_batch(prob, "u_prev", 1, 1)[0].requires_grad_()
    g = torch.randn(prob.output_size, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    out = layer(w=w, u_prev=b)
    (out * g).sum().backward()
    lhs, rhs = float((out.detach() * g).sum()), float((b.detach() * b.grad).sum())
    assert abs(lhs - rhs) <= 1e-9 * abs(lhs)
    if prob.enclosed:   # outputs orthogonal to the null space: zero pressure sum
        assert abs(float(prob.split(out.detach())["p"].sum())) < 1e-10 * float(out.detach().abs().max())


def test_assembled_adjoint_operator_is_the_exact_transpose(oseen_open):
    from fempdl.solve.petsc import petsc_to_scipy

    layer = SolveLayer(oseen_open, KSPOptions.preset("schur", max_it=3))
    w = velocity_batch(oseen_open, "w", 1, 0)[0].requires_grad_()
    layer(w=w, u_prev=w.detach()).sum().backward()
    solver = layer.system._solver
    A, At = petsc_to_scipy(solver._A), petsc_to_scipy(solver._At)
    assert abs(A.T - At).max() == 0.0 and abs(A - A.T).max() > 1e-3     # non-symmetric, exactly transposed
    assert layer.options.assembled_adjoint


@pytest.mark.parametrize("control", ["w", "u_prev", "f"])
def test_oseen_gradcheck_converged(oseen_open, control):
    layer = SolveLayer(oseen_open, KSPOptions.preset("lu"))
    values = {name: velocity_batch(oseen_open, name, 1, seed)[0] for seed, name in enumerate(("w", "u_prev", "f"))}
    weights = torch.randn(oseen_open.output_size, dtype=torch.float64, generator=torch.Generator().manual_seed(5))

    def loss(m):
        return (layer(**{**values, control: m}) * weights).sum()
    assert torch.autograd.gradcheck(loss, (values[control].clone().requires_grad_(),), eps=1e-6, atol=1e-7, rtol=1e-6)


def test_oseen_gradcheck_enclosed_with_null_space(oseen_enclosed):
    # Central differences at eps = 1e-6 turn a solve error of rtol into rtol / 1e-6: solve to 1e-14.
    layer = SolveLayer(oseen_enclosed, KSPOptions.preset("schur", rtol=1e-14, atol=1e-30))
    u_prev = velocity_batch(oseen_enclosed, "u_prev", 1, 1)[0]
    weights = torch.randn(oseen_enclosed.output_size, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    w = velocity_batch(oseen_enclosed, "w", 1, 0)[0].requires_grad_()
    assert torch.autograd.gradcheck(lambda m: (layer(w=m, u_prev=u_prev) * weights).sum(), (w,),
                                    eps=1e-6, atol=1e-7, rtol=1e-5)


@pytest.mark.parametrize("k", [1, 7, 20])
def test_capped_schur_gmres_runs_exactly_k_iterations_forward_and_adjoint(oseen_enclosed, k):
    layer = SolveLayer(oseen_enclosed, KSPOptions.preset("schur", max_it=k, gmres_restart=5))
    w = velocity_batch(oseen_enclosed, "w", 3, 0).requires_grad_()
    layer(w=w, u_prev=w.detach()).sum().backward()
    s = layer.stats
    assert (s.forward_iterations, s.backward_iterations) == (3 * k, 3 * k)
    assert s.forward_solves == s.backward_solves == 3 and s.failures == 0


def test_a_cap_far_past_convergence_ends_at_the_happy_breakdown(oseen_enclosed):
    """GMRES under a pure cap (tolerance 0) far past convergence: PETSc reports DIVERGED_BREAKDOWN
    once a restart cycle starts from a round-off residual; that is the exact solution, not a failure."""
    w = velocity_batch(oseen_enclosed, "w", 3, 0)
    capped = SolveLayer(oseen_enclosed, KSPOptions.preset("schur", max_it=200, gmres_restart=5))
    u = capped(w=w, u_prev=w)
    assert capped.stats.failures == 0 and capped.stats.forward_iterations < 3 * 200
    converged = SolveLayer(oseen_enclosed, KSPOptions.preset("schur", rtol=1e-13))(w=w, u_prev=w)
    torch.testing.assert_close(u, converged, rtol=1e-9, atol=1e-11)


def test_capped_implicit_gradient_approaches_the_converged_one(oseen_open):
    w0 = velocity_batch(oseen_open, "w", 1, 0)[0]
    f = velocity_batch(oseen_open, "f", 1, 3)[0]

    def grad(opts):
        w = w0.clone().requires_grad_()
        (SolveLayer(oseen_open, opts)(w=w, f=f) ** 2).sum().backward()
        return w.grad

    exact = grad(KSPOptions.preset("lu"))
    errors = [float((grad(KSPOptions.preset("schur", max_it=k)) - exact).norm() / exact.norm()) for k in (2, 8, 30)]
    assert errors[0] > errors[1] > errors[2] and errors[2] < 1e-6, errors


@pytest.mark.parametrize("nu", [1.0, 1e-2, 1e-4])
@pytest.mark.parametrize("dt", [1e-4, 1.0, 1e2])
def test_oseen_stability_matrix(nu, dt):
    """Channel past the cylinder, inflow 1.5 at the centre: finite, bounded velocities for every nu and dt."""
    msh = mesh.load("obstacle", MPI.COMM_WORLD, h=0.1)
    height = 0.41
    inflow = lambda x: np.stack([6.0 * x[1] * (height - x[1]) / height ** 2, 0 * x[0]])  # noqa: E731
    prob = forms.oseen.problem(msh, controls=("w", "u_prev"), nu=nu, dt=dt,
                               velocity={"inlet": inflow, "walls": 0.0, "obstacle": 0.0})
    w = torch.as_tensor(prob.interpolate(inflow, "w"))
    parts = prob.split(SolveLayer(prob, KSPOptions.preset("lu"))(w=w, u_prev=w))
    speed = parts["u"].reshape(-1, 2).norm(dim=1)
    assert torch.isfinite(parts["u"]).all() and torch.isfinite(parts["p"]).all()
    assert float(speed.max()) < 3.0 * 1.5, float(speed.max())


def test_oseen_without_supg_warns_beyond_cell_peclet_one(coarse_lshape_mesh):
    with pytest.warns(UserWarning, match="Péclet"):
        forms.oseen.problem(coarse_lshape_mesh, nu=1e-4, supg=False, w=(1.0, 0.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        forms.oseen.problem(coarse_lshape_mesh, nu=1e-4, w=(1.0, 0.0))          # SUPG on
        forms.oseen.problem(coarse_lshape_mesh, nu=1.0, supg=False, w=(1.0, 0.0))


# ----------------------------------------------------------------- Burgers
@pytest.mark.parametrize("control", ["w", "u_prev"])
def test_burgers_step_gradcheck(coarse_lshape_mesh, control):
    prob = forms.burgers.problem(coarse_lshape_mesh, controls=("w", "u_prev"), nu=0.01, dt=0.1)
    layer = SolveLayer(prob, KSPOptions.preset("gmres-ilu", rtol=1e-13))
    values = {name: velocity_batch(prob, name, 2, seed) for seed, name in enumerate(("w", "u_prev"))}
    assert torch.autograd.gradcheck(lambda m: layer(**{**values, control: m}),
                                    (values[control].clone().requires_grad_(),), eps=1e-6, atol=1e-7, rtol=1e-6)


def test_burgers_gmres_ilu_adjoint_is_exact_at_the_cap(coarse_lshape_mesh):
    """ILU has a true transpose: capped GMRES+ILU runs K iterations in both directions."""
    prob = forms.burgers.problem(coarse_lshape_mesh, controls=("w", "u_prev"))
    layer = SolveLayer(prob, KSPOptions.preset("gmres-ilu", max_it=4))
    u = velocity_batch(prob, "u_prev", 2, 0).requires_grad_()
    layer(w=u, u_prev=u).sum().backward()
    assert (layer.stats.forward_iterations, layer.stats.backward_iterations) == (8, 8)
    assert not layer.options.assembled_adjoint


# ------------------------------------------------------------------ errors
def test_flow_errors_are_clear(coarse_lshape_mesh, oseen_enclosed, oseen_open):
    with pytest.raises(ValueError, match="Taylor-Hood"):
        forms.stokes.problem(coarse_lshape_mesh, degree=1)
    with pytest.raises(ValueError, match="2 finite components"):
        forms.oseen.problem(coarse_lshape_mesh, w=(1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match="do not occur"):
        forms.stokes.problem(coarse_lshape_mesh, velocity={99: 0.0})
    with pytest.raises(ValueError, match="null space"):
        SolveLayer(oseen_enclosed, KSPOptions(max_it=5), diff="unrolled")
    with pytest.raises(ValueError, match="null space"):
        SolveLayer(oseen_enclosed, KSPOptions(max_it=5, engine="batched"))
    poisson = forms.poisson.problem(coarse_lshape_mesh)
    with pytest.raises(ValueError, match="fields"):
        SolveLayer(poisson, KSPOptions.preset("schur", max_it=3))
    with pytest.raises(ValueError, match="single solution space"):
        poisson.split(np.zeros(poisson.output_size))
    with pytest.raises(ValueError, match="output_size"):
        oseen_open.split(np.zeros(3))


def test_lu_on_an_enclosed_flow_detects_the_null_pivot(oseen_enclosed):
    """The "lu" preset on a singular operator (pressure constant) equals the converged Schur
    solve and its adjoint passes the dot-product test: MUMPS gets null-pivot detection."""
    w = velocity_batch(oseen_enclosed, "w", 1, 0)[0]
    b = velocity_batch(oseen_enclosed, "u_prev", 1, 1)[0].requires_grad_()
    lu = SolveLayer(oseen_enclosed, "lu")
    out = lu(w=w, u_prev=b)
    reference = SolveLayer(oseen_enclosed, CONVERGED_SCHUR)(w=w, u_prev=b.detach())
    assert float((out.detach() - reference).abs().max()) <= 1e-8 * float(reference.abs().max())
    g = torch.randn(oseen_enclosed.output_size, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    (out * g).sum().backward()
    lhs, rhs = float((out.detach() * g).sum()), float((b.detach() * b.grad).sum())
    assert abs(lhs - rhs) <= 1e-9 * abs(lhs)
