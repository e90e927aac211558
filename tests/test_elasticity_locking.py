"""Locking of linear elasticity as nu -> 1/2 (issue #55): the displacement-only form warns where it
locks, and the mixed Taylor-Hood (u, p) form stays accurate, converges at its rate and has exact
gradients for the body force and Young's modulus.

The manufactured displacements are divergence-free, so each solves the problem for every nu with
f = -mu Δu and p = 0: the error against it is the discretisation's own, whatever lmbda is.
``clamped`` (zero on the unit square's boundary) is the problem the warning's threshold was
measured on; ``divergence_free`` has nonzero Dirichlet data (P1 locks far less on it: locking
depends on the problem, the warning's rule is for the clamped one).
"""
from __future__ import annotations

import warnings

from mpi4py import MPI
import dolfinx.mesh
import numpy as np
import pytest
import sympy
import torch
import ufl

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.core import _dolfinx
from fempdl.forms._common import LOCKING_LAME_RATIO

from helpers import integral

F64 = torch.float64
X, Y = sympy.symbols("x y")


def clamped(x, y, m):
    """curl(sin(pi x)^2 sin(pi y)^2 / pi) in module ``m`` (sympy or ufl): zero on the boundary."""
    return (2 * m.sin(m.pi * x) ** 2 * m.sin(m.pi * y) * m.cos(m.pi * y),
            -2 * m.sin(m.pi * x) * m.cos(m.pi * x) * m.sin(m.pi * y) ** 2)


def divergence_free(x, y, m):
    """curl(sin(pi x) cos(pi y) / pi) in module ``m`` (sympy or ufl)."""
    return (-m.sin(m.pi * x) * m.sin(m.pi * y), -m.cos(m.pi * x) * m.cos(m.pi * y))


def compressible(x, y, m):
    """A displacement with div u != 0 (so p = lmbda div u != 0), zero on the unit square's boundary."""
    return (m.sin(m.pi * x) * m.sin(m.pi * y), x * y * (1 - x) * (1 - y))


def nu_of_ratio(ratio: float) -> float:
    """The Poisson ratio with lmbda / mu = 2 nu / (1 - 2 nu) = ratio."""
    return ratio / (2 * (1 + ratio))


def as_numpy(components):
    fns = [sympy.lambdify((X, Y), c, "numpy") for c in components]
    return lambda x: np.stack([fn(x[0], x[1]) + 0.0 * x[0] for fn in fns])


def load(exact, nu: float, E: float = 1.0):
    """The body force f = -div sigma(u) of the displacement ``exact``, as a callable x -> (2, N)."""
    u = exact(X, Y, sympy)
    mu, lmbda = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    div = sympy.simplify(sympy.diff(u[0], X) + sympy.diff(u[1], Y))
    eps = [[(sympy.diff(u[i], v) + sympy.diff(u[j], w)) / 2 for j, v in enumerate((X, Y))]
           for i, w in enumerate((X, Y))]
    sigma = [[2 * mu * eps[i][j] + (lmbda * div if i == j else 0) for j in range(2)] for i in range(2)]
    return as_numpy([-(sympy.diff(sigma[i][0], X) + sympy.diff(sigma[i][1], Y)) for i in range(2)])


def square(n: int):
    return dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, n, n)


def solve(n: int, nu: float, exact, **kw):
    """(problem, output values) of the manufactured problem on the n x n unit square, by LU."""
    f = load(exact, nu)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")                 # the locking warning: measured here on purpose
        prob = forms.elasticity.problem(square(n), nu=nu, g=as_numpy(exact(X, Y, sympy)), **kw)
    return prob, SolveLayer(prob, "lu")(f=torch.as_tensor(prob.interpolate(f, "f"))).numpy()


def relative_l2(fn, exact) -> float:
    comm = fn.function_space.mesh.comm
    error = fn - exact

    def norm(e):
        return np.sqrt(integral(_dolfinx.compile_form(ufl.inner(e, e) * ufl.dx(degree=8)), comm))
    return norm(error) / norm(exact)


def displacement_error(n: int, nu: float, exact, **kw) -> float:
    prob, values = solve(n, nu, exact, **kw)
    uh = prob.to_function(values, "u") if prob.fields else prob.to_function(values)
    x = ufl.SpatialCoordinate(uh.function_space.mesh)
    return relative_l2(uh, ufl.as_vector(exact(x[0], x[1], ufl)))


# ------------------------------------------------------------------ the warning
@pytest.mark.parametrize("nu, degree", [(0.4999, 1), (0.4999, 2), (nu_of_ratio(1.01 * LOCKING_LAME_RATIO), 1)])
def test_displacement_form_warns_where_it_locks(nu, degree):
    with pytest.warns(UserWarning, match=r'nu=.* lmbda/mu=.*displacement-only P\d locks.*formulation="mixed"'):
        forms.elasticity.problem(square(2), nu=nu, degree=degree)


@pytest.mark.parametrize("nu, formulation", [(0.3, "displacement"),
                                             (nu_of_ratio(0.99 * LOCKING_LAME_RATIO), "displacement"),
                                             (0.4999, "mixed")])
def test_no_warning_away_from_locking_or_with_the_mixed_form(nu, formulation):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        forms.elasticity.problem(square(2), nu=nu, formulation=formulation)


# ------------------------------------------------------------------ accuracy
def test_mixed_form_is_locking_free_where_p1_locks():
    n = 8
    mixed = {nu: displacement_error(n, nu, clamped, formulation="mixed") for nu in (0.3, 0.4999, 0.499999)}
    p1 = {nu: displacement_error(n, nu, clamped) for nu in (0.3, 0.4999)}
    assert mixed[0.4999] <= 2 * mixed[0.3] and mixed[0.499999] <= 2 * mixed[0.3], mixed
    # Without the mixed form the displacement locks: P1 loses nearly all of it (measured 0.99 against 0.23).
    assert p1[0.4999] > 3 * p1[0.3] and p1[0.4999] > 0.5, p1
    assert p1[0.4999] > 50 * mixed[0.4999], (p1, mixed)


def test_warning_threshold_is_where_p1_error_doubles():
    """The rule behind LOCKING_LAME_RATIO, re-measured: P1's error ratio to nu = 0.3 crosses 2 between
    half and twice the threshold."""
    errors = {ratio: displacement_error(16, nu_of_ratio(ratio), clamped) for ratio in
              (1.5, LOCKING_LAME_RATIO / 2, 2 * LOCKING_LAME_RATIO)}      # 1.5: nu = 0.3
    assert errors[LOCKING_LAME_RATIO / 2] < 2 * errors[1.5] < errors[2 * LOCKING_LAME_RATIO], errors


def test_mixed_form_converges_at_taylor_hood_rate_near_incompressibility():
    errors = np.array([displacement_error(n, 0.4999, divergence_free, formulation="mixed") for n in (4, 8, 16)])
    rates = np.log2(errors[:-1] / errors[1:])
    assert np.all(np.abs(rates - 3.0) < 0.3), (errors, rates)     # L2 of P2: h^3


def test_mixed_pressure_is_the_solid_pressure():
    """p = lmbda div u, for a displacement that is not divergence-free (compressible, nu = 0.3)."""
    nu = 0.3
    prob, values = solve(16, nu, compressible, formulation="mixed")
    parts = prob.split(values)
    assert set(parts) == {"u", "p"} and len(parts["u"]) == prob.control_size("f")
    assert len(parts["u"]) + len(parts["p"]) == prob.output_size
    ph = prob.to_function(parts["p"], "p")
    x = ufl.SpatialCoordinate(ph.function_space.mesh)
    lmbda = nu / ((1 + nu) * (1 - 2 * nu))
    assert relative_l2(ph, lmbda * ufl.div(ufl.as_vector(compressible(x[0], x[1], ufl)))) < 1e-2


# ------------------------------------------------------------------ gradients
@pytest.mark.parametrize("nu", [0.3, 0.4999])
def test_mixed_gradients_for_body_force_and_youngs_modulus_are_exact(nu):
    prob = forms.elasticity.problem(square(2), controls=("f", "E"), nu=nu, formulation="mixed")
    layer = SolveLayer(prob, "lu")
    g = torch.Generator().manual_seed(0)
    f = torch.rand(prob.control_size("f"), dtype=F64, generator=g).requires_grad_()
    E = (1.0 + torch.rand(prob.control_size("E"), dtype=F64, generator=g)).requires_grad_()
    # The whole (u, p) output, so the pressure's dependence on E (through 1 / lmbda) is checked too.
    assert torch.autograd.gradcheck(lambda f, E: layer(f=f, E=E), (f, E))


# ------------------------------------------------------------------ incompressible limit and refusals
def test_mixed_form_takes_nu_one_half_with_a_free_boundary_part():
    msh = mesh.load("lshape", h=0.4)
    f = (0.3, -1.0)
    values = {}
    for nu in (0.5, 0.4999999):
        with warnings.catch_warnings():
            warnings.simplefilter("error")                       # no locking warning either
            prob = forms.elasticity.problem(msh, nu=nu, f=f, formulation="mixed", dirichlet="outer")
        values[nu] = SolveLayer(prob, "lu")(f=torch.as_tensor(prob.interpolate(
            lambda x: np.stack([0.3 + 0 * x[0], -1 + 0 * x[0]]), "f")))
    u = {nu: prob.split(v)["u"] for nu, v in values.items()}
    assert torch.all(torch.isfinite(values[0.5]))
    assert (u[0.5] - u[0.4999999]).norm() <= 1e-4 * u[0.5].norm()        # the limit is continuous


def test_bad_mixed_parameters_are_refused():
    msh = square(2)
    with pytest.raises(ValueError, match=r"formulation must be one of \['displacement', 'mixed'\]"):
        forms.elasticity.problem(msh, formulation="u-p")
    with pytest.raises(ValueError, match=r"needs degree >= 2 \(Taylor-Hood"):
        forms.elasticity.problem(msh, formulation="mixed", degree=1)
    with pytest.raises(ValueError, match=r"in \(0, 0.5\] for formulation='mixed'"):
        forms.elasticity.problem(msh, formulation="mixed", nu=0.0)
    with pytest.raises(ValueError, match="determines the pressure only up to a constant"):
        forms.elasticity.problem(msh, formulation="mixed", nu=0.5)
    with pytest.raises(ValueError, match=r"formulation='mixed' takes nu up to 0.5"):
        forms.elasticity.problem(msh, nu=0.5)
    prob = forms.elasticity.problem(msh, formulation="mixed")
    assert "nu" in prob.positive and len(prob.near_nullspace) == 0 and prob.symmetric
