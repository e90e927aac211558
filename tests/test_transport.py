"""Marker transport step: rates against a manufactured solution, mass conservation, gradients, Péclet check."""
from __future__ import annotations

import warnings

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
M_EXACT = sympy.sin(sympy.pi * X) * sympy.cos(sympy.pi * Y / 2) + X * Y
W_EXACT = (1.0 + Y / 2, sympy.sin(X))                # not divergence-free on purpose: div(m w) is tested in full
KAPPA, DT = 0.05, 0.1


def scalar_callable(expr):
    fn = sympy.lambdify((X, Y), expr, "numpy")
    return lambda x: fn(x[0], x[1]) + 0.0 * x[0]


def vector_callable(exprs):
    fns = [sympy.lambdify((X, Y), e, "numpy") for e in exprs]
    return lambda x: np.stack([f(x[0], x[1]) + 0.0 * x[0] for f in fns])


def _ufl(expr, x):
    return sympy.lambdify((X, Y), expr, modules=[{"sin": ufl.sin, "cos": ufl.cos, "pi": ufl.pi}, "math"])(x[0], x[1])


def transport_error(h: float, degree: int, supg: bool) -> tuple[int, float]:
    """A stationary exact solution: m_prev = m, f = div(m w) - kappa Δm; m = m_exact on the boundary."""
    f = sum(sympy.diff(M_EXACT * c, v) for c, v in zip(W_EXACT, (X, Y))) \
        - KAPPA * (sympy.diff(M_EXACT, X, 2) + sympy.diff(M_EXACT, Y, 2))
    msh = mesh.load("lshape", MPI.COMM_WORLD, h=h)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")             # cell Péclet ~ 1 on the coarsest mesh without SUPG
        prob = forms.transport.problem(msh, controls=("w", "m_prev", "f"), kappa=KAPPA, dt=DT, degree=degree,
                                       supg=supg, g=scalar_callable(M_EXACT), dirichlet=None)
    inputs = {"w": prob.interpolate(vector_callable(W_EXACT), "w"),
              "m_prev": prob.interpolate(scalar_callable(M_EXACT), "m_prev"),
              "f": prob.interpolate(scalar_callable(f), "f")}
    m = SolveLayer(prob, KSPOptions.preset("lu"))(**{k: torch.as_tensor(v) for k, v in inputs.items()}).numpy()
    mh = dolfinx.fem.Function(prob.V)
    mh.x.array[: prob.output_size] = m
    mh.x.scatter_forward()
    x = ufl.SpatialCoordinate(msh.mesh)
    err = _dolfinx.compile_form((mh - _ufl(M_EXACT, x)) ** 2 * ufl.dx(degree=8))
    return prob.V.mesh.comm.allreduce(prob.output_size), float(np.sqrt(integral(err, msh.mesh.comm)))


@pytest.mark.parametrize("degree,supg", [(1, True), (1, False), (2, True)])
def test_transport_l2_rate_against_a_manufactured_solution(degree, supg):
    results = np.array([transport_error(h, degree, supg) for h in (0.2, 0.1, 0.05)])
    dofs, errors = results[:, 0], results[:, 1]
    rates = -2.0 * np.log(errors[1:] / errors[:-1]) / np.log(dofs[1:] / dofs[:-1])
    expected = degree + 1.0
    assert abs(rates[-1] - expected) < 0.3, (dofs, errors, rates)
    assert errors[-1] < errors[0] / 2 ** (expected + 0.5), errors


@pytest.fixture(scope="module")
def coarse():
    return mesh.load("lshape", MPI.COMM_WORLD, h=0.2)


def no_slip_velocity(prob, seed: int) -> torch.Tensor:
    """A random rotation-like velocity, zero at the boundary nodes (so w = 0 on the whole boundary)."""
    space = prob.control("w").function_space
    nodes = dolfinx.fem.locate_dofs_topological(space, 1, _dolfinx.boundary_facets(space.mesh))
    w = torch.as_tensor(prob.interpolate(lambda x: np.stack([-x[1], x[0]]), "w")).reshape(-1, 2)
    w = w * (1 + 0.3 * torch.rand(w.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(seed)))
    w[torch.as_tensor(nodes[nodes < len(w)], dtype=torch.long)] = 0.0
    return w.reshape(-1)


@pytest.mark.parametrize("supg", [True, False])
def test_marker_mass_is_conserved_on_an_enclosed_domain(coarse, supg):
    """No Dirichlet part and w = 0 on the boundary: ∫ m is the same after every step, for any w."""
    prob = forms.transport.problem(coarse, controls=("w", "m_prev"), kappa=0.05, dt=0.1, supg=supg)
    layer = SolveLayer(prob, KSPOptions.preset("lu"))
    w = 3.0 * no_slip_velocity(prob, 0)
    m = torch.as_tensor(prob.interpolate(lambda x: np.exp(-10 * ((x[0] + 0.5) ** 2 + (x[1] - 0.5) ** 2))))
    mass_fn = dolfinx.fem.Function(prob.V)
    mass_form = _dolfinx.compile_form(mass_fn * ufl.dx)

    def mass(values):
        mass_fn.x.array[: prob.output_size] = values.numpy()
        return integral(mass_form, coarse.mesh.comm)

    m0, m_start = mass(m), m.clone()
    masses = []
    for _ in range(5):
        m = layer(w=w, m_prev=m)
        masses.append(mass(m))
    assert float((m - m_start).abs().max()) > 1e-2                # the marker moved
    np.testing.assert_allclose(masses, m0, rtol=1e-12, atol=0)


def test_without_supg_the_velocity_enters_the_matrix_affinely(coarse):
    galerkin = forms.transport.problem(coarse, supg=False, kappa=1.0)
    stabilised = forms.transport.problem(coarse, supg=True)
    assert galerkin.affine_matrix_controls == {"w"} and "m_prev" in galerkin.affine_rhs_controls
    assert stabilised.affine_matrix_controls == frozenset() and "m_prev" not in stabilised.affine_rhs_controls


@pytest.mark.parametrize("control", ["w", "m_prev"])
def test_transport_step_gradcheck(coarse, control):
    prob = forms.transport.problem(coarse, controls=("w", "m_prev"), kappa=0.01, dt=0.1)
    layer = SolveLayer(prob, KSPOptions.preset("lu"))
    gen = torch.Generator().manual_seed(3)
    values = {"w": torch.as_tensor(prob.interpolate(lambda x: np.stack([-x[1], x[0]]), "w"))
              + 0.2 * torch.rand(2, prob.control_size("w"), generator=gen, dtype=torch.float64),
              "m_prev": torch.rand(2, prob.control_size("m_prev"), generator=gen, dtype=torch.float64)}
    assert torch.autograd.gradcheck(lambda x: layer(**{**values, control: x}),
                                    (values[control].clone().requires_grad_(),), eps=1e-6, atol=1e-7, rtol=1e-6)


def test_without_supg_a_high_cell_peclet_number_warns(coarse):
    with pytest.warns(UserWarning, match="Péclet"):
        forms.transport.problem(coarse, kappa=1e-4, supg=False, w=(1.0, 0.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        forms.transport.problem(coarse, kappa=1e-4, w=(1.0, 0.0))            # SUPG on
        forms.transport.problem(coarse, kappa=1.0, supg=False, w=(1.0, 0.0))
    with pytest.raises(ValueError, match="kappa=0 without SUPG"):
        forms.transport.problem(coarse, kappa=0.0, supg=False)


def test_velocity_space_must_live_on_the_same_mesh(coarse):
    other = mesh.load("lshape", MPI.COMM_WORLD, h=0.5)
    space = _dolfinx.function_space(other.mesh, "Lagrange", 2, shape=(2,))
    with pytest.raises(ValueError, match="velocity_space"):
        forms.transport.problem(coarse, velocity_space=space)
