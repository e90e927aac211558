"""The solver of a layer without options, chosen by dimension, size, block size, symmetry, fields and
whether the matrix changes between calls (fempdl.solve.default_solver)."""
from __future__ import annotations

import math

from mpi4py import MPI
import dolfinx.mesh
import pytest
import torch
from petsc4py import PETSc

from fempdl import KSPOptions, NewtonOptions, NonlinearSolveLayer, SolveLayer, forms
from fempdl.solve import default_solver
from fempdl.solve.default_solver import (
    DIRECT_MAX_DOFS,
    DIRECT_MAX_DOFS_REFACTORED,
    SystemTraits,
    default_options,
    default_preset,
    direct_max_dofs,
    explain_default,
)

F64 = torch.float64


@pytest.fixture(scope="module")
def cube():
    return dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, 6, 6, 6)


@pytest.fixture
def small_limits(monkeypatch):
    """Direct limits below every mesh here: the iterative defaults run on small problems."""
    for table in ("DIRECT_MAX_DOFS", "DIRECT_MAX_DOFS_REFACTORED"):
        monkeypatch.setattr(default_solver, table, {1: 10, 2: 10, 3: 10})


def rand(n, seed=0, shift=0.0):
    return (torch.rand(n, dtype=F64, generator=torch.Generator().manual_seed(seed)) + shift).requires_grad_()


# ------------------------------------------------------------------ the rule
@pytest.mark.parametrize("traits, preset", [
    (SystemTraits(tdim=3, dofs=68_921, symmetric=True, matrix_fixed=True), "amg"),        # was LU: 33 s vs 1.3 s
    (SystemTraits(tdim=3, dofs=1_000_000, symmetric=True), "amg"),                        # was GMRES + Jacobi
    (SystemTraits(tdim=3, dofs=9_261, symmetric=True, matrix_fixed=True), "lu"),          # factor reused
    (SystemTraits(tdim=3, dofs=9_261, symmetric=True, matrix_fixed=False), "amg"),        # refactorised per call
    (SystemTraits(tdim=3, dofs=2_197, symmetric=True), "lu"),
    (SystemTraits(tdim=2, dofs=290_000, symmetric=True, matrix_fixed=True), "lu"),
    (SystemTraits(tdim=2, dofs=150_000, symmetric=True, matrix_fixed=False), "amg"),
    (SystemTraits(tdim=1, dofs=500_000, symmetric=False), "lu"),
    (SystemTraits(tdim=3, dofs=50_000, block_size=3, symmetric=True, near_nullspace=True), "amg"),
    (SystemTraits(tdim=3, dofs=50_000, symmetric=True, fields=("u", "p")), "schur"),      # symmetric, indefinite
    (SystemTraits(tdim=3, dofs=50_000, fields=("u", "p")), "schur"),
    (SystemTraits(tdim=3, dofs=50_000), "gmres-ilu"),
    (SystemTraits(tdim=3, dofs=50_000, block_size=3, near_nullspace=True), "gmres-gamg"),    # hyperelastic Newton
    (SystemTraits(tdim=2, dofs=200_000, fields=("c", "phi")), "gmres-ilu"),
], ids=lambda v: v if isinstance(v, str) else f"{v.tdim}D-{v.dofs}")
def test_the_default_follows_the_problem(traits, preset):
    name, options = default_preset(traits)
    assert name == preset
    assert not options.capped and (options.direct or options.rtol is None)   # converged to DEFAULT_RTOL


def test_the_iterative_defaults_are_the_fitting_presets():
    big = dict(tdim=3, dofs=10**6)
    assert default_preset(SystemTraits(**big, symmetric=True))[1] == KSPOptions.preset("amg")
    elasticity = default_preset(SystemTraits(**big, block_size=3, symmetric=True, near_nullspace=True))[1]
    assert (elasticity.ksp_type, elasticity.pc_type) == ("cg", "gamg")    # GAMG reads the rigid-body modes
    assert default_preset(SystemTraits(**big, fields=("u", "p")))[1] == KSPOptions.preset("schur")
    # Block Jacobi with ILU(0) blocks: ILU(0) on one process, and it runs under MPI (PCILU does not).
    gmres = default_preset(SystemTraits(**big))[1]
    assert (gmres.ksp_type, gmres.pc_type, gmres.gmres_restart) == ("gmres", "bjacobi", 30)


def test_the_direct_limit_falls_with_the_block_size_and_a_refactorised_matrix():
    assert direct_max_dofs(3, 1, matrix_fixed=True) == DIRECT_MAX_DOFS[3]
    assert direct_max_dofs(3, 3, matrix_fixed=True) == int(DIRECT_MAX_DOFS[3] / math.sqrt(3))
    assert direct_max_dofs(2, 2) == int(DIRECT_MAX_DOFS_REFACTORED[2] / math.sqrt(2))
    for tdim in (1, 2, 3):
        assert direct_max_dofs(tdim, matrix_fixed=False) <= direct_max_dofs(tdim, matrix_fixed=True)
    assert direct_max_dofs(3, matrix_fixed=True) < 68_921 <= direct_max_dofs(2, matrix_fixed=True)


# ------------------------------------------------------------------ the traits of real problems
def test_traits_are_read_from_the_problem(cube, coarse_lshape):
    fixed = SystemTraits.of(forms.poisson.problem(cube))
    assert (fixed.tdim, fixed.dofs, fixed.block_size, fixed.symmetric, fixed.matrix_fixed) == (3, 343, 1, True, True)
    assert not SystemTraits.of(forms.poisson.problem(cube, controls=("f", "kappa"))).matrix_fixed
    elastic = SystemTraits.of(forms.elasticity.problem(cube))
    assert (elastic.block_size, elastic.near_nullspace, elastic.spd) == (3, True, True)
    mixed = SystemTraits.of(forms.elasticity.problem(cube, formulation="mixed", nu=0.3))
    assert mixed.fields == ("u", "p") and mixed.symmetric and not mixed.spd
    stokes = SystemTraits.of(forms.stokes.problem(coarse_lshape))
    assert stokes.fields == ("u", "p") and not stokes.symmetric and stokes.tdim == 2
    newton = SystemTraits.of(forms.nonlinear_diffusion.problem(cube))
    assert not newton.symmetric and not newton.matrix_fixed       # a new Jacobian at every Newton step


def test_the_choice_is_explained(cube, small_limits):
    assert explain_default(forms.poisson.problem(cube)) == (
        "amg: 343 unknowns > 10, the direct limit in 3D for a fixed matrix (block size 1); symmetric on one field")
    assert "gmres-ilu: " in explain_default(forms.nonlinear_diffusion.problem(cube))
    assert "refactorised matrix" in explain_default(forms.nonlinear_diffusion.problem(cube))


# ------------------------------------------------------------------ the defaults at work
def test_a_large_3d_poisson_layer_solves_by_amg_with_the_gradient_of_lu(cube, small_limits):
    prob = forms.poisson.problem(cube, controls=("f", "kappa"))
    layer = SolveLayer(prob)
    assert layer.options == KSPOptions.preset("amg") and not layer.options.capped
    exact = SolveLayer(prob, "lu")
    f, kappa = rand(prob.control_size("f")), rand(prob.control_size("kappa"), seed=1, shift=1.0)
    w = torch.rand(prob.output_size, dtype=F64, generator=torch.Generator().manual_seed(2))
    u = layer(f=f, kappa=kappa)
    grads = torch.autograd.grad((u * w).sum(), (f, kappa))
    u_lu = exact(f=f, kappa=kappa)
    grads_lu = torch.autograd.grad((u_lu * w).sum(), (f, kappa))
    # rtol 1e-10 on the preconditioned residual: the error is bounded by it times A's condition (~1e2 here).
    torch.testing.assert_close(u, u_lu, rtol=0, atol=1e-7 * u_lu.abs().max().item())
    for g, g_lu in zip(grads, grads_lu):
        torch.testing.assert_close(g, g_lu, rtol=0, atol=1e-7 * g_lu.abs().max().item())
    assert 0 < layer.stats.max_forward_iterations < 30        # AMG: a handful of iterations, not Jacobi's hundreds


def test_elasticity_defaults_to_gamg_with_its_rigid_body_modes(cube, small_limits):
    prob = forms.elasticity.problem(cube, controls=("f",))
    layer = SolveLayer(prob)
    assert (layer.options.ksp_type, layer.options.pc_type) == ("cg", "gamg")
    f = rand(prob.control_size("f"))
    torch.testing.assert_close(layer(f=f), SolveLayer(prob, "lu")(f=f), rtol=0, atol=1e-7)


def test_a_newton_step_defaults_to_gmres_ilu_beyond_the_limit(cube, small_limits):
    prob = forms.nonlinear_diffusion.problem(cube)
    layer = NonlinearSolveLayer(prob)
    ksp = layer.options.ksp
    assert (ksp.ksp_type, ksp.pc_type) == ("gmres", "bjacobi") and not ksp.capped
    exact = NonlinearSolveLayer(prob, NewtonOptions(ksp=KSPOptions.preset("lu")))
    f = rand(prob.control_size("f"), shift=1.0)
    u = layer(f=f)
    (g,) = torch.autograd.grad(u.sum(), f)
    u_lu = exact(f=f)
    (g_lu,) = torch.autograd.grad(u_lu.sum(), f)
    torch.testing.assert_close(u, u_lu, rtol=0, atol=1e-7 * u_lu.abs().max().item())
    torch.testing.assert_close(g, g_lu, rtol=0, atol=1e-7 * g_lu.abs().max().item())


def test_a_hyperelastic_newton_step_defaults_to_gmres_gamg_beyond_the_limit(small_limits):
    beam = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [4, 1, 1]], [12, 3, 3])
    prob = forms.hyperelasticity.problem(beam, controls=("T",))
    layer = NonlinearSolveLayer(prob)
    assert (layer.options.ksp.ksp_type, layer.options.ksp.pc_type) == ("gmres", "gamg")
    exact = NonlinearSolveLayer(prob, NewtonOptions(ksp=KSPOptions.preset("lu")))
    T = torch.full((prob.control_size("T"),), -1e-3, dtype=F64, requires_grad=True)
    u, u_lu = layer(T=T), exact(T=T)
    (g,), (g_lu,) = torch.autograd.grad(u.sum(), T), torch.autograd.grad(u_lu.sum(), T)
    torch.testing.assert_close(u, u_lu, rtol=0, atol=1e-7 * u_lu.abs().max().item())
    torch.testing.assert_close(g, g_lu, rtol=0, atol=1e-7 * g_lu.abs().max().item())


def test_small_problems_keep_the_exact_direct_default(cube, coarse_lshape):
    assert default_options(forms.poisson.problem(cube, controls=("f", "kappa"))) == KSPOptions.preset("lu")
    assert default_options(forms.stokes.problem(coarse_lshape)) == KSPOptions.preset("lu")


@pytest.mark.skipif(not PETSc.Sys.hasExternalPackage("hypre"), reason="the GAMG-for-hypre swap needs hypre")
def test_hypre_is_swapped_for_gamg_only_where_a_near_nullspace_is_given():
    traits = SystemTraits(tdim=3, dofs=10**6, symmetric=True)
    assert default_preset(traits)[1].pc_type == "hypre"
    assert default_preset(SystemTraits(tdim=3, dofs=10**6, symmetric=True, near_nullspace=True))[1].pc_type == "gamg"
