"""A failed Newton solve names what went wrong and a fix that applies, not a neighbouring cause.

Three failures used to be misreported: a Jacobian that is NaN at the initial guess (the p-Laplacian's
|grad u|^(p-2) at grad u = 0) came out as a NaN residual with "reduce the load"; a missing Dirichlet
condition (a singular J) as "raise converged_max_it"; a failed line search as a NaN residual with
"use snes_type='newtonls'", the method in use. The problems here are small and built from UFL.
"""
from __future__ import annotations

from mpi4py import MPI
import dolfinx.fem
import dolfinx.mesh
import numpy as np
import pytest
import torch
import ufl
from petsc4py import PETSc

from fempdl import KSPOptions, NewtonOptions, NonlinearProblem, NonlinearSolveLayer, SolverFailedError
from fempdl.core import _dolfinx
from fempdl.solve.newton_options import LINE_SEARCHES
from fempdl.solve.newton_stats import SNES_REASON_NAMES, NewtonFailure, NewtonSolveStats, explain

F64 = torch.float64


@pytest.fixture(scope="module")
def V():
    return _dolfinx.function_space(dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 6, 6), "Lagrange", 1)


def zero_on_boundary(V):
    msh = V.mesh
    facets = dolfinx.mesh.locate_entities_boundary(msh, msh.topology.dim - 1, lambda x: np.full(x.shape[1], True))
    dofs = dolfinx.fem.locate_dofs_topological(V, msh.topology.dim - 1, facets)
    return dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), dofs, V)


def failure(layer, **controls) -> str:
    n = layer.problem.control_size("f")
    values = {name: torch.full((n,), value, dtype=F64) for name, value in controls.items()}
    with pytest.raises(SolverFailedError) as info:
        layer(**values)
    return str(info.value)


# ------------------------------------------------------------------ a Jacobian NaN at the initial guess
def p_laplacian(V, p: float) -> NonlinearProblem:
    """-div(kappa |grad u|^(p-2) grad u) = f, u = 0 on the boundary; controls f and kappa."""
    u, v = dolfinx.fem.Function(V), ufl.TestFunction(V)
    f, kappa = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
    F = (kappa * ufl.inner(ufl.grad(u), ufl.grad(u)) ** ((p - 2) / 2) * ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx
         - f * v * ufl.dx)
    return NonlinearProblem(F, u, [zero_on_boundary(V)], controls={"f": f, "kappa": kappa})


@pytest.mark.parametrize("p, residual", [
    (3.0, "F(u) itself is finite there: the residual is NaN only through J"),   # |grad u|^(p-4) in J only
    (1.5, "F(u) is NaN or inf there too"),                                      # |grad u|^(p-2) in F as well
])
def test_a_jacobian_undefined_at_the_initial_guess_is_named_as_the_jacobian(V, p, residual):
    """From zero, grad u = 0: the p-Laplacian's coefficient is undefined there. Named as J's NaN at the
    initial guess, with the controls J depends on, a start away from it and a regularised coefficient;
    not a load to reduce. The start the message suggests works."""
    layer = NonlinearSolveLayer(p_laplacian(V, p), NewtonOptions(ksp="lu"))
    message = failure(layer, f=1.0, kappa=1.0)
    assert "its Jacobian J(u) became NaN or inf at the initial guess (J depends on the controls ['kappa']" in message
    assert residual in message
    assert "initial_guess=" in message and "(eps + |grad u|^2)^((p-2)/2)" in message
    assert "reduce the load" not in message and "the residual became NaN" not in message
    n = layer.problem.control_size("f")
    x = torch.as_tensor(layer.problem.dof_coordinates()[:, :2], dtype=F64)
    start = (x * (1 - x)).prod(dim=1)              # zero on the boundary, grad u != 0 almost everywhere
    u = layer(f=torch.ones(n, dtype=F64), kappa=torch.ones(n, dtype=F64), initial_guess=start)
    assert layer.stats.last_newton.ok and torch.isfinite(u).all()


# ------------------------------------------------------------------ a missing Dirichlet condition
def neumann_diffusion(V, *, nullspace: bool = False) -> NonlinearProblem:
    """-div((1 + u^2) grad u) = f with no Dirichlet condition: u is fixed only up to a constant."""
    u, v, f = dolfinx.fem.Function(V), ufl.TestFunction(V), dolfinx.fem.Function(V)
    F = (1 + u ** 2) * ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx - f * v * ufl.dx
    n = V.dofmap.index_map.size_local
    return NonlinearProblem(F, u, [], controls={"f": f}, nullspace=[np.ones(n)] if nullspace else ())


@pytest.mark.parametrize("ksp, says", [
    ("lu", "the residual stopped decreasing at"),                          # MUMPS's steps on a singular J
    ("gmres", "its linear solve failed (DIVERGED_BREAKDOWN"),              # GMRES breaks down on it
    (KSPOptions.preset("jacobi", max_it=20), "the residual did not decrease in 50 steps"),
])
def test_a_missing_dirichlet_condition_is_named(V, ksp, says):
    message = failure(NonlinearSolveLayer(neumann_diffusion(V), NewtonOptions(ksp=ksp)), f=1.0)
    assert says in message
    assert "the problem has no Dirichlet condition" in message and "add a Dirichlet condition (bcs=)" in message
    assert "declare the null space (nullspace=)" in message
    assert "raise converged_max_it" not in message


def test_a_declared_null_space_with_a_load_outside_its_range_names_the_load(V):
    message = failure(NonlinearSolveLayer(neumann_diffusion(V, nullspace=True), NewtonOptions(ksp="lu")), f=1.0)
    assert "the residual stopped decreasing" in message and "a load orthogonal to it" in message
    assert "raise converged_max_it" not in message


# ------------------------------------------------------------------ a failed line search
def wrong_jacobian(V, *, nan_beyond: bool) -> NonlinearProblem:
    """J = -dF/du: its step increases ||F||, so every line search fails. With ``nan_beyond`` the
    conductivity sqrt(1 + u) is NaN where u < -1, which the line search's trial steps reach."""
    u, v, f = dolfinx.fem.Function(V), ufl.TestFunction(V), dolfinx.fem.Function(V)
    q = ufl.sqrt(1 + u) if nan_beyond else 1 + u ** 2
    F = q * ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx - f * v * ufl.dx
    J = -ufl.derivative(F, u, ufl.TrialFunction(V))
    return NonlinearProblem(F, u, [zero_on_boundary(V)], controls={"f": f}, J=J)


@pytest.mark.parametrize("nan_beyond, load", [(True, 30.0), (False, 10.0)])
def test_a_failed_line_search_is_named_with_fixes_other_than_the_method_in_use(V, nan_beyond, load):
    layer = NonlinearSolveLayer(wrong_jacobian(V, nan_beyond=nan_beyond), NewtonOptions(snes_type="newtonls", ksp="lu"))
    message = failure(layer, f=load)
    assert "its line search ('bt') found no step along the Newton direction that decreases ||F||" in message
    assert "SNES reason DIVERGED_LINE_SEARCH" in message
    assert "linesearch='basic'" in message and "linesearch='l2'" in message and "linesearch='bt'" not in message
    assert "snes_type='newtonls'" not in message and "the residual became NaN" not in message
    assert "J= is not dF/du" in message
    assert ("were cut back" in message) == nan_beyond == layer.stats.last_newton.nonfinite_residual


# ------------------------------------------------------------------ every message, every method
def stats(reason_name: str, norms=(1.0, 0.5)) -> NewtonSolveStats:
    reason = {name: code for code, name in SNES_REASON_NAMES.items()}[reason_name]
    return NewtonSolveStats(steps=len(norms) - 1, reason=reason, reason_name=reason_name, residual_norms=tuple(norms),
                            inner_iterations=1, capped=False, ok=False, time=0.0)


METHODS = [NewtonOptions(snes_type="newton", ksp="lu"), NewtonOptions(snes_type="newtontr", ksp="lu"),
           *(NewtonOptions(snes_type="newtonls", linesearch=ls, ksp="lu") for ls in LINE_SEARCHES)]


@pytest.mark.parametrize("options", METHODS, ids=lambda o: f"{o.snes_type}-{o.linesearch}")
@pytest.mark.parametrize("reason_name", sorted(n for n in SNES_REASON_NAMES.values() if n.startswith("DIVERGED")))
def test_no_message_suggests_the_method_in_use(options, reason_name):
    cause, fix = explain(options, stats(reason_name), NewtonFailure(inner_reason="DIVERGED_BREAKDOWN"))
    assert f"snes_type={options.snes_type!r}" not in fix, fix
    if options.linesearch is not None:
        assert f"linesearch={options.linesearch!r}" not in fix, fix
    assert cause and fix


def test_a_residual_at_its_round_off_floor_is_not_called_singular():
    """A residual that wanders at round-off is not one that stopped decreasing: the message keeps the
    tolerance fixes, and names a singular J only where the last steps left ||F|| unchanged."""
    options = NewtonOptions(ksp="lu")
    floor = stats("DIVERGED_MAX_IT", (1.0, 1e-3, 6e-11, 4e-11, 7e-11, 5e-11))
    assert "raise converged_max_it" in explain(options, floor, NewtonFailure())[1]
    stuck = stats("DIVERGED_MAX_IT", (1.0, 0.3, 0.25, 0.25, 0.25, 0.25))
    fix = explain(options, stuck, NewtonFailure())[1]
    assert "stopped decreasing at 2.500e-01" in fix and "a missing Dirichlet condition" in fix
    assert "raise converged_max_it" not in fix
