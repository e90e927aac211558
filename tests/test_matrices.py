"""PETSc matrices of bilinear forms (fempdl/core/matrices.py): on one rank the matrix PETSc solves shares
DOLFINx's CSR arrays and is assembled by DOLFINx's CSR assembler; the entries equal those of DOLFINx's
PETSc assembly bit for bit, a factorisation sees every reassembly, and blocked spaces keep the PETSc path.
Fixed numeric coefficients of the bundled forms are Constants (fempdl/forms/_common.py)."""
from mpi4py import MPI
import dolfinx.fem
import dolfinx.fem.petsc
import numpy as np
import pytest
import torch
from petsc4py import PETSc

from fempdl import NewtonOptions, NonlinearSolveLayer, SolveLayer, forms, mesh
from fempdl.core import matrices


@pytest.fixture(scope="module")
def lshape():
    return mesh.load("lshape", MPI.COMM_SELF, h=0.1)


def dolfinx_petsc(form, bcs=()):
    A = dolfinx.fem.petsc.create_matrix(form)
    A.zeroEntries()
    dolfinx.fem.petsc.assemble_matrix(A, form, list(bcs), 1.0)
    A.assemble()
    return A


def assert_same_entries(A, B):
    a, b = A.getValuesCSR(), B.getValuesCSR()
    for x, y in zip(a, b):
        assert np.array_equal(x, y)


def test_a_jacobian_is_assembled_into_the_csr_arrays_petsc_solves_bit_for_bit(lshape):
    problem = forms.nonlinear_diffusion.problem(lshape, controls=("u0", "f"), alpha=2.0, dt=0.01)
    problem.u.x.array[:] = np.linspace(-1.0, 1.0, len(problem.u.x.array))
    A = matrices.create_matrix(problem.J_form)
    assert A.getAttr("fempdl_csr") is not None and A.getType() == "seqaij"
    matrices.assemble_matrix_into(A, problem.J_form, problem.bcs)
    reference = dolfinx_petsc(problem.J_form, problem.bcs)
    assert_same_entries(A, reference)

    # A factorisation set up on A is redone after a reassembly at another state.
    ksp = PETSc.KSP().create(MPI.COMM_SELF)
    ksp.setOperators(A)
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    b, x = A.createVecs()
    b.set(1.0)
    ksp.solve(b, x)
    problem.u.x.array[:] *= 3.0
    matrices.assemble_matrix_into(A, problem.J_form, problem.bcs)
    ksp.solve(b, x)
    fresh = PETSc.KSP().create(MPI.COMM_SELF)
    fresh.setOperators(dolfinx_petsc(problem.J_form, problem.bcs))
    fresh.setType("preonly")
    fresh.getPC().setType("lu")
    y = x.duplicate()
    fresh.solve(b, y)
    assert np.array_equal(x.getArray(), y.getArray())
    for obj in (ksp, fresh, A, reference, b, x, y):
        obj.destroy()


def test_another_form_of_the_same_spaces_goes_through_petsc_and_a_blocked_space_keeps_petsc(lshape):
    heat = forms.heat.problem(lshape, controls=("u0", "f"))
    V = heat.V
    mass = dolfinx.fem.form(ufl_mass(V))
    A = matrices.create_matrix(heat.a_form)
    matrices.assemble_matrix_into(A, mass)            # not the form A was made for: PETSc's insertion
    assert_same_entries(A, dolfinx_petsc(mass))
    elasticity = forms.elasticity.problem(lshape, controls=("f",))
    B = matrices.create_matrix(elasticity.a_form)
    assert B.getAttr("fempdl_csr") is None and B.getBlockSize() == 2
    matrices.assemble_matrix_into(B, elasticity.a_form, elasticity.bcs)
    assert_same_entries(B, dolfinx_petsc(elasticity.a_form, elasticity.bcs))


def ufl_mass(V):
    import ufl
    return ufl.TrialFunction(V) * ufl.TestFunction(V) * ufl.dx


def test_a_fixed_number_is_a_constant_and_solves_as_the_field_holding_it(lshape):
    fixed = forms.nonlinear_diffusion.problem(lshape, controls=("u0", "f"), kappa=2.0, alpha=0.5, dt=0.01)
    field = forms.nonlinear_diffusion.problem(lshape, controls=("u0", "f", "kappa", "alpha"), dt=0.01)
    kinds = {c.name: type(c).__name__ for c in fixed.F.coefficients()}
    assert "kappa" not in kinds and "alpha" not in kinds and len(fixed.F.constants()) == 3   # kappa, alpha, dt
    assert isinstance(field.control("kappa"), dolfinx.fem.Function)
    n = fixed.output_size
    g = torch.Generator().manual_seed(0)
    u0, f = torch.rand(n, dtype=torch.float64, generator=g), torch.rand(n, dtype=torch.float64, generator=g)
    options = NewtonOptions(rtol=1e-13, atol=1e-15, ksp="lu")
    a = NonlinearSolveLayer(fixed, options)(u0=u0, f=f)
    ones = torch.ones(field.control_size("kappa"), dtype=torch.float64)
    b = NonlinearSolveLayer(field, options)(u0=u0, f=f, kappa=2.0 * ones, alpha=0.5 * ones)
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
    heat = forms.heat.problem(lshape, controls=("u0",), kappa=lambda x: 1.0 + x[0] ** 2)
    assert "kappa" in {c.name for c in heat.a.coefficients()}                     # a callable is a field
    SolveLayer(heat, "lu").close()


@pytest.mark.parametrize("kappa, message", [(-1.0, "kappa must be > 0 everywhere"),
                                            (float("nan"), "kappa must be finite")])
def test_a_bad_fixed_number_is_refused(lshape, kappa, message):
    with pytest.raises(ValueError, match=message):
        forms.poisson.problem(lshape, controls=("f",), kappa=kappa)
