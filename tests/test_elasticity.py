"""Linear elasticity: the rigid-body modes span the operator's kernel without boundary conditions, hand
algebraic multigrid its near null space (fewer GAMG iterations, the same solution), and the layer's
gradients for the body force and Young's modulus are exact."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fempdl import KSPOptions, SolveLayer, forms, mesh
from fempdl.core.nullspaces import rigid_body_modes
from fempdl.solve.assembly import assemble_scipy

F64 = torch.float64


@pytest.mark.parametrize("name, h", [("lshape", 0.25), ("box", 0.3)])
def test_rigid_body_modes_are_the_kernel_without_boundary_conditions(name, h):
    prob = forms.elasticity.problem(mesh.load(name, h=h), controls=("f",))
    A = assemble_scipy(prob.a_form)                       # no Dirichlet rows
    modes = rigid_body_modes(prob.V)
    assert modes.shape == ({2: 3, 3: 6}[prob.V.mesh.geometry.dim], prob.output_size)
    scale = abs(A).sum(axis=1).max()
    for mode in modes:
        assert np.abs(A @ mode).max() <= 1e-12 * scale * np.abs(mode).max()
    # A displacement that is not rigid is not annihilated.
    stretch = prob.interpolate(lambda x: np.stack([x[0]] + [0 * x[0]] * (prob.V.mesh.geometry.dim - 1)))
    assert np.abs(A @ stretch).max() > 1e-3 * scale


def test_the_near_null_space_saves_gamg_iterations_and_changes_no_solution():
    msh = mesh.load("box")
    options = KSPOptions(ksp_type="cg", pc_type="gamg", rtol=1e-8, engine="petsc")
    iterations, solutions = {}, {}
    for near in (True, False):
        prob = forms.elasticity.problem(msh, controls=("f",), dirichlet=("bottom",), near_nullspace=near)
        assert len(prob.near_nullspace) == (6 if near else 0)
        f = torch.as_tensor(prob.interpolate(lambda x: np.stack([0 * x[0], 0 * x[0], -1 - x[0]]), "f"))
        layer = SolveLayer(prob, options)
        solutions[near] = layer(f=f)
        iterations[near] = layer.stats.forward_iterations
    assert iterations[True] < 0.8 * iterations[False], iterations           # measured: 16 against 24-28
    reference = SolveLayer(prob, "lu")(f=f)
    for u in solutions.values():
        assert (u - reference).norm() <= 1e-6 * reference.norm()


def test_gradients_for_body_force_and_youngs_modulus_are_exact():
    prob = forms.elasticity.problem(mesh.load("lshape", h=0.4), controls=("f", "E"), nu=0.25)
    layer = SolveLayer(prob, "lu")
    g = torch.Generator().manual_seed(0)
    f = torch.rand(prob.control_size("f"), dtype=F64, generator=g).requires_grad_()
    E = (1.0 + torch.rand(prob.control_size("E"), dtype=F64, generator=g)).requires_grad_()
    assert torch.autograd.gradcheck(lambda f, E: layer(f=f, E=E), (f, E))


def test_bad_parameters_are_refused():
    msh = mesh.load("lshape", h=0.4)
    with pytest.raises(ValueError, match=r"nu must be a Poisson's ratio in \[0, 0.5\), got 0.5"):
        forms.elasticity.problem(msh, nu=0.5)
    with pytest.raises(ValueError, match="leaves rigid-body motions free"):
        forms.elasticity.problem(msh, dirichlet=())
    with pytest.raises(ValueError, match="E must be > 0 everywhere"):
        forms.elasticity.problem(msh, E=0.0)
    with pytest.raises(ValueError, match="rigid_body_modes needs a vector space"):
        rigid_body_modes(forms.poisson.problem(msh).V)
