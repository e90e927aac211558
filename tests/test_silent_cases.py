"""Cases that used to return a wrong result without a word: a layer without options, a singular
operator, a direct solve that does not factorise, and a second derivative through the implicit layer."""
from __future__ import annotations

import re

import pytest
import torch

from fempdl import KSPOptions, SolveLayer, forms
from fempdl.layer.implicit_diff import SECOND_DERIVATIVE_MESSAGE

F64 = torch.float64


@pytest.fixture(scope="module")
def prob(coarse_lshape):
    prob = forms.poisson.problem(coarse_lshape, controls=("f", "kappa"))
    prob.positive = ()          # kappa <= 0 on purpose: the matrix checks behind the positivity check
    return prob


def inputs(prob, kappa: float = 1.0, batch: int = 2):
    g = torch.Generator().manual_seed(0)
    f = torch.rand(batch, prob.control_size("f"), dtype=F64, generator=g)
    return f, torch.full((prob.control_size("kappa"),), kappa, dtype=F64)


# ------------------------------------------------------------------ a layer without options
def test_a_layer_without_options_returns_the_solution(lshape):
    """No options: the solution (a direct solve here), not a cap of 20 iterations."""
    prob = forms.poisson.problem(lshape, controls=("f", "kappa"))
    f, kappa = inputs(prob)
    default = SolveLayer(prob)
    assert default.options == KSPOptions.preset("lu") and default.max_it is None
    converged = SolveLayer(prob, KSPOptions.preset("cg", rtol=1e-13))(f=f, kappa=kappa)
    torch.testing.assert_close(default(f=f, kappa=kappa), converged, rtol=0, atol=1e-10)
    # Twenty Jacobi iterations (the old default) are far from it on the bundled L-shape.
    capped = SolveLayer(prob, KSPOptions(max_it=20))(f=f, kappa=kappa)
    assert (capped - converged).norm() > 0.5 * converged.norm()


def test_options_are_capped_only_when_asked(prob):
    """A bare KSPOptions and the preset of the same name both run to rtol; max_it caps them."""
    assert KSPOptions().max_it is None and KSPOptions(ksp_type="cg").max_it is None
    assert KSPOptions(ksp_type="richardson", pc_type="jacobi") == KSPOptions.preset("jacobi")
    assert KSPOptions(max_it=7).max_it == 7 and KSPOptions.preset("jacobi", max_it=7).max_it == 7


# ------------------------------------------------------------------ singular operators
@pytest.mark.parametrize("options", [KSPOptions.preset("lu"), KSPOptions(max_it=20), KSPOptions.preset("cg")],
                         ids=["lu", "capped-jacobi", "cg"])
def test_a_zero_coefficient_is_refused_naming_the_control(prob, options):
    """kappa = 0 empties the interior rows: LU returned |u| = 3e-149 and capped Jacobi finite garbage."""
    f, kappa = inputs(prob, kappa=0.0)
    layer = SolveLayer(prob, options)
    with pytest.raises(ValueError, match=r"the assembled matrix has \d+ empty rows \(it is singular\) with "
                                         r"control\(s\) \['kappa'\]; check for a zero"):
        layer(f=f, kappa=kappa)
    assert layer.stats.forward_solves == 0
    u = layer(f=f, kappa=kappa + 1.0)             # the layer works on after the refusal
    assert torch.isfinite(u).all()


def test_a_zero_coefficient_on_part_of_the_domain_is_refused(prob):
    f, kappa = inputs(prob)
    x = torch.as_tensor(prob.dof_coordinates("kappa")[:, 0])
    kappa = torch.where(x < 0.0, 0.0, 1.0).to(F64)          # zero on the left part of the L
    with pytest.raises(ValueError, match=r"empty rows .* \['kappa'\]"):
        SolveLayer(prob, "lu")(f=f, kappa=kappa)


def test_a_fixed_zero_coefficient_names_the_problem(coarse_lshape):
    """A fixed coefficient a user set to zero is refused as the problem's own, before it makes the matrix
    singular."""
    prob = forms.poisson.problem(coarse_lshape, controls=("f",))
    kappa, = prob.a.constants()                 # a fixed number: a Constant
    assert prob.constants["kappa"] is kappa
    kappa.value = 0.0                           # a user's edit of the fixed coefficient
    with pytest.raises(ValueError, match=r"Constant 'kappa' must be > 0 \(problem.positive\), got 0"):
        SolveLayer(prob, "lu")(f=torch.ones(prob.control_size("f"), dtype=F64))


def test_an_indefinite_but_regular_operator_is_not_refused(prob):
    """A coefficient that changes sign makes zero diagonal entries without empty rows: not refused here
    (an LU solves it; CG reports the indefiniteness itself)."""
    f, _ = inputs(prob, batch=1)
    x = torch.as_tensor(prob.dof_coordinates("kappa")[:, 0])
    kappa = torch.where(x < 0.3, -1.0, 1.0).to(F64)
    u = SolveLayer(prob, "lu")(f=f, kappa=kappa)
    assert torch.isfinite(u).all()


# ------------------------------------------------------------------ direct solves that are not
def test_preonly_needs_a_preconditioner_that_factorises():
    assert KSPOptions(ksp_type="preonly", pc_type="redundant").direct          # PETSc's default: LU inside
    assert KSPOptions(ksp_type="preonly", pc_type="redundant",
                      petsc_options={"redundant_pc_type": "cholesky"}).direct
    for inner in ({"redundant_pc_type": "jacobi"}, {"redundant_ksp_type": "richardson"}):
        with pytest.raises(ValueError, match=r"pc_type='redundant' \(redundant_.*\) the result is not the solution"):
            KSPOptions(ksp_type="preonly", pc_type="redundant", petsc_options=inner)


# ------------------------------------------------------------------ second derivatives
def test_second_derivatives_through_the_implicit_layer_raise(prob):
    """A Hessian-vector product used to drop the layer's term (1-1.5% off), or return 0 for the layer alone."""
    layer = SolveLayer(prob, "lu")
    f = inputs(prob, batch=1)[0][0].requires_grad_()
    kappa = inputs(prob)[1]
    first, = torch.autograd.grad(layer(f=f, kappa=kappa).sum() ** 2, f)
    again, = torch.autograd.grad(layer(f=f, kappa=kappa).sum() ** 2, f, create_graph=True)
    torch.testing.assert_close(again.detach(), first, rtol=0, atol=0)     # first order is unchanged
    with pytest.raises(RuntimeError, match="second derivatives through SolveLayer"):
        torch.autograd.grad(again.sum(), f)
    with pytest.raises(RuntimeError, match=re.escape(SECOND_DERIVATIVE_MESSAGE[:60])):
        torch.autograd.functional.hvp(lambda x: layer(f=x, kappa=kappa).sum() ** 2, f.detach(),
                                      torch.ones_like(f))
    with pytest.raises(RuntimeError, match="second derivatives through SolveLayer"):
        gradient = torch.func.grad(lambda x: layer(f=x, kappa=kappa).sum() ** 2)
        torch.func.grad(lambda x: gradient(x).sum())(f.detach())


def test_first_derivatives_under_torch_func_still_work(prob):
    layer = SolveLayer(prob, "lu")
    f, kappa = inputs(prob, batch=1)
    jac = torch.func.jacrev(lambda x: layer(f=x, kappa=kappa))(f[0])
    assert jac.shape == (prob.output_size, prob.control_size("f")) and torch.isfinite(jac).all()


# ------------------------------------------------------------------ folded meshes
def grid_msh(path, centre=(0.5, 0.5)):
    """A gmsh 2.2 file of the unit square in 8 triangles around the node ``centre`` (0.5, 0.5 when unfolded)."""
    nodes = [(i * 0.5, j * 0.5) for j in range(3) for i in range(3)]
    nodes[4] = centre
    triangles = []
    for j in range(2):
        for i in range(2):
            a, b, c, d = j * 3 + i, j * 3 + i + 1, (j + 1) * 3 + i, (j + 1) * 3 + i + 1
            triangles += [(a, b, d), (a, d, c)]
    lines = (["$MeshFormat", "2.2 0 8", "$EndMeshFormat", "$PhysicalNames", "1", '2 1 "domain"', "$EndPhysicalNames",
              "$Nodes", str(len(nodes))] + [f"{k + 1} {x} {y} 0" for k, (x, y) in enumerate(nodes)]
             + ["$EndNodes", "$Elements", str(len(triangles))]
             + [f"{k + 1} 2 2 1 1 {a + 1} {b + 1} {c + 1}" for k, (a, b, c) in enumerate(triangles)] + ["$EndElements"])
    path.write_text("\n".join(lines) + "\n")
    return path


def test_a_folded_mesh_is_refused_on_load(tmp_path):
    """Moving the middle node past the edge inverts three triangles (the area integral grows): refused."""
    from fempdl import mesh
    good = mesh.load(grid_msh(tmp_path / "good.msh"))
    assert good.mesh.topology.index_map(2).size_local == 8
    with pytest.raises(ValueError, match=r"folded.msh: 3 interior facet\(s\) have both their cells on the same "
                                         r"side, e.g. near .*: the mesh is folded"):
        mesh.load(grid_msh(tmp_path / "folded.msh", centre=(1.2, 0.5)))
    with pytest.raises(ValueError, match="flat cells"):                  # the node on an edge: flat cells
        mesh.load(grid_msh(tmp_path / "flat.msh", centre=(1.0, 0.5)))


def test_a_positional_control_names_the_keywords(prob):
    f, kappa = inputs(prob)
    with pytest.raises(TypeError, match=r"SolveLayer takes its controls as keywords, got 1 positional argument\(s\); "
                                        r"call it as layer\(f=\.\.\., kappa=\.\.\.\)"):
        SolveLayer(prob, "lu")(f)


def test_a_system_outlives_the_layer_it_came_from(prob):
    """SolveLayer(p).system.constant_matrix() used to segfault: the temporary layer's finaliser freed the
    PETSc objects the system still used. Now the system frees them when it is collected itself."""
    A = SolveLayer(prob, "lu").system.constant_matrix()
    assert A.shape == (prob.output_size, prob.output_size) and A.nnz > prob.output_size
    system = SolveLayer(prob, KSPOptions(max_it=3)).system
    assert system.constant_matrix().shape == A.shape
    layer = SolveLayer(prob, "lu")
    layer.close()
    layer.close()                                       # twice: nothing more to free
    with pytest.raises(RuntimeError, match="this SolveLayer was closed"):
        layer(f=inputs(prob)[0])


def test_a_dropped_layer_frees_its_system_at_once(prob):
    """Without a reference cycle the system (and the PETSc options it put into the global database) goes
    with the last reference, not at some later cyclic garbage collection."""
    import gc
    import weakref

    from petsc4py import PETSc
    gc.collect()
    gc.disable()
    try:
        layer = SolveLayer(prob, KSPOptions.preset("gmres", max_it=3))
        f, kappa = inputs(prob)
        layer(f=f.requires_grad_(), kappa=kappa).sum().backward()
        system = weakref.ref(layer.system)
        del layer
        assert system() is None
        assert not [k for k in PETSc.Options().getAll() if k.startswith("fempdl")]
    finally:
        gc.enable()
