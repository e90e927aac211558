"""Soundness at the extremes (docs/semantics.md, "At the extremes"): data of any representable scale,
singular systems, a capped stationary iteration that diverges outside PRDP, and failures that name
their cause. Each test fails without the rule it checks."""
from __future__ import annotations

import warnings

from mpi4py import MPI
import dolfinx
import numpy as np
import pytest
import torch
import ufl

from fempdl import Problem, forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.core import _dolfinx
from fempdl.ksp_adjoint import KSPOptions
from fempdl.layer.rollout import Rollout
from fempdl.solve.stats import SolverFailedError, SolverWarning

EPS = np.finfo(float).eps


@pytest.fixture(scope="module")
def poisson():
    msh = mesh.load("lshape", MPI.COMM_WORLD, h=0.2)
    prob = forms.poisson.problem(msh, controls=("f",))
    rng = np.random.default_rng(3)
    f = torch.tensor(1.0 + rng.random(prob.control_size("f")), dtype=torch.float64)
    g = torch.tensor(rng.random(prob.output_size), dtype=torch.float64)
    lu = SolveLayer(prob, "lu")
    u = lu(f=f).detach()
    fg = f.clone().requires_grad_()
    (lu(f=fg) * g).sum().backward()
    return prob, f, g, u, fg.grad.clone()


def _rel(a, b) -> float:
    return float((a - b).norm() / b.norm())


# The presets' converged solves run to rtol 1e-10: their error is bounded by cond(A) rtol. A solve
# that took PETSc's atol of 1e-50 stopped at iteration 0 with u = 0 (error 1).
SCALED = [1e-50, 1e-60, 1e-120, 1e120, 1e300]


@pytest.mark.parametrize("preset", ["cg", "gmres", "jacobi", "amg"])
@pytest.mark.parametrize("batch", [1, 16])          # 16: the batched engine takes CG and Richardson
def test_sources_of_any_scale_solve_to_the_same_relative_accuracy(poisson, preset, batch):
    prob, f, _, u_ref, _ = poisson
    layer = SolveLayer(prob, preset)
    for scale in SCALED:
        u = layer(f=(f * scale).expand(batch, -1))
        assert torch.isfinite(u).all()
        for row in u:
            assert _rel(row / scale, u_ref) < 1e-6, (preset, scale)


@pytest.mark.parametrize("preset", ["cg", "gmres", "lu"])
def test_a_subnormal_source_solves_to_its_own_precision(poisson, preset):
    prob, f, _, u_ref, _ = poisson
    scale = 1e-310     # subnormal (below 2.2e-308): f * scale and b = M f keep about 35 of float64's 53 bits
    f_sub = f * scale
    # The reference is the solution of the source as represented, scaled up exactly by 2^1100.
    represented = torch.tensor(np.ldexp(f_sub.numpy(), 1100))
    ref = SolveLayer(prob, "lu")(f=represented)
    u = SolveLayer(prob, preset)(f=f_sub)
    assert (u != 0).any()
    rel = float(np.linalg.norm(np.ldexp(u.numpy(), 1100) - ref.numpy()) / ref.norm())
    # b's entries (about 1e-312, 2^-1036) are represented to 2^-1075 absolute: 2^-39 of themselves.
    assert rel < 1e-8, rel


@pytest.mark.parametrize("preset", ["cg", "gmres", "jacobi"])
def test_a_tiny_loss_gives_the_scaled_gradient(poisson, preset):
    prob, f, g, _, grad_ref = poisson
    layer = SolveLayer(prob, preset)
    fg = f.clone().requires_grad_()
    (layer(f=fg) * g * 1e-60).sum().backward()
    assert _rel(fg.grad * 1e60, grad_ref) < 1e-6


def test_a_given_atol_is_on_the_data_as_given(poisson):
    prob, f, _, u_ref, _ = poisson
    # atol far above the scaled residual: the solve stops at once (x = 0), as PETSc would on these data.
    u = SolveLayer(prob, KSPOptions.preset("cg", atol=1.0, engine="petsc"))(f=f * 1e-100)
    assert float(u.abs().max()) == 0.0
    u = SolveLayer(prob, KSPOptions.preset("cg", atol=1e-140, engine="petsc"))(f=f * 1e-100)
    assert _rel(u / 1e-100, u_ref) < 1e-6


def _pure_neumann(V, nullspace=()):
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    f = dolfinx.fem.Function(V)
    a = ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx
    return Problem(a, ufl.inner(f, v) * ufl.dx, [], controls={"f": f}, nullspace=nullspace)


@pytest.mark.parametrize("preset", ["lu", "cg", "gmres"])
@pytest.mark.parametrize("shape", [None, (2,)])
def test_a_system_without_dirichlet_conditions_or_null_space_is_refused(preset, shape):
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 6, 6)
    prob = _pure_neumann(_dolfinx.function_space(msh, "Lagrange", 1, **({"shape": shape} if shape else {})))
    f = torch.ones(prob.control_size("f"), dtype=torch.float64)
    with pytest.raises(ValueError, match="the system is singular: the operator maps the constant .* declare the null"):
        SolveLayer(prob, preset)(f=f)


def test_a_reaction_term_or_a_dirichlet_condition_is_not_singular():
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 6, 6)
    V = _dolfinx.function_space(msh, "Lagrange", 1)
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    f = dolfinx.fem.Function(V)
    # A weak reaction (1e-6 against a diffusivity of 1) is far from round-off: it solves.
    a = (ufl.inner(ufl.grad(u), ufl.grad(v)) + 1e-6 * u * v) * ufl.dx
    prob = Problem(a, f * v * ufl.dx, [], controls={"f": f})
    out = SolveLayer(prob, "lu")(f=torch.ones(prob.control_size("f"), dtype=torch.float64))
    assert torch.isfinite(out).all()
    stokes = forms.stokes.problem(mesh.load("lshape", MPI.COMM_WORLD, h=0.3))    # declares its null space
    assert torch.isfinite(SolveLayer(stokes, "lu")()).all()


def test_an_incompatible_load_with_a_declared_null_space_is_projected_and_said():
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 6, 6)
    V = _dolfinx.function_space(msh, "Lagrange", 1)
    n = V.dofmap.index_map.size_local
    prob = _pure_neumann(V, nullspace=[np.ones(n)])
    x = V.tabulate_dof_coordinates()[:n]
    layer = SolveLayer(prob, "lu")
    # A load with zero integral (b = M f orthogonal to the constants): f minus its weighted mean.
    weights_form = _dolfinx.compile_form(ufl.TestFunction(V) * ufl.dx)
    weights = _dolfinx.assemble_vector_into(_dolfinx.create_vector(weights_form), weights_form).getArray()[:n]
    g = np.cos(np.pi * x[:, 0]) + x[:, 1]
    compatible = torch.tensor(g - (weights @ g) / weights.sum())
    with warnings.catch_warnings():
        warnings.simplefilter("error", SolverWarning)
        layer(f=compatible)
    with pytest.warns(SolverWarning, match="part along the operator's declared null space"):
        u = layer(f=torch.ones(n, dtype=torch.float64))
    assert abs(float(u.sum())) < 1e-10 * float(u.abs().sum())     # the solution orthogonal to the constants


def test_a_diverging_capped_iteration_warns_in_a_plain_call():
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 8, 8)
    prob = forms.poisson.problem(msh, controls=("f",), degree=2)      # Jacobi's iteration diverges on P2
    f = torch.ones(prob.control_size("f"), dtype=torch.float64)
    layer = SolveLayer(prob, KSPOptions.preset("jacobi", max_it=40))
    with pytest.warns(SolverWarning, match=r"residual at .* times its start at Caps\(max_it=40\): the iteration "
                                           "diverges"):
        layer(f=f)
    with warnings.catch_warnings():           # measured once per cap: the next call is free
        warnings.simplefilter("error", SolverWarning)
        layer(f=f)
        for preset in ("cg", "gmres"):        # Krylov methods bound their residual: never watched
            SolveLayer(prob, KSPOptions.preset(preset, max_it=40))(f=f)
        p1 = forms.poisson.problem(msh, controls=("f",))
        SolveLayer(p1, KSPOptions.preset("jacobi", max_it=40))(f=torch.ones(p1.control_size("f"),
                                                                             dtype=torch.float64))


def test_a_badly_scaled_saddle_point_names_its_scaling():
    prob = forms.stokes.problem(mesh.load("obstacle", MPI.COMM_WORLD, h=0.15), nu=1e-6, f=(1.0, 0.0))
    with pytest.raises(SolverFailedError, match=r"badly scaled; its diagonal spans .* use an iterative preset "
                                                r"\('schur'"):
        SolveLayer(prob, "lu")()
    assert torch.isfinite(SolveLayer(prob, "schur")()).all()


def test_an_overflowing_rollout_names_the_step_and_the_state():
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 8, 8)
    # Explicit Euler far beyond its stability limit (dt ~ h^2 / 4): the state grows ~1e3-fold a step.
    prob = forms.heat.problem(msh, controls=("u0",), dt=1.0, theta=0.0)
    n = prob.control_size("u0")
    rollout = Rollout(SolveLayer(prob, "lu"), state="u0")
    u0 = torch.tensor(np.random.default_rng(0).random(n))
    with pytest.raises(SolverFailedError, match=r"step \d+ of 400 \(solve\); the state entering it reaches .*: "
                                                r".*(right-hand side holding NaN|overflows float64).*unstable step"):
        rollout(u0, 400)


def test_hyperelasticity_warns_where_its_displacement_form_locks():
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 4, 4)
    with pytest.warns(UserWarning, match=r"hyperelasticity: nu=0.4999 .* displacement-only P1 locks"):
        forms.hyperelasticity.problem(msh, nu=0.4999)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        forms.hyperelasticity.problem(msh, nu=0.3)
