"""CappedSolver: exact iteration counts, exact Jacobi iterates, transposes, options handling."""
from __future__ import annotations

import dolfinx.fem
import dolfinx.fem.petsc
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg  # noqa: F401  (sp.linalg)
import ufl
from petsc4py import PETSc

from fempdl.core import _dolfinx
from fempdl.ksp_adjoint import CappedSolver, KSPOptions, SolverFailedError, SolverWarning

from helpers import CAPPED


@pytest.fixture(scope="module")
def advection_matrix(lshape):
    """A non-symmetric, diagonally dominant operator (diffusion + advection + mass)
    with Dirichlet rows, so transposed solves differ from forward ones."""
    V = _dolfinx.function_space(lshape.mesh, "Lagrange", 1)
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    w = ufl.as_vector((3.0, -2.0))
    a = (0.1 * ufl.inner(ufl.grad(u), ufl.grad(v)) + ufl.inner(w, ufl.grad(u)) * v + 20.0 * u * v) * ufl.dx
    bc = _dolfinx.dirichlet_bc(V, dolfinx.fem.Constant(lshape.mesh, 0.0), _dolfinx.boundary_facets(lshape.mesh))
    A = dolfinx.fem.petsc.assemble_matrix(_dolfinx.compile_form(a), bcs=[bc])
    A.assemble()
    yield A
    A.destroy()


def as_scipy(A: PETSc.Mat) -> sp.csr_matrix:
    indptr, indices, data = A.getValuesCSR()
    return sp.csr_matrix((data, indices, indptr), shape=A.getSize())


def vectors(A, seed=0):
    rng = np.random.default_rng(seed)
    b, x = A.createVecLeft(), A.createVecRight()
    b.setArray(rng.standard_normal(b.getLocalSize()))
    return b, x


@pytest.mark.parametrize("solver", ["jacobi", "gmres"])  # CG needs symmetry: tested below
@pytest.mark.parametrize("k", [1, 7, 40])
def test_capped_solve_runs_exactly_max_it(advection_matrix, solver, k):
    b, x = vectors(advection_matrix)
    with CappedSolver(advection_matrix, CAPPED[solver](k)) as s:
        forward = s.solve(b, x)
        backward = s.solve_transpose(b, x)
        assert (forward.iterations, backward.iterations) == (k, k)
        assert forward.capped and backward.capped and forward.ok
        assert forward.reason_name in ("DIVERGED_MAX_IT", "CONVERGED_ITS")
        assert (s.stats.forward_iterations, s.stats.backward_iterations) == (k, k)


def test_capped_cg_runs_exactly_max_it(lshape):
    from fempdl.forms import poisson
    prob = poisson.problem(lshape)
    A = dolfinx.fem.petsc.assemble_matrix(prob.a_form, bcs=list(prob.bcs))
    A.assemble()
    b, x = vectors(A)
    with CappedSolver(A, CAPPED["cg"](13)) as s:
        assert s.solve(b, x).iterations == 13
        assert s.solve_transpose(b, x).iterations == 13
    A.destroy()


@pytest.mark.parametrize("omega", [None, 0.7])
def test_jacobi_iterate_and_transpose_match_the_k_step_formula(advection_matrix, omega):
    """x_{k+1} = x_k + omega D^{-1} (b - A x_k) from x_0 = 0, and the same on A^T."""
    k = 9
    extra = {} if omega is None else {"ksp_richardson_scale": omega}
    A = as_scipy(advection_matrix)
    d = A.diagonal()
    b, x = vectors(advection_matrix)
    rhs = b.getArray().copy()
    for op, method in ((A, "solve"), (A.T.tocsr(), "solve_transpose")):
        ref = np.zeros_like(rhs)
        for _ in range(k):
            ref = ref + (omega or 1.0) * (rhs - op @ ref) / d
        with CappedSolver(advection_matrix, KSPOptions(max_it=k, petsc_options=extra)) as s:
            getattr(s, method)(b, x)
        np.testing.assert_allclose(x.getArray(), ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())


def test_dot_product_test_of_capped_jacobi_transpose(advection_matrix):
    """<c, S_K b> = <S_K^T c, b>: the transposed capped solve is the exact adjoint of the K-step map."""
    b, x = vectors(advection_matrix, 1)
    c, y = vectors(advection_matrix, 2)
    with CappedSolver(advection_matrix, KSPOptions(max_it=11)) as s:
        s.solve(b, x)
        s.solve_transpose(c, y)
    lhs, rhs = c.dot(x), y.dot(b)
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)


@pytest.mark.parametrize("options", [KSPOptions.preset("lu"), KSPOptions.preset("gmres", rtol=1e-13)],
                         ids=["lu", "gmres"])
def test_dot_product_test_of_converged_transpose(advection_matrix, options):
    """<c, A^{-1} b> = <A^{-T} c, b> for converged solves."""
    A = as_scipy(advection_matrix)
    b, x = vectors(advection_matrix, 1)
    c, y = vectors(advection_matrix, 2)
    with CappedSolver(advection_matrix, options) as s:
        s.solve(b, x)
        s.solve_transpose(c, y)
    assert abs(c.dot(x) - y.dot(b)) <= 1e-9 * abs(c.dot(x))
    np.testing.assert_allclose(A.T @ y.getArray(), c.getArray(), atol=1e-8)


def test_max_it_moves_the_cap_and_the_adjoint_follows(advection_matrix):
    b, x = vectors(advection_matrix)
    with CappedSolver(advection_matrix, KSPOptions(max_it=3)) as s:
        s.max_it = 17
        assert s.solve(b, x).iterations == 17
        assert s.solve_transpose(b, x).iterations == 17
        with pytest.raises(ValueError, match="max_it must be >= 1"):
            s.max_it = 0
        assert s.max_it == 17


def test_adjoint_override_decouples_the_cap(advection_matrix):
    b, x = vectors(advection_matrix)
    opts = KSPOptions(max_it=4, adjoint=KSPOptions.preset("gmres", max_it=9))
    with CappedSolver(advection_matrix, opts) as s:
        s.max_it = 6
        assert s.solve(b, x).iterations == 6
        assert s.solve_transpose(b, x).iterations == 9


def test_residual_norm_only_when_a_tolerance_is_asked(advection_matrix):
    b, x = vectors(advection_matrix)
    with CappedSolver(advection_matrix, KSPOptions(max_it=50)) as s:
        assert s.solve(b, x).residual_norm is None
    with CappedSolver(advection_matrix, KSPOptions(max_it=5000, rtol=1e-6)) as s:
        stats = s.solve(b, x)
    assert stats.reason_name == "CONVERGED_RTOL" and not stats.capped
    assert 0 < stats.iterations < 5000
    assert stats.residual_norm <= 1e-6 * b.norm() * 1.0001


def test_converged_mode_reaches_rtol(advection_matrix):
    A = as_scipy(advection_matrix)
    b, x = vectors(advection_matrix)
    with CappedSolver(advection_matrix, KSPOptions.preset("gmres")) as s:
        stats = s.solve(b, x)
    assert stats.ok and stats.reason > 0
    assert np.linalg.norm(A @ x.getArray() - b.getArray()) <= 1e-8 * b.norm()


def test_petsc_options_are_removed_from_the_global_database(advection_matrix):
    opts = KSPOptions.preset("gmres", max_it=5, petsc_options={"ksp_gmres_modifiedgramschmidt": None})
    with CappedSolver(advection_matrix, opts) as s:
        b, x = vectors(advection_matrix)
        assert s.solve(b, x).iterations == 5
    assert not [k for k in PETSc.Options().getAll() if k.startswith("fempdl")]


def test_zero_right_hand_side_gives_zero(advection_matrix):
    b, x = vectors(advection_matrix)
    b.set(0.0)
    with CappedSolver(advection_matrix, KSPOptions.preset("gmres", max_it=10)) as s:
        stats = s.solve(b, x)
    assert stats.ok and x.norm() == 0.0


def test_presets():
    assert KSPOptions.preset("jacobi").ksp_type == "richardson"
    assert KSPOptions.preset("jacobi", max_it=5).max_it == 5
    assert KSPOptions.preset("lu").direct
    assert KSPOptions.preset("gmres").gmres_restart == 30
    opts = KSPOptions(max_it=3)
    assert opts.adjoint_options is opts
    assert opts.with_max_it(8).max_it == 8 and opts.max_it == 3


@pytest.mark.parametrize("adjoint_operator", ["auto", "assembled"])
@pytest.mark.parametrize("on_failure", ["raise", "warn"])
def test_a_failed_factorisation_does_not_outlive_its_matrix(lshape, adjoint_operator, on_failure):
    """MUMPS fails on a matrix with a NaN diagonal entry, and PETSc keeps that preconditioner failed:
    the next solve on the KSP failed too (or stopped with PETSc error 76), however sane the matrix
    reassembled in place had become. The solver renews a failed KSP at its next solve, forward and
    transposed, so a training loop outlives one bad sample."""
    V = _dolfinx.function_space(lshape.mesh, "Lagrange", 1)
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    form = _dolfinx.compile_form((0.1 * ufl.inner(ufl.grad(u), ufl.grad(v))
                                  + ufl.inner(ufl.as_vector((3.0, -2.0)), ufl.grad(u)) * v + 20.0 * u * v) * ufl.dx)
    A = dolfinx.fem.petsc.assemble_matrix(form)
    A.assemble()
    b, x = vectors(A)
    M = as_scipy(A).tocsc()
    expected = {"forward": sp.linalg.spsolve(M, b.getArray()), "backward": sp.linalg.spsolve(M.T.tocsc(), b.getArray())}
    options = KSPOptions.preset("lu", petsc_options={"pc_factor_mat_solver_type": "mumps"}, on_failure=on_failure,
                                adjoint_operator=adjoint_operator)
    with CappedSolver(A, options) as s:
        for direction, solve in (("forward", s.solve), ("backward", s.solve_transpose)):
            assert solve(b, x).ok
            A.setValue(5, 5, np.nan)
            A.assemble()
            if on_failure == "raise":
                with pytest.raises(SolverFailedError, match="NaN or inf"):
                    solve(b, x)
            else:
                with pytest.warns(SolverWarning):
                    assert not solve(b, x).ok           # DIVERGED_PC(SETUP)_FAILED
            for _ in range(2):              # reassembled as a Newton step or a new sample would
                A.zeroEntries()
                dolfinx.fem.petsc.assemble_matrix(A, form)
                A.assemble()
                assert solve(b, x).ok
                np.testing.assert_allclose(x.getArray(), expected[direction], rtol=1e-10, atol=1e-14)
    A.destroy()


@pytest.mark.parametrize("entry, defect", [
    (np.nan, "NaN or inf entries"), (np.inf, "NaN or inf entries"), (-np.inf, "NaN or inf entries"),
    (1e200, None),                       # finite, though its square overflows the Frobenius norm
])
def test_operator_defect_sees_every_non_finite_entry(advection_matrix, entry, defect):
    """A NaN in a row escaped the infinity norm (a NaN row sum never exceeds the largest one), so a
    Jacobian with NaN entries reached MUMPS; an entry past 1e154 is finite and no defect."""
    from fempdl.solve.assembly import operator_defect
    A = advection_matrix.duplicate(copy=True)
    assert operator_defect(A) is None
    indptr, indices, _ = A.getValuesCSR()
    row = 7
    A.setValue(row, [c for c in indices[indptr[row]:indptr[row + 1]] if c != row][0], entry)
    A.assemble()
    assert operator_defect(A) == defect
    A.destroy()
