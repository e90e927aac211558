"""Nonlinear diffusion: -div(q(u) grad u) = f, steady or one backward-Euler step, solved by Newton.

Strong form: -div(kappa q(u) grad u) = f in Omega (steady), or with a time step dt
(u - u0) / dt - div(kappa q(u) grad u) = f (one implicit step of nonlinear heat
conduction from the state u0); u = g on Gamma_D (the whole boundary by default),
q(u) grad u . n = 0 on the rest. The conductivity is q(u) = 1 + alpha u^2 unless
a UFL function ``q`` of u is given (then ``alpha`` is not used).

Residual: find u in V_g = {u in P_k : u = g on Gamma_D} such that for all v in V_0

    F(u, v) = ∫ kappa q(u) ∇u·∇v dx - ∫ f v dx  [+ ∫ (u - u0) v / dt dx]  = 0.

Controls: ``"f"`` (the source, in V), ``"kappa"`` (a field scaling q, P1 or DG0),
``"alpha"`` (the coefficient inside the nonlinearity, P1 or DG0), and, for a time
step, ``"u0"`` (the previous state, in V). The Jacobian is ufl.derivative(F, u).
"""
from __future__ import annotations

import dolfinx.fem
import ufl

from fempdl.core import _dolfinx
from fempdl.core.mesh import as_tagged
from fempdl.core.nonlinear_problem import NonlinearProblem
from fempdl.forms._common import (
    check_controls,
    check_degree,
    coefficient_space,
    dirichlet_bcs,
    fixed_constants,
    make_coefficient,
    make_function,
    positive_constant,
    ufl_law,
)

CONTROLS = ("f", "kappa", "alpha", "u0")


def problem(msh, controls=("f",), *, degree: int = 1, q=None, kappa=1.0, kappa_space: str = "P1", alpha=1.0,
            alpha_space: str = "P1", f=1.0, g=0.0, dirichlet=None, dt: float | None = None,
            u0=0.0) -> NonlinearProblem:
    """Build the nonlinear diffusion problem on ``msh``.

    Args:
        msh: a :class:`fempdl.core.mesh.TaggedMesh` or a dolfinx Mesh.
        controls: names among ``("f", "kappa", "alpha", "u0")`` that become layer inputs
            (``"u0"`` only with ``dt``).
        degree: Lagrange degree k of u (and of f and u0).
        q: a function of the UFL unknown returning the conductivity (e.g.
            ``lambda u: 1 + u**4``); default ``1 + alpha u^2``. Torch code here is refused in one
            line (a form is compiled to C once): a trainable law is UFL with controls as parameters.
        kappa, alpha: fixed values (float or callable x -> values) of the fields,
            in ``kappa_space`` / ``alpha_space`` (``"P1"`` or ``"DG0"``); kappa > 0.
        f, g: the source and the Dirichlet data (float or callable).
        dirichlet: ``None`` (whole boundary) or facet tags (names or ints).
        dt: ``None`` for the steady problem, else the time step (> 0) of one
            backward-Euler step from ``u0`` (a float or callable, or the control ``"u0"``).

    Returns:
        A :class:`fempdl.NonlinearProblem`; with ``dt``, ``problem.constants`` holds ``"dt"``.
    """
    controls = check_controls(controls, CONTROLS, "nonlinear_diffusion")
    if "u0" in controls and dt is None:
        raise ValueError("nonlinear_diffusion: control 'u0' is the previous state of a time step; give dt")
    if q is not None and "alpha" in controls:
        raise ValueError("nonlinear_diffusion: 'alpha' is the coefficient of the default q(u) = 1 + alpha u^2; "
                         "with a user-given q it is not used")
    if q is not None and not callable(q):
        raise TypeError(f"q must be a function of the unknown (u -> UFL expression), got {type(q).__name__}")
    tagged = as_tagged(msh)
    degree = check_degree(degree)
    V = _dolfinx.function_space(tagged.mesh, "Lagrange", degree)
    fns = {"f": make_function(V, f, "f"),
           "kappa": make_coefficient(coefficient_space(tagged.mesh, kappa_space), kappa, "kappa",
                                     control="kappa" in controls, positive=True),
           "alpha": make_coefficient(coefficient_space(tagged.mesh, alpha_space), alpha, "alpha",
                                     control="alpha" in controls)}
    bcs = dirichlet_bcs(tagged, V, g, dirichlet)
    if not bcs and dt is None:
        raise ValueError("nonlinear_diffusion: dirichlet=() leaves the steady u determined only up to a constant; "
                         "give at least one Dirichlet boundary part")
    u = dolfinx.fem.Function(V, name="u")
    v = ufl.TestFunction(V)
    conductivity = (1 + fns["alpha"] * u ** 2) if q is None else ufl_law(q, u, "q")
    F = fns["kappa"] * conductivity * ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx - fns["f"] * v * ufl.dx
    constants = fixed_constants(fns, ("kappa",))
    if dt is not None:
        dt_c = positive_constant(tagged.mesh, dt, "dt")
        fns["u0"] = make_function(V, u0, "u0")
        F = F + (u - fns["u0"]) * v / dt_c * ufl.dx
        constants["dt"] = dt_c
    return NonlinearProblem(F, u, bcs, controls={name: fns[name] for name in controls}, constants=constants,
                            positive={"kappa"} & set(controls) | set(constants))
