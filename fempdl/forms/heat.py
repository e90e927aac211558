"""One theta-step of the heat equation du/dt - div(kappa grad u) = f.

With step dt and theta in [0, 1] (1 = implicit Euler, the default; 1/2 =
Crank-Nicolson), the step u0 -> u1 solves

    (M + theta dt K(kappa)) u1 = (M - (1 - theta) dt K(kappa)) u0 + dt M f,

with u1 = g on Gamma_D (the whole boundary by default). Weak form: find u1 in
V_g such that for all v in V_0

    ∫ u1 v + theta dt kappa ∇u1·∇v dx = ∫ u0 v - (1 - theta) dt kappa ∇u0·∇v + dt f v dx.

Controls: ``"u0"`` and ``"f"`` (both in the solution space V, so a step's output
feeds the next step's ``u0``) and ``"kappa"`` (P1 or DG0). f always enters the
right-hand side affinely (one sparse product per sample), and so does u0
unless kappa is a control and theta < 1 (then the u0 term depends on kappa).
kappa enters the matrix for theta > 0 and the right-hand side for theta < 1.
``dt`` is a ``fem.Constant`` (``problem.constants["dt"].value``) so it can change without
recompiling.
"""
from __future__ import annotations

import math

import ufl

from fempdl.core import _dolfinx
from fempdl.core.checks import is_real
from fempdl.core.mesh import as_tagged
from fempdl.core.problem import Problem
from fempdl.forms._common import (
    check_controls,
    check_degree,
    coefficient_space,
    dirichlet_bcs,
    fixed_constants,
    make_coefficient,
    make_function,
    positive_constant,
)

CONTROLS = ("u0", "f", "kappa")


def problem(msh, controls=("u0",), *, dt: float = 0.01, theta: float = 1.0, degree: int = 1,
            kappa_space: str = "P1", u0=0.0, f=0.0, kappa=1.0, g=0.0, dirichlet=None) -> Problem:
    """Build one heat step on ``msh``.

    Args:
        msh: a :class:`fempdl.core.mesh.TaggedMesh` or a dolfinx Mesh.
        controls: names among ``("u0", "f", "kappa")`` that become layer inputs.
        dt: time step (> 0).
        theta: 1 implicit Euler, 0.5 Crank-Nicolson, 0 explicit Euler (a mass solve).
        degree: Lagrange degree of the solution space.
        kappa_space: ``"P1"`` or ``"DG0"``.
        u0, f, kappa, g: fixed values (float or callable x -> values).
        dirichlet: ``None`` (whole boundary), facet tags, or ``()`` for none
            (zero-flux boundary; the mass matrix keeps the step well posed).

    Returns:
        A :class:`fempdl.Problem`; ``problem.constants["dt"]`` is the step Constant.
    """
    controls = check_controls(controls, CONTROLS, "heat")
    tagged = as_tagged(msh)
    if not is_real(theta) or not (0.0 <= theta <= 1.0) or not math.isfinite(theta):
        raise ValueError(f"theta must be in [0, 1], got {theta!r}")
    theta = float(theta)        # a numpy scalar times a UFL form would be numpy's product, not UFL's
    degree = check_degree(degree)
    msh_ = tagged.mesh
    V = _dolfinx.function_space(msh_, "Lagrange", degree)
    dt_c = positive_constant(msh_, dt, "dt")
    u0_fn = make_function(V, u0, "u0")
    f_fn = make_function(V, f, "f")
    kappa_fn = make_coefficient(coefficient_space(msh_, kappa_space), kappa, "kappa", control="kappa" in controls,
                                positive=True)
    bcs = dirichlet_bcs(tagged, V, g, dirichlet)

    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    # Terms with a zero factor are left out rather than multiplied by 0 (UFL
    # collapses 0*form), which also keeps u0 an affine right-hand-side control for theta = 1.
    a = u * v * ufl.dx
    if theta > 0:
        a = a + theta * dt_c * kappa_fn * ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx
    L = u0_fn * v * ufl.dx + dt_c * f_fn * v * ufl.dx
    if theta < 1:
        L = L - (1.0 - theta) * dt_c * kappa_fn * ufl.inner(ufl.grad(u0_fn), ufl.grad(v)) * ufl.dx
    fns = {"u0": u0_fn, "f": f_fn, "kappa": kappa_fn}
    fixed = fixed_constants(fns, ("kappa",))
    return Problem(a, L, bcs, controls={name: fns[name] for name in controls}, constants={"dt": dt_c, **fixed},
                   symmetric=True, positive={"kappa"} & set(controls) | {"dt"} | set(fixed))
