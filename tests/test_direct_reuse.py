"""Direct solves factorise once per matrix: the adjoint transposes the forward's factor, and symmetric
problems may use Cholesky.

The observable is the matrix itself: an adjoint that neither reassembles nor restores A leaves its
version (and PETSc's state, which decides whether the factor is rebuilt) where the forward left it.
"""
from __future__ import annotations

from mpi4py import MPI
import dolfinx.mesh
import numpy as np
import pytest
import torch
import ufl

from fempdl import KSPOptions, Problem, SolveLayer, forms
from fempdl.core import _dolfinx

F64 = torch.float64


@pytest.fixture(scope="module")
def box():
    return dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [2, 1, 1]], [4, 2, 2], dolfinx.mesh.CellType.hexahedron)


@pytest.fixture(scope="module")
def elastic(box):
    return forms.elasticity.problem(box, controls=("E", "f"), f=(0.0, 0.0, -1.0))


def young(prob, seed: int) -> torch.Tensor:
    return torch.as_tensor(1.0 + np.random.default_rng(seed).random(prob.control_size("E")))


def loss_and_grad(layer, E: torch.Tensor, w: torch.Tensor):
    E = E.clone().requires_grad_()
    u = layer(E=E)
    (u * w).sum().backward()
    return u.detach(), E.grad


@pytest.mark.parametrize("batched", [False, True], ids=["shared", "one-sample batch"])
@pytest.mark.parametrize("preset", ["lu", "cholesky"])
def test_the_adjoint_reuses_the_forward_matrix_and_factor(elastic, preset, batched):
    layer = SolveLayer(elastic, preset)
    E = young(elastic, 0)[None] if batched else young(elastic, 0)
    w = torch.linspace(-1, 1, elastic.output_size, dtype=F64)
    E_in = E.clone().requires_grad_()
    u = layer(E=E_in)
    version = layer.system.matrix_version
    (u * w).sum().backward()
    assert layer.system.matrix_version == version        # no reassembly, no restore: the factor is reused
    # The same gradient as a layer whose adjoint assembles and factorises A afresh.
    E_ref = E.clone().requires_grad_()
    fresh = SolveLayer(elastic, preset)
    u_ref = fresh(E=E_ref)
    fresh.system._A_inputs = None            # forget what A holds: the adjoint assembles it again
    (u_ref * w).sum().backward()
    assert fresh.system.matrix_version > 1
    assert (u - u_ref).abs().max() <= 1e-12 * u_ref.abs().max()
    assert (E_in.grad - E_ref.grad).abs().max() <= 1e-12 * E_ref.grad.abs().max()


def test_a_new_control_value_reassembles_before_the_adjoint(elastic):
    """The fingerprint, not the call order, decides: a call with other values in between makes the
    adjoint of the first call assemble A again with its own values."""
    layer = SolveLayer(elastic, "lu")
    w = torch.linspace(-1, 1, elastic.output_size, dtype=F64)
    E1 = young(elastic, 2).requires_grad_()
    u1 = layer(E=E1)
    with torch.no_grad():
        layer(E=young(elastic, 3))
    (u1 * w).sum().backward()
    _, expected = loss_and_grad(SolveLayer(elastic, "lu"), young(elastic, 2), w)
    assert (E1.grad - expected).abs().max() <= 1e-12 * expected.abs().max()


def test_cholesky_equals_lu_on_a_symmetric_problem(elastic):
    w = torch.linspace(-1, 1, elastic.output_size, dtype=F64)
    u_c, g_c = loss_and_grad(SolveLayer(elastic, "cholesky"), young(elastic, 4), w)
    u_l, g_l = loss_and_grad(SolveLayer(elastic, "lu"), young(elastic, 4), w)
    # Both are backward-stable direct solves of the same SPD system (condition number ~1e3 here).
    assert (u_c - u_l).abs().max() <= 1e-10 * u_l.abs().max()
    assert (g_c - g_l).abs().max() <= 1e-10 * g_l.abs().max()


def test_cholesky_is_refused_on_a_problem_not_declared_symmetric(box):
    burgers = forms.burgers.problem(dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 4, 4), controls=("w",))
    assert not burgers.symmetric
    with pytest.raises(ValueError, match="factorises A as symmetric, but this problem is not declared symmetric"):
        SolveLayer(burgers, "cholesky")
    with pytest.raises(ValueError, match="not declared symmetric"):
        SolveLayer(burgers, KSPOptions.preset("lu", adjoint=KSPOptions.preset("cholesky")))


def test_a_false_symmetric_declaration_is_caught_before_factorising():
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 4, 4)
    V = _dolfinx.function_space(msh, "Lagrange", 1)
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    f = dolfinx.fem.Function(V)
    a = ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx + u.dx(0) * v * ufl.dx      # advection: not symmetric
    bc = _dolfinx.dirichlet_bc(V, 0.0, _dolfinx.boundary_facets(msh))
    prob = Problem(a, f * v * ufl.dx, [bc], {"f": f}, symmetric=True)
    with pytest.raises(ValueError, match="declared symmetric .* but its assembled matrix is not"):
        SolveLayer(prob, "cholesky")(f=torch.ones(prob.control_size("f"), dtype=F64))
    with pytest.raises(TypeError, match="symmetric must be a bool"):
        Problem(a, f * v * ufl.dx, [bc], {"f": f}, symmetric="yes")


def test_the_symmetric_forms_are_declared_so(box):
    square = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 4, 4)
    assert forms.poisson.problem(square).symmetric and forms.heat.problem(square).symmetric
    assert forms.elasticity.problem(box).symmetric
    assert not forms.burgers.problem(square).symmetric
