"""Manufactured solutions on the unstructured L-shape: L2 rates of P1 (2) and P2 (3).

The solve goes through SolveLayer (LU), so the rates check forms, Dirichlet
data, DOF ordering of inputs/outputs and the layer together.
"""
from __future__ import annotations

from mpi4py import MPI
import dolfinx.fem
import numpy as np
import pytest
import sympy
import torch
import ufl

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.core import _dolfinx
from fempdl.ksp_adjoint import KSPOptions

from helpers import integral

X, Y = sympy.symbols("x y")
U_EXACT = sympy.sin(sympy.pi * X) * sympy.cos(sympy.pi * Y / 2) + X * Y
# Linear, so the P1 coefficient space represents it exactly (a P1 kappa error
# would cap every rate at 2).
KAPPA = 1 + X / 2 + Y / 4
F = -(sympy.diff(KAPPA * sympy.diff(U_EXACT, X), X) + sympy.diff(KAPPA * sympy.diff(U_EXACT, Y), Y))


def as_numpy(expr):
    fn = sympy.lambdify((X, Y), expr, "numpy")
    return lambda x: fn(x[0], x[1]) + 0.0 * x[0]


def exact_ufl(x):
    return ufl.sin(ufl.pi * x[0]) * ufl.cos(0.5 * ufl.pi * x[1]) + x[0] * x[1]


def l2_error(prob, values: np.ndarray) -> float:
    uh = dolfinx.fem.Function(prob.V)
    uh.x.array[: prob.output_size] = values
    uh.x.scatter_forward()
    x = ufl.SpatialCoordinate(prob.V.mesh)
    err = _dolfinx.compile_form((uh - exact_ufl(x)) ** 2 * ufl.dx(degree=8))
    return float(np.sqrt(integral(err, prob.V.mesh.comm)))


def poisson_error(h: float, degree: int) -> tuple[int, float]:
    msh = mesh.load("lshape", MPI.COMM_WORLD, h=h)
    prob = forms.poisson.problem(msh, controls=("f",), degree=degree, kappa=as_numpy(KAPPA),
                                 g=as_numpy(U_EXACT))
    layer = SolveLayer(prob, KSPOptions.preset("lu"))
    # The source, interpolated into the solution space, is the layer's input.
    f = torch.as_tensor(prob.interpolate(as_numpy(F), "f"))
    u = layer(f=f).numpy()
    return prob.V.mesh.comm.allreduce(prob.output_size), l2_error(prob, u)


@pytest.mark.parametrize("degree,expected", [(1, 2.0), (2, 3.0)])
def test_poisson_l2_rate(degree, expected):
    results = [poisson_error(h, degree) for h in (0.2, 0.1, 0.05)]
    dofs = np.array([r[0] for r in results], dtype=float)
    errors = np.array([r[1] for r in results])
    # Unstructured meshes: measure the rate against N^(-1/2) ~ h in 2D.
    rates = -2.0 * np.log(errors[1:] / errors[:-1]) / np.log(dofs[1:] / dofs[:-1])
    assert np.all(np.abs(rates - expected) < 0.3), (dofs, errors, rates)
    assert errors[-1] < errors[0] / 2 ** (expected + 0.5)
